"""Hostile inputs of the dense fused top view and of the BEV scores (library calls), and of
``jaxfish bev``'s options."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .corpus import Case


def _dense(range_value=None, **kw):
    """`fuse_cameras_dense` on a tiny rig (48 x 36 fisheyes, 32 x 32 BEV at 0.5 m) whose range maps
    are 5 m everywhere, some pixels replaced by ``range_value``."""
    import jax.numpy as jnp

    import jaxfish as jf
    from jaxfish import bev

    rig = jf.default_rig(width=48, height=36, dtype=jnp.float32)
    rng = np.full((4, 36, 48), 5.0, np.float32)
    if range_value is not None:
        rng[:, ::3, ::2] = range_value
    sem = np.ones((4, 36, 48), np.int32)
    cam = jf.Orthographic(0.5, width=32, height=32, dtype=jnp.float32)
    pose = jf.Pose(np.array([[0.0, -1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, -1.0]]), np.array([1.3, 0.0, 50.0]),
                   dtype=jnp.float32)
    return bev.fuse_cameras_dense([c.camera for c in rig.values()], [c.camera_to_vehicle for c in rig.values()], rng,
                                  sem, cam, pose, **kw)


def _finite(out) -> bool:
    h = np.asarray(out.height_m)
    return bool(np.all(np.isfinite(h)) and np.all(h[~np.asarray(out.observed)] == 0.0)
                and np.all(np.asarray(out.semantic)[~np.asarray(out.observed)] == -1))


def _scores(tmp: Path, num_classes=3, **kw):
    from jaxfish import bev

    return bev.bev_scores(np.array([1, 2, -1]), np.array([1, 2, 2]), num_classes=num_classes, **kw)


CASES = [
    Case("bev-dense-nan-ranges", call=lambda tmp: _dense(np.nan), raises=None, check=_finite),
    Case("bev-dense-infinite-ranges", call=lambda tmp: _dense(np.inf), raises=None, check=_finite),
    Case("bev-dense-negative-ranges", call=lambda tmp: _dense(-3.0), raises=None, check=_finite),
    Case("bev-dense-negative-fill-radius", call=lambda tmp: _dense(fill_radius=-1), raises=ValueError,
         says=("fill_radius must be >= 0",)),
    Case("bev-dense-nan-tolerance", call=lambda tmp: _dense(range_tolerance=float("nan")), raises=ValueError,
         says=("range_tolerance must be >= 0",)),
    Case("bev-dense-negative-height-tolerance", call=lambda tmp: _dense(height_tolerance_rad=-0.1), raises=ValueError,
         says=("height_tolerance_rad must be >= 0",)),
    Case("bev-scores-observed-shape", call=lambda tmp: _scores(tmp, observed=np.ones(2, bool)), raises=ValueError,
         says=("observed",)),
    Case("bev-scores-zero-classes", call=lambda tmp: _scores(tmp, num_classes=0), raises=ValueError,
         says=("num_classes must be positive",)),
    Case("bev-samples-on-a-capture", "bev {capture} --out {tmp}/o --samples 00000", says=("--samples is for built",),
         absent=("{tmp}/o",)),
]
