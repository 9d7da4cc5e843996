"""Stacking a rig's cameras and poses on a leading camera axis (for `jax.vmap` over cameras)."""

from __future__ import annotations

from collections.abc import Sequence

import jax
import jax.numpy as jnp

from ..cameras import AbstractCamera
from ..transforms import Pose


def stack_cameras(cameras: AbstractCamera | Sequence[AbstractCamera]) -> AbstractCamera:
    """One camera pytree whose array leaves carry a leading camera axis ``(N, ...)``: the cameras
    must be of one model and image size (static fields equal). A camera already stacked is
    returned as is."""
    if isinstance(cameras, AbstractCamera):
        return cameras
    cams = list(cameras)
    if not cams:
        raise ValueError("stack_cameras: no cameras given")
    defs = {jax.tree_util.tree_structure(c) for c in cams}
    if len(defs) != 1:
        sizes = [(type(c).__name__, getattr(c, "width", None), getattr(c, "height", None)) for c in cams]
        raise ValueError(f"stack_cameras: cameras must share one model and image size to be stacked, got {sizes}")
    return jax.tree.map(lambda *xs: jnp.stack(xs), *cams)


def stack_poses(poses: Pose | Sequence[Pose], *, dtype=jnp.float32) -> Pose:
    """Poses stacked on a leading axis ``(N,)`` as ``dtype``: a batched `Pose` is returned as is, a
    single `Pose` (a ``(3, 3)`` rotation) becomes a batch of one."""
    if isinstance(poses, Pose):
        r, t = poses.rotation_matrix, poses.translation
        if tuple(jnp.shape(r)) == (3, 3):
            r, t = jnp.asarray(r)[None], jnp.asarray(t)[None]
        return Pose(r, t, dtype=dtype)
    ps = list(poses)
    if not ps:
        raise ValueError("stack_poses: no poses given")
    return Pose(jnp.stack([jnp.asarray(p.rotation_matrix) for p in ps]), jnp.stack([jnp.asarray(p.translation) for p in ps]),
                dtype=dtype)


def rig_rays(cameras: AbstractCamera | Sequence[AbstractCamera]) -> tuple[jax.Array, jax.Array]:
    """Unit rays ``(N, H, W, 3)`` (camera frames, float32) and validity ``(N, H, W)`` of every pixel
    of every camera: the per-rig constant `fuse_cameras` accepts as ``rays=``."""
    cam = stack_cameras(cameras)
    return jax.vmap(lambda c: c.unproject(c.pixel_grid(jnp.float32)))(cam)
