"""Oracle mode: the scene rendered straight through a fisheye camera, and the error of the
cube -> fisheye pipeline measured against it."""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from .._constants import FAR_DEPTH_M
from ..calibration import Calibration
from ..reprojection import CubeRig, build_lut, resample_bilinear, resample_depth, resample_nearest, supersample_offsets
from ..transforms import Pose
from ._caster import DEFAULT_CHUNK, render_pixels
from ._model import StreetFrame

_F32 = jnp.float32


class FisheyeOracle(eqx.Module):
    """Exact per-pixel ground truth of one fisheye camera at t, rendered ray by ray.

    - `rgb` ``(H, W, 3)`` linear RGB in [0, 1], the mean over the ``supersample²`` sub-pixel rays;
    - from the pixel-centre ray: `valid` (the lens has a ray), `hit`, `range_m` (Euclidean range
      along the ray, 1000 for sky), `depth_m` (planar z in the fisheye camera frame), `semantic`
      (CARLA 0.9.10 tag), `actor_id`, `object_index`, `point_world` (CARLA world, metres);
    - `motion_px` ``(H, W, 2)``: ``uv(t) - uv(t-1)`` of the surface point seen at each pixel, i.e.
      where it was in the same camera at t-1 is ``uv - motion_px`` (objects move with their
      actors, the camera with the ego); `motion_valid` is False where that point had no image at
      t-1 (behind the lens' domain). Sky points are taken at 1000 m.
    """

    rgb: Float[Array, "H W 3"]
    valid: Bool[Array, "H W"]
    hit: Bool[Array, "H W"]
    range_m: Float[Array, "H W"]
    depth_m: Float[Array, "H W"]
    semantic: Int[Array, "H W"]
    actor_id: Int[Array, "H W"]
    object_index: Int[Array, "H W"]
    point_world: Float[Array, "H W 3"]
    motion_px: Float[Array, "H W 2"]
    motion_valid: Bool[Array, "H W"]


def render_fisheye(frame: StreetFrame, calib: Calibration, *, supersample: int = 1, chunk_size: int = DEFAULT_CHUNK) -> FisheyeOracle:
    """Render ``calib``'s fisheye directly (its own per-pixel rays) at t: the exact oracle."""
    scene = frame.scene
    cam = calib.camera.astype(_F32)
    mount = Pose(calib.camera_to_vehicle.rotation_matrix, calib.camera_to_vehicle.translation, dtype=_F32)
    pose_t = scene.camera_to_world(mount, 1.0)
    pose_prev = scene.camera_to_world(mount, 0.0)
    grid = cam.pixel_grid(_F32)
    b = render_pixels(scene, cam, pose_t, grid, time=1.0, chunk_size=chunk_size)
    rgb = b.rgb
    n = int(supersample)
    if n > 1:
        acc = jnp.zeros_like(rgb)
        cnt = jnp.zeros(rgb.shape[:-1], _F32)
        for off in supersample_offsets(n):
            s = render_pixels(scene, cam, pose_t, grid + jnp.asarray(off, _F32), time=1.0, chunk_size=chunk_size)
            acc = acc + jnp.where(s.valid[..., None], s.rgb, 0.0)
            cnt = cnt + s.valid.astype(_F32)
        rgb = jnp.where((cnt > 0)[..., None], acc / jnp.maximum(cnt, 1.0)[..., None], rgb)
    motion, motion_valid = _motion(scene, cam, pose_prev, grid, b.point_world, b.object_index, b.valid)
    return FisheyeOracle(
        rgb=rgb, valid=b.valid, hit=b.hit, range_m=b.range_m, depth_m=b.depth_m, semantic=b.semantic,
        actor_id=b.actor_id, object_index=b.object_index, point_world=b.point_world,
        motion_px=motion, motion_valid=motion_valid,
    )


@eqx.filter_jit
def _motion(scene, cam, pose_prev: Pose, grid, point_t, object_index, valid):
    p_prev = scene.move_points(object_index, point_t, 1.0, 0.0)
    p_cam = pose_prev.inverse().apply(p_prev)
    uv_prev, ok = cam.project(p_cam)
    ok = ok & valid
    return jnp.where(ok[..., None], grid - uv_prev, 0.0), ok


@dataclasses.dataclass(frozen=True)
class OracleErrors:
    """Errors of a cube -> fisheye reconstruction against the oracle, over the pixels both see
    (``pixels``): depth relative error of the range on pixels that hit geometry in both (mean,
    median, 95th percentile, and the fraction above 5 %), semantic label agreement (fraction of equal
    tags), instance agreement (equal actor ids), and RGB PSNR (dB, on [0, 1] linear RGB)."""

    pixels: int
    depth_rel_mean: float
    depth_rel_median: float
    depth_rel_p95: float
    depth_rel_over_5pct: float
    label_agreement: float
    instance_agreement: float
    rgb_psnr_db: float

    def as_dict(self) -> dict[str, float]:
        """The numbers as a plain dict (for JSON reports)."""
        return dataclasses.asdict(self)


def compare_to_oracle(rgb, range_m, semantic, actor_id, valid, oracle: FisheyeOracle) -> OracleErrors:
    """Errors of fisheye buffers (``rgb`` in [0, 1], ``range_m``, ``semantic``, ``actor_id``,
    ``valid``) against `FisheyeOracle` (see `OracleErrors`)."""
    v = np.asarray(valid) & np.asarray(oracle.valid)
    o_rng = np.asarray(oracle.range_m, np.float64)
    p_rng = np.asarray(range_m, np.float64)
    both_hit = v & (o_rng < FAR_DEPTH_M) & (p_rng < FAR_DEPTH_M)
    rel = np.abs(p_rng - o_rng)[both_hit] / o_rng[both_hit]
    lab = np.asarray(semantic)[v] == np.asarray(oracle.semantic)[v]
    inst = np.asarray(actor_id)[v] == np.asarray(oracle.actor_id)[v]
    diff = (np.asarray(rgb, np.float64) - np.asarray(oracle.rgb, np.float64))[v]
    mse = float(np.mean(diff * diff)) if diff.size else 0.0
    psnr = float(10 * np.log10(1.0 / mse)) if mse > 0 else float("inf")
    q = lambda f, x: float(f(x)) if x.size else 0.0  # noqa: E731
    return OracleErrors(
        pixels=int(v.sum()),
        depth_rel_mean=q(np.mean, rel), depth_rel_median=q(np.median, rel),
        depth_rel_p95=q(lambda x: np.percentile(x, 95), rel), depth_rel_over_5pct=q(lambda x: np.mean(x > 0.05), rel),
        label_agreement=q(np.mean, lab), instance_agreement=q(np.mean, inst), rgb_psnr_db=psnr,
    )


def cube_to_fisheye(faces_rgb, faces_depth, faces_semantic, faces_actor, calib: Calibration, face_size: int, *, supersample: int = 1):
    """The cube -> fisheye pipeline of `jaxfish.reprojection` on one camera's faces at t: faces
    ``(F, S, S, ...)`` in the `CubeRig` order; RGB bilinear (uint8 in, [0, 1] out) averaged over
    ``supersample²`` sub-pixel samples, depth through `resample_depth` (planar -> range), labels and
    ids nearest — the geometric buffers at the pixel centre, like the oracle's. Returns
    ``(rgb, range_m, semantic, actor_id, valid)``."""
    rig = CubeRig(face_size, dtype=_F32)
    make = jax.jit(build_lut, static_argnames=("supersample",))
    cam = calib.camera.astype(_F32)
    lut = make(rig, cam, supersample=1)
    lut_rgb = make(rig, cam, supersample=supersample) if supersample > 1 else lut
    rgb, valid = resample_bilinear(jnp.asarray(faces_rgb), lut_rgb)
    rng, _ = resample_depth(jnp.asarray(faces_depth, _F32), lut)
    sem, _ = resample_nearest(jnp.asarray(faces_semantic), lut)
    act, _ = resample_nearest(jnp.asarray(faces_actor), lut)
    return np.asarray(rgb, np.float32) / 255.0, np.asarray(rng), np.asarray(sem), np.asarray(act), np.asarray(valid)


def oracle_errors(frame: StreetFrame, calib: Calibration, face_size: int, *, supersample: int = 1,
                  chunk_size: int = DEFAULT_CHUNK) -> OracleErrors:
    """Render one camera's cube faces at t, run the cube -> fisheye pipeline, render the oracle,
    and return the pipeline's errors. The faces come from the same renderer as the oracle (no
    quantisation other than the uint8 RGB CARLA stores), so the error is the pipeline's alone."""
    from ._sensors import render_cube_faces, to_uint8

    faces = render_cube_faces(frame, calib, face_size, time=1.0, chunk_size=chunk_size)
    names = list(faces)
    stack = lambda f: np.stack([f(faces[n]) for n in names])  # noqa: E731
    rgb, rng, sem, act, valid = cube_to_fisheye(
        stack(lambda b: to_uint8(b.rgb)), stack(lambda b: np.asarray(b.depth_m)),
        stack(lambda b: np.asarray(b.semantic, np.int32)), stack(lambda b: np.asarray(b.actor_id)),
        calib, face_size, supersample=supersample,
    )
    oracle = render_fisheye(frame, calib, supersample=supersample, chunk_size=chunk_size)
    return compare_to_oracle(rgb, rng, sem, act, valid, oracle)
