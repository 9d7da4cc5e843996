"""The top-view grid: BEV pixel <-> vehicle-frame ground point, height maps and occupancy.

A BEV image is an `Orthographic` camera mounted by ``camera_to_vehicle`` (OpenCV camera -> ISO
8855 vehicle). For the standard mount (looking straight down, image up = vehicle forward, image
right = vehicle right) pixel ``(u, v)`` is the ground point ``x = x0 - (v - cy) m``,
``y = y0 - (u - cx) m`` (``m`` metres per pixel, ``(x0, y0)`` the camera's position): every
function here uses the pose itself, so any downward-looking mount works.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float, UInt8

from .._constants import FAR_DEPTH_M
from ..cameras import Orthographic
from ..groundtruth import apply_pose
from ..transforms import Pose

OCCUPANCY_MIN_HEIGHT_M = 0.2
"""A BEV cell is occupied when its top surface is more than this many metres above the ground:
curbs (~0.15 m) and speed bumps (~0.1 m) are traversable, cars, people, poles and walls are not."""
HEIGHT_COLOR_RANGE_M = (0.0, 4.0)
"""Height range (metres) of the colour rendering of height maps (`colorize_height`)."""

_DOWN_MIN_COSINE = 1.0 - 1e-3
"""A BEV camera counts as looking straight down when its optical axis (camera +z, in the vehicle
frame) has a component along vehicle -z above this (within ~2.6 degrees of the vertical)."""

_F32 = jnp.float32


def _pose32(pose: Pose) -> Pose:
    return Pose(pose.rotation_matrix, pose.translation, dtype=_F32)


def check_looks_down(camera_to_vehicle: Pose, what: str) -> None:
    """Raise ValueError (the message starts with ``what``) unless ``camera_to_vehicle`` is one
    pose (rotation ``(3, 3)``) looking straight down: ``R[:, 2] . (0, 0, -1) > _DOWN_MIN_COSINE``.
    The direction is checked when the pose is concrete; a traced pose inside ``jit`` is the
    caller's responsibility."""
    r = camera_to_vehicle.rotation_matrix
    if tuple(r.shape) != (3, 3):
        raise ValueError(f"{what}: camera_to_vehicle must be one pose (3 x 3 rotation), got {tuple(r.shape)}")
    if isinstance(r, jax.core.Tracer):
        return
    down = -float(np.asarray(r, np.float64)[2, 2])
    if not down > _DOWN_MIN_COSINE:
        axis = np.round(np.asarray(r, np.float64)[:, 2], 4).tolist()
        raise ValueError(f"{what}: camera_to_vehicle must look straight down (optical axis R[:, 2] = (0, 0, -1) in the "
                         f"vehicle frame, cosine > {_DOWN_MIN_COSINE}), got optical axis {axis}")


def bev_pixel_to_vehicle(camera: Orthographic, camera_to_vehicle: Pose) -> Float[Array, "2 3"]:
    """The affine map ``[x, y] = A @ [u, v, 1]`` from a BEV pixel to the vehicle-frame ``(x, y)`` of
    the ground point it sees (ISO 8855, metres), for a camera looking straight down
    (``camera_to_vehicle`` maps camera +z to vehicle -z). Standard mount: ``[[0, -m, x0 + m cy],
    [-m, 0, y0 + m cx]]``."""
    check_looks_down(camera_to_vehicle, "bev_pixel_to_vehicle")
    pose = _pose32(camera_to_vehicle)
    r, t = pose.rotation_matrix, pose.translation
    m = camera.metres_per_pixel.astype(_F32)
    cx, cy = camera.cx.astype(_F32), camera.cy.astype(_F32)
    a = jnp.stack([r[:2, 0] * m, r[:2, 1] * m, t[:2] - r[:2, 0] * m * cx - r[:2, 1] * m * cy], axis=-1)
    return a


def bev_ground_points(camera: Orthographic, camera_to_vehicle: Pose) -> Float[Array, "H W 3"]:
    """Vehicle-frame ground point (z = 0) at the centre of every BEV pixel: where each pixel's ray
    meets the ground plane (float32, metres)."""
    check_looks_down(camera_to_vehicle, "bev_ground_points")
    pose = _pose32(camera_to_vehicle)
    grid = camera.pixel_grid(_F32)
    origin = apply_pose(pose, camera.ray_origins(grid).astype(_F32))
    d = pose.rotation_matrix[:, 2]
    dz = jnp.where(jnp.abs(d[2]) > 1e-6, d[2], -1.0)
    s = -origin[..., 2] / dz
    pts = origin + s[..., None] * d
    return pts.at[..., 2].set(0.0)


def vehicle_to_bev_pixels(
    camera: Orthographic, camera_to_vehicle: Pose, points: Float[ArrayLike, "*batch 3"]
) -> Float[Array, "*batch 2"]:
    """BEV pixel ``(u, v)`` (pixel-centre convention) straight above each vehicle-frame point."""
    check_looks_down(camera_to_vehicle, "vehicle_to_bev_pixels")
    p = jnp.asarray(points, _F32)
    if p.shape[-1:] != (3,):
        raise ValueError(f"vehicle_to_bev_pixels: points must be (..., 3), got {p.shape}")
    cam_pts = apply_pose(_pose32(camera_to_vehicle).inverse(), p)
    m = camera.metres_per_pixel.astype(_F32)
    return jnp.stack([cam_pts[..., 0] / m + camera.cx.astype(_F32), cam_pts[..., 1] / m + camera.cy.astype(_F32)], -1)


def height_map(
    camera: Orthographic,
    camera_to_vehicle: Pose,
    range_m: Float[ArrayLike, "H W"],
    *,
    far_m: float = FAR_DEPTH_M,
) -> Float[Array, "H W"]:
    """Height (metres above the vehicle's ground plane z = 0) of the surface each BEV pixel sees,
    from the BEV depth (distance from the image plane along the ray; CARLA's planar depth of an
    orthographic camera is the same). Sky / far (``>= far_m``) is 0."""
    r = jnp.asarray(range_m, _F32)
    if r.shape != (camera.height, camera.width):
        raise ValueError(f"height_map: range map {r.shape} does not match the BEV image {(camera.height, camera.width)}")
    check_looks_down(camera_to_vehicle, "height_map")
    grid = camera.pixel_grid(_F32)
    pts = camera.ray_origins(grid).astype(_F32) + r[..., None] * jnp.asarray([0.0, 0.0, 1.0], _F32)
    z = apply_pose(_pose32(camera_to_vehicle), pts)[..., 2]
    return jnp.where((r < far_m) & (r > 0), z, 0.0).astype(_F32)


def occupancy_map(
    height_m: Float[ArrayLike, "H W"],
    *,
    observed: Bool[ArrayLike, "H W"] | None = None,
    min_height_m: float = OCCUPANCY_MIN_HEIGHT_M,
) -> Bool[Array, "H W"]:
    """Occupancy: a cell is occupied when its top surface is more than ``min_height_m`` above the
    ground (and, for fused maps, the cell was ``observed``)."""
    h = jnp.asarray(height_m, _F32)
    if h.ndim != 2:
        raise ValueError(f"occupancy_map: height map must be (H, W), got {h.shape}")
    occ = h > min_height_m
    return occ if observed is None else occ & jnp.asarray(observed, bool)


# Viridis at 9 evenly spaced points (matplotlib's table), linearly interpolated.
_VIRIDIS = np.array([
    (68, 1, 84), (71, 44, 122), (59, 81, 139), (44, 113, 142), (33, 144, 141),
    (39, 173, 129), (92, 200, 99), (170, 220, 50), (253, 231, 37),
], np.float32)


def colorize_height(
    height_m: Float[ArrayLike, "H W"],
    *,
    valid: Bool[ArrayLike, "H W"] | None = None,
    range_m: tuple[float, float] = HEIGHT_COLOR_RANGE_M,
) -> UInt8[Array, "H W 3"]:
    """Colour rendering of a height map: viridis from ``range_m[0]`` (dark blue) to ``range_m[1]``
    (yellow), clipped; cells not ``valid`` are black."""
    h = jnp.asarray(height_m, _F32)
    lo, hi = float(range_m[0]), float(range_m[1])
    if not hi > lo:
        raise ValueError(f"colorize_height: range_m must be increasing, got {range_m}")
    s = jnp.clip((h - lo) / (hi - lo), 0.0, 1.0) * (len(_VIRIDIS) - 1)
    i0 = jnp.clip(jnp.floor(s).astype(jnp.int32), 0, len(_VIRIDIS) - 2)
    f = (s - i0.astype(_F32))[..., None]
    table = jnp.asarray(_VIRIDIS)
    rgb = table[i0] * (1.0 - f) + table[i0 + 1] * f
    if valid is not None:
        rgb = jnp.where(jnp.asarray(valid, bool)[..., None], rgb, 0.0)
    return jnp.clip(jnp.round(rgb), 0, 255).astype(jnp.uint8)
