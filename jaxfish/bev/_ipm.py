"""The IPM baseline: inverse perspective mapping of fisheye semantic maps onto the ground plane."""

from __future__ import annotations

from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from .._numerics import materialize
from ..cameras import AbstractCamera, Orthographic
from ..groundtruth import apply_pose
from ..transforms import Pose
from ._cameras import stack_cameras, stack_poses
from ._fusion import UNOBSERVED
from ._grid import bev_ground_points, check_looks_down

_F32 = jnp.float32


class IpmBev(eqx.Module):
    """A top view by inverse perspective mapping: per cell the `semantic` class sampled from the
    chosen camera (`UNOBSERVED` = -1 where no camera sees the cell's ground point), the
    `camera_index` of that camera (-1: none) and the `incidence_rad` of the ground point in it
    (angle from its optical axis; pi where none)."""

    semantic: Int[Array, "*batch H W"]
    camera_index: Int[Array, "*batch H W"]
    incidence_rad: Float[Array, "*batch H W"]


def _sample_one(camera, to_camera, labels, ground):
    p = apply_pose(to_camera, ground)
    # computed once into buffers: XLA on CPU otherwise repeats the projection in its consumers
    uv, ok = materialize(camera.project(p), p[0, 0, 0])
    ok = ok & camera.contains(uv)
    h, w = labels.shape
    iu = jnp.clip(jnp.floor(uv[..., 0] + 0.5).astype(jnp.int32), 0, w - 1)
    iv = jnp.clip(jnp.floor(uv[..., 1] + 0.5).astype(jnp.int32), 0, h - 1)
    lab = jnp.take(labels.reshape(-1), iv * w + iu)  # labels already -1 where not valid: one gather
    ok = ok & (lab >= 0)
    theta = jnp.arctan2(jnp.hypot(p[..., 0], p[..., 1]), p[..., 2])
    return jnp.where(ok, lab, UNOBSERVED), jnp.where(ok, theta, jnp.pi)


def ipm_semantics(
    cameras: AbstractCamera | Sequence[AbstractCamera],
    cameras_to_vehicle: Pose | Sequence[Pose],
    semantic: Int[ArrayLike, "N h w"],
    bev_camera: Orthographic,
    bev_camera_to_vehicle: Pose,
    *,
    valid: Bool[ArrayLike, "N h w"] | None = None,
) -> IpmBev:
    """IPM of N cameras' semantic maps into the top view of ``bev_camera``.

    Every BEV cell's ground point (z = 0 in the vehicle frame, `bev_ground_points`) is projected
    into every camera through its model (e.g. the WoodScape polynomial) and ``cameras_to_vehicle``
    pose; the class of the nearest pixel is read (pixels not ``valid`` and negative labels do not
    count). **Blending rule:** among the cameras that see the point, the one seeing it closest to
    its optical axis (smallest incidence angle θ, i.e. the least distorted and best resolved view)
    gives the class; ties go to the lower camera index. IPM assumes everything lies on the ground:
    a point at height h seen from a camera at height H at horizontal distance d lands at distance
    ``d H / (H - h)`` — upright objects are stretched away from the cameras. Pure, jittable."""
    cam = stack_cameras(cameras)
    poses = stack_poses(cameras_to_vehicle)
    sem = jnp.asarray(semantic)
    n = poses.rotation_matrix.shape[0]
    if sem.ndim != 3 or sem.shape[0] != n or not jnp.issubdtype(sem.dtype, jnp.integer):
        raise ValueError(f"ipm_semantics: semantic must be integer (N={n}, H, W), got {sem.dtype} {sem.shape}")
    if (cam.height, cam.width) != sem.shape[1:]:
        raise ValueError(f"ipm_semantics: semantic maps {sem.shape[1:]} do not match the cameras' images {(cam.height, cam.width)}")
    ok_valid = jnp.ones(sem.shape, bool) if valid is None else jnp.asarray(valid, bool)
    if ok_valid.shape != sem.shape:
        raise ValueError(f"ipm_semantics: valid must be {sem.shape}, got {ok_valid.shape}")
    check_looks_down(bev_camera_to_vehicle, "ipm_semantics: bev_camera_to_vehicle")
    return _ipm(cam, poses, sem.astype(jnp.int32), ok_valid, bev_camera, bev_camera_to_vehicle)


@jax.jit
def _ipm(cam, poses, sem, ok_valid, bev_camera, bev_camera_to_vehicle):
    # compiled once per shape: eager callers run one kernel instead of dispatching op by op
    ground = bev_ground_points(bev_camera, bev_camera_to_vehicle)
    masked = jnp.where(ok_valid, sem, UNOBSERVED)
    labels, theta = jax.vmap(_sample_one, in_axes=(0, 0, 0, None))(cam, poses.inverse(), masked, ground)
    best = jnp.argmin(theta, axis=0)
    th = jnp.min(theta, axis=0)
    lab = jnp.take_along_axis(labels, best[None], axis=0)[0]
    seen = lab >= 0
    return IpmBev(semantic=jnp.where(seen, lab, UNOBSERVED), camera_index=jnp.where(seen, best, -1).astype(jnp.int32),
                  incidence_rad=jnp.where(seen, th, jnp.pi).astype(_F32))
