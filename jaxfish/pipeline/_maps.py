"""Range and class maps of every fisheye camera of a frame at t: the inputs of the camera-fused
and IPM top views (`jaxfish.bev.fuse_cameras`, `jaxfish.bev.ipm_semantics`)."""

from __future__ import annotations

import functools
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Bool, Float, Int

from .. import groundtruth as gt
from ..cameras import AbstractCamera
from ..reprojection import resample_depth, resample_nearest
from ..transforms import Pose
from ._constants import RigConstants
from ._frame import Frame


class CameraMaps(eqx.Module):
    """Per fisheye camera at t (leading axis ``N`` over `names`):

    - `names`, `cameras` (float32 lens models), `cameras_to_vehicle` (mounts);
    - `range_m` ``(N, H, W)``: range along each pixel's ray (metres, far 1000, 0 without a ray);
    - `semantic` ``(N, H, W)`` int32: SynWoodScape classes, -1 where no ray;
    - `valid` ``(N, H, W)``: the pixel has a ray seen by a face;
    - `range_resolution_rad`: the angle of one cube-face pixel, (pi / 2) / face size, or None when
      unknown (`jaxfish.bev.fuse_cameras_dense`'s tolerance).
    """

    names: tuple[str, ...] = eqx.field(static=True)
    cameras: tuple[AbstractCamera, ...]
    cameras_to_vehicle: tuple[Pose, ...]
    range_m: Float[np.ndarray, "N H W"]
    semantic: Int[np.ndarray, "N H W"]
    valid: Bool[np.ndarray, "N H W"]
    range_resolution_rad: float | None = eqx.field(static=True, default=None)


def _split_classes(world, base, centre, rot, half, cls, margin_m):
    """Vehicle-like pixels inside a two-wheeler or ego box take the box's class (first box wins)."""
    d = world[None] - centre[:, None, None, :]
    local = jnp.einsum("kji,khwj->khwi", rot, d)
    inside = jnp.all(jnp.abs(local) <= half[:, None, None, :] + margin_m, axis=-1)  # (K, H, W)
    hit = jnp.any(inside, axis=0)
    box_cls = jnp.where(hit, cls[jnp.argmax(inside, axis=0)], -1)
    vehicle_like = (base == 10) | (base == 21)
    return jnp.where(vehicle_like & hit, box_cls, base)


@functools.partial(jax.jit, static_argnums=(10,))
def _camera_maps_kernel(lut, cam, rays, c2w, depth, tag, centre, rot, half, cls, margin_m):
    # as `jaxfish.groundtruth.fisheye_images`, without the RGB
    rng, valid = resample_depth(depth.astype(jnp.float32), lut, far_m=gt.FAR_RANGE_M)
    tags, _ = resample_nearest(tag, lut, reduce="centre")
    pts, ok = gt.pixel_points(cam, rng, dtype=jnp.float32, rays=rays)
    world = gt.apply_pose(c2w, pts)
    base = gt.carla_to_synwoodscape(tags.astype(jnp.int32))
    sem = _split_classes(world, base, centre, rot, half, cls, margin_m)
    valid = valid & ok
    return rng, jnp.where(valid, sem, -1), valid


def camera_maps(frame: Frame, constants: RigConstants, *, margin_m: float = 0.05) -> CameraMaps:
    """`CameraMaps` of a frame at t, lighter than `sample_truth` (no flow, instances or events):
    per camera the cube faces' depth and tags resampled to the fisheye as
    `jaxfish.groundtruth.fisheye_images` does; tags become SynWoodScape classes, and vehicle pixels
    whose 3D point lies in a two-wheeler or the ego box (grown by ``margin_m``) take that box's
    class (21, 24), as in the full ground truth. Raises ``ValueError`` when the cameras differ in
    image size."""
    boxes = frame.motion.boxes
    sel = np.asarray(boxes.active) & np.isin(np.asarray(boxes.class_id), (21, 24))
    # one never-containing padding box keeps the kernel's box axis non-empty
    centre = jnp.asarray(np.concatenate([np.asarray(boxes.box_to_world.translation)[sel].reshape(-1, 3),
                                         np.zeros((1, 3))]), jnp.float32)
    rot = jnp.asarray(np.concatenate([np.asarray(boxes.box_to_world.rotation_matrix)[sel].reshape(-1, 3, 3),
                                      np.eye(3)[None]]), jnp.float32)
    half = jnp.asarray(np.concatenate([np.asarray(boxes.half_extent)[sel].reshape(-1, 3), np.full((1, 3), -1e9)]),
                       jnp.float32)
    cls = jnp.asarray(np.concatenate([np.asarray(boxes.class_id)[sel].reshape(-1), [-1]]), jnp.int32)
    rng, sem, val = [], [], []
    for k, cf in zip(constants.cameras, frame.camera_frames, strict=True):
        c2w = gt.camera_to_world(frame.motion.vehicle_to_world, k.camera_to_vehicle)
        r, s, v = _camera_maps_kernel(k.lut, k.camera, k.rays, c2w, jnp.asarray(cf.faces.depth_m),
                                      jnp.asarray(cf.faces.semantic), centre, rot, half, cls, float(margin_m))
        rng.append(np.asarray(r))
        sem.append(np.asarray(s))
        val.append(np.asarray(v))
    shapes = {a.shape for a in rng}
    if len(shapes) > 1:
        raise ValueError(f"the fisheye cameras differ in image size ({sorted(shapes)})")
    return CameraMaps(names=constants.names, cameras=tuple(k.camera for k in constants.cameras),
                      cameras_to_vehicle=tuple(k.camera_to_vehicle for k in constants.cameras),
                      range_m=np.stack(rng), semantic=np.stack(sem).astype(np.int32), valid=np.stack(val),
                      range_resolution_rad=math.pi / 2 / constants.face_size)
