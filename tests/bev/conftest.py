"""An analytic scene for the BEV tests, rendered independently in float64 NumPy: the ground plane
z = 0 carrying a class pattern, and axis-aligned boxes standing on it. Each fisheye pixel's ray
(vehicle frame) hits the nearest surface: range and class follow in closed form."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxfish as jf
from jaxfish import bev

F32 = jnp.float32
CAM_W, CAM_H = 320, 240
BEV_SIZE, BEV_MPP = 160, 0.1
#: BEV camera 50 m above (1.3, 0) looking down, image up = vehicle forward (the capture's mount).
BEV_X0 = 1.3
BEV_ROTATION = np.array([[0.0, -1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
#: Boxes (x0, x1, y0, y1, height, class) in the vehicle frame, metres: all but the last lower than
#: every camera (0.62 m and up), so that their tops are seen; the last (1.5 m) only by its sides.
BOXES = ((5.0, 6.5, -1.0, 0.6, 0.5, 10), (-6.5, -5.0, 1.5, 3.0, 0.3, 22), (1.0, 2.0, 4.0, 5.0, 0.4, 5),
         (0.5, 2.0, -5.5, -4.5, 0.15, 8), (-3.5, -2.5, -5.0, -4.0, 1.5, 11))


def ground_class(x, y):
    """The ground pattern: classes 1..4 on a 1.0 m (x) by 0.7 m (y) checkerboard offset from the origin."""
    ix = np.floor((np.asarray(x) - 0.3) / 1.0).astype(np.int64) % 2
    iy = np.floor((np.asarray(y) + 0.2) / 0.7).astype(np.int64) % 2
    return 1 + ix + 2 * iy


def render(rays_vehicle: np.ndarray, origin: np.ndarray, boxes=BOXES):
    """Range (1000 where nothing is hit) and class (13 = sky) of rays from ``origin`` (one point or
    one per ray; float64)."""
    d = np.asarray(rays_vehicle, np.float64)
    o = np.asarray(origin, np.float64)
    down = d[..., 2] < -1e-9
    best = np.where(down, -o[..., 2] / np.where(down, d[..., 2], -1.0), np.inf)
    cls = np.where(down, 0, 13)
    hit_pt = o + np.where(np.isfinite(best), best, 0.0)[..., None] * d
    cls = np.where(down, ground_class(hit_pt[..., 0], hit_pt[..., 1]), 13)
    for x0, x1, y0, y1, h, c in boxes:
        lo, hi = np.array([x0, y0, 0.0]), np.array([x1, y1, h])
        with np.errstate(divide="ignore", invalid="ignore"):
            t1 = (lo - o) / d
            t2 = (hi - o) / d
        tmin = np.nanmax(np.minimum(t1, t2), axis=-1)
        tmax = np.nanmin(np.maximum(t1, t2), axis=-1)
        hit = (tmax >= tmin) & (tmin > 0) & (tmin < best)
        best = np.where(hit, tmin, best)
        cls = np.where(hit, c, cls)
    rng = np.where(np.isfinite(best), np.minimum(best, 1000.0), 1000.0)
    return rng, cls


@dataclasses.dataclass(frozen=True)
class Rig:
    """The four cameras stacked, their rays, and the analytic scene seen by them."""

    calibs: dict
    cameras: object
    poses: object
    rays: tuple
    range_m: np.ndarray  # (4, H, W) float32
    semantic: np.ndarray  # (4, H, W) int32
    range_ground: np.ndarray  # ground only (no boxes)
    semantic_ground: np.ndarray
    bev_camera: object
    bev_pose: object


@pytest.fixture(scope="session")
def rig() -> Rig:
    calibs = {k: c.astype(F32) for k, c in jf.default_rig(width=CAM_W, height=CAM_H, dtype=F32).items()}
    cams = bev.stack_cameras([c.camera for c in calibs.values()])
    poses = bev.stack_poses([c.camera_to_vehicle for c in calibs.values()])
    rays = jax.jit(bev.rig_rays)(cams)
    ray, ok = (np.asarray(a, np.float64) for a in rays)
    out = {True: ([], []), False: ([], [])}
    for i, calib in enumerate(calibs.values()):
        r = np.asarray(calib.camera_to_vehicle.rotation_matrix, np.float64)
        t = np.asarray(calib.camera_to_vehicle.translation, np.float64)
        for with_boxes in (True, False):
            rng, cls = render(ray[i] @ r.T, t, BOXES if with_boxes else ())
            out[with_boxes][0].append(np.where(ok[i] > 0, rng, 0.0).astype(np.float32))
            out[with_boxes][1].append(np.where(ok[i] > 0, cls, -1).astype(np.int32))
    bev_cam = jf.Orthographic(BEV_MPP, width=BEV_SIZE, height=BEV_SIZE, dtype=F32)
    bev_pose = jf.Pose(BEV_ROTATION, np.array([BEV_X0, 0.0, 50.0]), dtype=F32)
    return Rig(calibs, cams, poses, rays, np.stack(out[True][0]), np.stack(out[True][1]), np.stack(out[False][0]),
               np.stack(out[False][1]), bev_cam, bev_pose)


def cell_centres() -> tuple[np.ndarray, np.ndarray]:
    """Vehicle (x, y) of every BEV cell centre, from the documented convention
    ``x = x0 - (v - cy) m``, ``y = -(u - cx) m`` (independent of `jaxfish.bev`)."""
    c = (BEV_SIZE - 1) / 2.0
    v, u = np.mgrid[0:BEV_SIZE, 0:BEV_SIZE].astype(np.float64)
    return BEV_X0 - (v - c) * BEV_MPP, -(u - c) * BEV_MPP


def pattern_is_uniform(x, y, radius):
    """True where the ground pattern is one class over the square of half-size ``radius`` around (x, y)."""
    ref = ground_class(x, y)
    same = np.ones(np.shape(x), bool)
    for dx in (-radius, 0.0, radius):
        for dy in (-radius, 0.0, radius):
            same &= ground_class(x + dx, y + dy) == ref
    return same
