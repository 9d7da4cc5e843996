"""Multi-camera fusion: fisheye range + semantic maps -> 3D points -> vehicle frame -> the top-view
grid, with a scatter-max z-buffer (the highest point of a cell wins, as a camera looking down
would see it)."""

from __future__ import annotations

import functools
from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from .._constants import FAR_DEPTH_M
from .._numerics import materialize
from ..cameras import AbstractCamera, Orthographic
from ..transforms import Pose
from ._cameras import rig_rays, stack_cameras, stack_poses
from ._grid import OCCUPANCY_MIN_HEIGHT_M, bev_ground_points, check_looks_down

HEIGHT_QUANTUM_M = 1e-3
"""Heights are stored in the fusion z-buffer in steps of this many metres (1 mm)."""
MIN_HEIGHT_M = -100.0
"""Lowest height the fusion keeps (metres, vehicle frame); lower points are clipped to it."""
MAX_CLASSES = 64
"""Class ids must be below this to be fused (the z-buffer packs the class in the low bits)."""
UNOBSERVED = -1
"""Label of a BEV cell no point landed in (fusion) or no camera sees (IPM)."""

_F32 = jnp.float32
_Q0 = round(-MIN_HEIGHT_M / HEIGHT_QUANTUM_M)  # z-buffer level of height 0


class BevFusion(eqx.Module):
    """A top view fused from cameras: per cell the `height_m` of the highest point (metres above
    the ground; 0 where unobserved) and its `semantic` class (`UNOBSERVED` = -1 where no point
    landed), `observed` (at least one point) and `occupancy` (observed and higher than the
    occupancy threshold)."""

    height_m: Float[Array, "*batch H W"]
    semantic: Int[Array, "*batch H W"]
    observed: Bool[Array, "*batch H W"]
    occupancy: Bool[Array, "*batch H W"]


def _camera_to_bev_rows(cameras_to_vehicle: Pose, bev_camera: Orthographic, bev_to_vehicle: Pose) -> Array:
    """Per camera a (3, 4) matrix: rows giving BEV u, BEV v and vehicle z of a camera-frame point."""
    inv = Pose(bev_to_vehicle.rotation_matrix, bev_to_vehicle.translation, dtype=_F32).inverse()
    r, t = cameras_to_vehicle.rotation_matrix, cameras_to_vehicle.translation  # (N, 3, 3), (N, 3)
    rb = jnp.einsum("ij,njk->nik", inv.rotation_matrix, r)
    tb = jnp.einsum("ij,nj->ni", inv.rotation_matrix, t) + inv.translation
    m = bev_camera.metres_per_pixel.astype(_F32)
    row_u = jnp.concatenate([rb[:, 0] / m, (tb[:, 0] / m + bev_camera.cx.astype(_F32))[:, None]], -1)
    row_v = jnp.concatenate([rb[:, 1] / m, (tb[:, 1] / m + bev_camera.cy.astype(_F32))[:, None]], -1)
    row_z = jnp.concatenate([r[:, 2], t[:, 2:3]], -1)
    return jnp.stack([row_u, row_v, row_z], axis=1)


def _keys_and_cells(rows, rays, ok, range_m, semantic, valid, width, height, far_m):
    """Packed z-buffer keys and flat cell indices of one camera's pixels (dropped: index H*W)."""
    p = rays * range_m[..., None]
    x, y, z = p[..., 0], p[..., 1], p[..., 2]
    u = rows[0, 0] * x + rows[0, 1] * y + rows[0, 2] * z + rows[0, 3]
    v = rows[1, 0] * x + rows[1, 1] * y + rows[1, 2] * z + rows[1, 3]
    h = rows[2, 0] * x + rows[2, 1] * y + rows[2, 2] * z + rows[2, 3]
    iu = jnp.floor(u + 0.5)
    iv = jnp.floor(v + 0.5)
    keep = (ok & valid & (range_m > 0) & (range_m < far_m) & (semantic >= 0) & (semantic < MAX_CLASSES)
            & (iu >= 0) & (iu < width) & (iv >= 0) & (iv < height))
    cell = jnp.where(keep, iv.astype(jnp.int32) * width + iu.astype(jnp.int32), width * height)
    q = jnp.clip(jnp.round(h / HEIGHT_QUANTUM_M) + _Q0, 0, (2**31 - 1) // MAX_CLASSES - 1).astype(jnp.int32)
    return q * MAX_CLASSES + jnp.clip(semantic, 0, MAX_CLASSES - 1).astype(jnp.int32), cell


def fuse_cameras(
    cameras: AbstractCamera | Sequence[AbstractCamera],
    cameras_to_vehicle: Pose | Sequence[Pose],
    range_m: Float[ArrayLike, "N H W"],
    semantic: Int[ArrayLike, "N H W"],
    bev_camera: Orthographic,
    bev_camera_to_vehicle: Pose,
    *,
    valid: Bool[ArrayLike, "N H W"] | None = None,
    rays: tuple[Float[ArrayLike, "N H W 3"], Bool[ArrayLike, "N H W"]] | None = None,
    far_m: float = FAR_DEPTH_M,
    occupancy_min_height_m: float = OCCUPANCY_MIN_HEIGHT_M,
) -> BevFusion:
    """Fuse N cameras' range and semantic maps into the top view of ``bev_camera`` (mounted by
    ``bev_camera_to_vehicle``; looking straight down, checked when the pose is concrete).

    Every pixel with a valid ray, ``0 < range < far_m`` and a class in ``[0, MAX_CLASSES)`` becomes
    the 3D point ``range * ray`` (camera frame), moved to the vehicle frame by its
    ``cameras_to_vehicle`` pose and dropped into the BEV cell below it. Per cell **the highest
    point wins** (one scatter-max over all cameras' pixels of a key packing the height, quantised
    to `HEIGHT_QUANTUM_M`, above the class): the cell's height and class are those of that point,
    which is what a camera looking down would see; equal heights go to the larger class id.
    ``cameras`` (one model and image size) and ``cameras_to_vehicle`` are sequences or already
    stacked (`stack_cameras`); ``rays`` are `rig_rays` precomputed (one Newton solve per pixel
    saved); ``valid`` masks pixels out. The result is sparse where the cameras' pixels are coarser
    than the grid (distant cells); `fuse_cameras_dense` fills every cell a camera sees. Pure,
    jittable, float32."""
    cam = stack_cameras(cameras)
    poses = stack_poses(cameras_to_vehicle)
    r = jnp.asarray(range_m, _F32)
    sem = jnp.asarray(semantic)
    n = poses.rotation_matrix.shape[0]
    if r.ndim != 3 or r.shape[0] != n:
        raise ValueError(f"fuse_cameras: range_m must be (N={n}, H, W), got {r.shape}")
    if sem.shape != r.shape or not jnp.issubdtype(sem.dtype, jnp.integer):
        raise ValueError(f"fuse_cameras: semantic must be integer {r.shape}, got {sem.dtype} {sem.shape}")
    if (cam.height, cam.width) != r.shape[1:]:
        raise ValueError(f"fuse_cameras: range maps {r.shape[1:]} do not match the cameras' images {(cam.height, cam.width)}")
    check_looks_down(bev_camera_to_vehicle, "fuse_cameras: bev_camera_to_vehicle")
    ok_valid = jnp.ones(r.shape, bool) if valid is None else jnp.asarray(valid, bool)
    if ok_valid.shape != r.shape:
        raise ValueError(f"fuse_cameras: valid must be {r.shape}, got {ok_valid.shape}")
    ray, ok = rig_rays(cam) if rays is None else (jnp.asarray(rays[0], _F32), jnp.asarray(rays[1], bool))
    if ray.shape != r.shape + (3,) or ok.shape != r.shape:
        raise ValueError(f"fuse_cameras: rays must be ({r.shape + (3,)}, {r.shape}), got ({ray.shape}, {ok.shape})")
    return _fuse(poses, ray, ok, r, sem.astype(jnp.int32), ok_valid, bev_camera, bev_camera_to_vehicle, float(far_m),
                 float(occupancy_min_height_m))


@functools.partial(jax.jit, static_argnums=(8, 9))
def _fuse(poses, ray, ok, r, sem, ok_valid, bev_camera, bev_camera_to_vehicle, far_m, occupancy_min_height_m):
    # compiled once per shape: eager callers run one kernel instead of dispatching op by op
    w, h = bev_camera.width, bev_camera.height
    rows = _camera_to_bev_rows(poses, bev_camera, bev_camera_to_vehicle)
    keys, cells = jax.vmap(_keys_and_cells, in_axes=(0, 0, 0, 0, 0, 0, None, None, None))(
        rows, ray, ok, r, sem, ok_valid, w, h, far_m)
    # computed once into buffers: XLA on CPU would otherwise fuse them into the (serial) scatter
    keys, cells = materialize((keys, cells), r[0, 0, 0])
    buf = jnp.full((h * w,), jnp.iinfo(jnp.int32).min, jnp.int32)
    buf = buf.at[cells.reshape(-1)].max(keys.reshape(-1), mode="drop").reshape(h, w)
    observed = buf >= 0
    height = jnp.where(observed, (buf // MAX_CLASSES - _Q0).astype(_F32) * HEIGHT_QUANTUM_M, 0.0)
    cls = jnp.where(observed, buf % MAX_CLASSES, UNOBSERVED)
    return BevFusion(height_m=height, semantic=cls, observed=observed,
                     occupancy=observed & (height > occupancy_min_height_m))


GATHER_FILL_RADIUS = 2
"""`fuse_cameras_dense` draws its raised height hypotheses from the splat's observed heights within
this many cells of each cell (a (2R+1) x (2R+1) window)."""
GATHER_RANGE_TOLERANCE = 0.03
"""`fuse_cameras_dense`'s depth-consistency test along the line of sight: the pixel's range may
differ from the cell point's by this fraction of that range (plus the cell's half diagonal)."""
GATHER_HEIGHT_TOLERANCE_M = 0.01
"""Absolute part of `fuse_cameras_dense`'s test on a horizontal plane (metres)."""
GATHER_HEIGHT_TOLERANCE_RAD = 0.001
"""`fuse_cameras_dense`'s depth-consistency test on a horizontal plane: the height of the point a
pixel sees may differ from the hypothesis height by this angle (radians) times the range, plus
`GATHER_HEIGHT_TOLERANCE_M`. It bounds the angular error of the range map: about half a pixel of
the coarsest image the ranges were resampled from (range maps rendered per fisheye pixel: float
error only, the default leaves slack for gentle slopes; resampled from 256-pixel cube faces:
3 mrad, see ``jaxfish bev``). Every milliradian widens the band behind a face standing on the
ground that takes the face's class by ``1 mrad * r^2 / H`` (``r`` range, ``H`` camera height)."""

_NO_HEIGHT = -1.0e30  # an absent height hypothesis


def _gather_one(cam, rotation, translation, ray, labels, rng, points, hyp_ok, tol_abs, tol_rel, tol_angle):
    """One camera's verdict on the hypothesis points ``(H, W, 3)`` (vehicle frame): consistent,
    class read, range from the camera to the point."""
    p = jnp.einsum("ji,...j->...i", rotation, points - translation)  # R^T (P - t): camera frame
    # computed once into buffers: XLA on CPU otherwise repeats the projection in its consumers
    uv, ok = materialize(cam.project(p), p[0, 0, 0])
    ok = ok & hyp_ok & cam.contains(uv)
    h, w = rng.shape
    uv = jnp.where(ok[..., None], uv, 0.0)
    iu = jnp.clip(jnp.floor(uv[..., 0] + 0.5).astype(jnp.int32), 0, w - 1)
    iv = jnp.clip(jnp.floor(uv[..., 1] + 0.5).astype(jnp.int32), 0, h - 1)
    flat = iv * w + iu
    lab = jnp.take(labels.reshape(-1), flat)  # -1 where the pixel has no usable observation
    r_pix = jnp.take(rng.reshape(-1), flat)
    d = jnp.take(ray.reshape(-1, 3), flat, axis=0)
    r_pt = jnp.sqrt(jnp.sum(p * p, axis=-1))
    # height of the point the pixel sees (vehicle z): on the hypothesis' horizontal plane?
    q_z = translation[2] + r_pix * jnp.sum(rotation[2] * d, axis=-1)
    along_ray = jnp.abs(r_pix - r_pt) <= tol_abs + tol_rel * r_pt
    on_plane = jnp.abs(q_z - points[..., 2]) <= GATHER_HEIGHT_TOLERANCE_M + tol_angle * r_pt
    return ok & (lab >= 0) & (along_ray | on_plane), lab, r_pt


def fuse_cameras_dense(
    cameras: AbstractCamera | Sequence[AbstractCamera],
    cameras_to_vehicle: Pose | Sequence[Pose],
    range_m: Float[ArrayLike, "N H W"],
    semantic: Int[ArrayLike, "N H W"],
    bev_camera: Orthographic,
    bev_camera_to_vehicle: Pose,
    *,
    valid: Bool[ArrayLike, "N H W"] | None = None,
    rays: tuple[Float[ArrayLike, "N H W 3"], Bool[ArrayLike, "N H W"]] | None = None,
    far_m: float = FAR_DEPTH_M,
    occupancy_min_height_m: float = OCCUPANCY_MIN_HEIGHT_M,
    fill_radius: int = GATHER_FILL_RADIUS,
    range_tolerance: float = GATHER_RANGE_TOLERANCE,
    height_tolerance_rad: float = GATHER_HEIGHT_TOLERANCE_RAD,
) -> BevFusion:
    """A dense top view fused from N cameras: every BEV cell asks the cameras what they see where
    it is (a gather, the inverse of `fuse_cameras`' splat), with a depth-consistency test.

    1. `fuse_cameras` splats every pixel's 3D point (its heights seed the hypotheses below).
    2. Per cell, **height hypotheses** z: the ground (0), the splat's height of the cell (if
       observed), and the lowest and highest splat heights observed within ``fill_radius`` cells.
       The hypothesis point is ``P = (x, y, z)`` at the cell centre ``(x, y)``.
    3. ``P`` is projected into every camera (exact model, validity and image bounds); the nearest
       pixel's range ``r_pix`` (along its own ray ``d``), class and validity are read. The camera
       **sees P consistently** when the pixel has a usable observation (valid ray and pixel,
       ``0 < r_pix < far_m``, class in ``[0, MAX_CLASSES)``) and either
       ``|r_pix - |P - c|| <= m sqrt(2) / 2 + range_tolerance |P - c|`` (the pixel's surface is at
       P along the line of sight: vertical faces) or the point the pixel sees,
       ``Q = c + r_pix d`` (``d`` its ray), lies on the hypothesis' horizontal plane:
       ``|Q_z - z| <= GATHER_HEIGHT_TOLERANCE_M + height_tolerance_rad |P - c|`` (ground and
       tops seen at grazing angles, where a pixel's range spans more than the cell; the angle
       bounds the range map's own angular error). ``m`` is the cell size, ``c`` the camera centre. A pixel seeing something nearer (an occluder: its point is
       higher, or in front along the ray) or farther (free space at P) fails both.
    4. **Choice:** the highest consistent hypothesis wins (the top view sees the top surface);
       among the cameras consistent at that height, the nearest one (smallest ``|P - c|``, the
       best resolved view) gives the class; ties go to the lower camera index.
    5. A cell the splat observed keeps the splat's class and height unless the gather found a
       strictly higher surface (a splatted point lies in the cell: exact, no resolution loss).

    Returns a `BevFusion` (height of the chosen hypothesis, class, observed, occupancy); cells no
    camera sees consistently and no point reached are `UNOBSERVED`. Arguments as `fuse_cameras`.
    The labels of gathered cells come from the nearest fisheye pixel: where a pixel's footprint
    exceeds the cell (far away), a cell within half a footprint of a class boundary may read the
    neighbouring class, as IPM does. Pure, jittable, float32."""
    cam = stack_cameras(cameras)
    poses = stack_poses(cameras_to_vehicle)
    splat = fuse_cameras(cam, poses, range_m, semantic, bev_camera, bev_camera_to_vehicle, valid=valid, rays=rays,
                         far_m=far_m, occupancy_min_height_m=occupancy_min_height_m)
    radius = int(fill_radius)
    if radius < 0:
        raise ValueError(f"fuse_cameras_dense: fill_radius must be >= 0 cells, got {fill_radius}")
    tol_rel, tol_angle = float(range_tolerance), float(height_tolerance_rad)
    if not tol_rel >= 0:
        raise ValueError(f"fuse_cameras_dense: range_tolerance must be >= 0, got {range_tolerance}")
    if not tol_angle >= 0:
        raise ValueError(f"fuse_cameras_dense: height_tolerance_rad must be >= 0, got {height_tolerance_rad}")
    r = jnp.asarray(range_m, _F32)
    ok_valid = jnp.ones(r.shape, bool) if valid is None else jnp.asarray(valid, bool)
    ray, ok = rig_rays(cam) if rays is None else (jnp.asarray(rays[0], _F32), jnp.asarray(rays[1], bool))
    return _gather(splat, cam, poses, ray, ok, r, jnp.asarray(semantic).astype(jnp.int32), ok_valid, bev_camera,
                   bev_camera_to_vehicle, float(far_m), float(occupancy_min_height_m), radius, tol_rel, tol_angle)


@functools.partial(jax.jit, static_argnums=(10, 11, 12, 13, 14))
def _gather(splat, cam, poses, ray, ok, r, sem, ok_valid, bev_camera, bev_camera_to_vehicle, far_m,
            occupancy_min_height_m, radius, tol_rel, tol_angle):
    ground = bev_ground_points(bev_camera, bev_camera_to_vehicle)  # (H, W, 3), z = 0
    labels = jnp.where(ok & ok_valid & (r > 0) & (r < far_m) & (sem >= 0) & (sem < MAX_CLASSES), sem, UNOBSERVED)
    size = (2 * radius + 1, 2 * radius + 1)
    obs = splat.observed
    hi = jax.lax.reduce_window(jnp.where(obs, splat.height_m, -jnp.inf), -jnp.inf, jax.lax.max, size, (1, 1), "SAME")
    lo = jax.lax.reduce_window(jnp.where(obs, splat.height_m, jnp.inf), jnp.inf, jax.lax.min, size, (1, 1), "SAME")
    hyps = jnp.stack([jnp.zeros_like(splat.height_m), jnp.where(obs, splat.height_m, _NO_HEIGHT),
                      jnp.where(jnp.isfinite(lo), lo, _NO_HEIGHT), jnp.where(jnp.isfinite(hi), hi, _NO_HEIGHT)])
    tol_abs = bev_camera.metres_per_pixel.astype(_F32) * _F32(0.5 * 2**0.5)
    rot = poses.rotation_matrix.astype(_F32)
    trans = poses.translation.astype(_F32)

    def step(best, z):
        best_z, best_r, best_lab = best
        present = z > _NO_HEIGHT / 2
        pts = ground.at[..., 2].set(jnp.where(present, z, 0.0))
        cons, lab, r_pt = jax.vmap(_gather_one, in_axes=(0, 0, 0, 0, 0, 0, None, None, None, None, None))(
            cam, rot, trans, ray, labels, r, pts, present, tol_abs, tol_rel, tol_angle)
        r_c = jnp.where(cons, r_pt, jnp.inf)
        k = jnp.argmin(r_c, axis=0)  # nearest consistent camera; ties: the lower index
        r_k = jnp.min(r_c, axis=0)
        lab_k = jnp.take_along_axis(lab, k[None], axis=0)[0]
        seen = jnp.isfinite(r_k)
        better = seen & ((z > best_z) | ((z == best_z) & (r_k < best_r)))
        return (jnp.where(better, z, best_z), jnp.where(better, r_k, best_r), jnp.where(better, lab_k, best_lab)), None

    init = (jnp.full(obs.shape, -jnp.inf, _F32), jnp.full(obs.shape, jnp.inf, _F32), jnp.full(obs.shape, UNOBSERVED, jnp.int32))
    (best_z, _, best_lab), _ = jax.lax.scan(step, init, hyps.astype(_F32))
    gathered = best_lab >= 0
    use_gather = gathered & (~obs | (best_z > splat.height_m))
    observed = obs | gathered
    height = jnp.where(use_gather, best_z, splat.height_m)
    cls = jnp.where(use_gather, best_lab, splat.semantic)
    return BevFusion(height_m=height.astype(_F32), semantic=cls.astype(jnp.int32), observed=observed,
                     occupancy=observed & (height > occupancy_min_height_m))
