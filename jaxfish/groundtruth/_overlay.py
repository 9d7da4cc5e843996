"""Overlays on fisheye images: 3D box wireframes (the exact fisheye image of every box edge, as
densely sampled polylines), points in the vehicle frame (lidar) with their range, and NumPy
rasterisers that draw polylines, points and 2D boxes into a uint8 image."""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float, Int, UInt8

from .._numerics import float_dtype
from ..cameras import AbstractCamera
from ..transforms import Pose

BOX_EDGES: np.ndarray = np.array([(a, a | bit) for a in range(8) for bit in (4, 2, 1) if not a & bit], np.int64)
"""The 12 edges of a box as pairs of corner indices ``(12, 2)`` in `CORNER_SIGNS` order (corner ``k =
4 ix + 2 iy + iz``): two corners share an edge when their indices differ in exactly one bit."""
SAMPLES_PER_EDGE = 64
"""Default number of points sampled along each box edge (both corners included)."""
CHORD_TOLERANCE_PX = 0.25
"""Largest distance (pixels) between the projection of a sub-segment's 3D midpoint and the midpoint
of its straight chord in the image for the chord to be drawn (`box_edge_pixels`)."""


class BoxEdgePixels(eqx.Module):
    """The fisheye image of the edges of ``K`` boxes, each edge sampled at ``S`` points.

    - `uv` ``(*batch, K, 12, S, 2)``: pixels ``(u, v)`` of the samples (edge ``e`` runs from corner
      ``BOX_EDGES[e, 0]`` to ``BOX_EDGES[e, 1]``, sample ``s`` at the fraction ``s / (S - 1)``);
      finite placeholders where `valid` is False;
    - `valid` ``(*batch, K, 12, S)``: the camera projects the sample (inside its valid domain, not
      the camera centre); it says nothing of the image bounds;
    - `drawn` ``(*batch, K, 12, S - 1)``: whether the straight chord from sample ``s`` to ``s + 1``
      stands for the edge's image: both samples and the sub-segment's 3D midpoint are valid, and
      that midpoint projects within `CHORD_TOLERANCE_PX` of the chord's midpoint. False where the
      edge leaves the camera's domain (beyond ``theta_max``, behind a pinhole) or where its image
      jumps (an edge passing the back axis of a fisheye, where the azimuth flips): each run of
      drawn chords is one polyline, never joined across such a split.
    """

    uv: Float[Array, "*batch K 12 S 2"]
    valid: Bool[Array, "*batch K 12 S"]
    drawn: Bool[Array, "*batch K 12 S-1"]


class ProjectedPoints(eqx.Module):
    """Points projected into one camera.

    - `uv` ``(*batch, 2)``: pixels (finite placeholders where `valid` is False);
    - `range_m` ``(*batch,)``: Euclidean distance from the camera centre, metres (the range of
      ``depth_maps/raw_data``);
    - `valid` ``(*batch,)``: the camera projects the point and its pixel lies inside the image
      ``[-0.5, W - 0.5] x [-0.5, H - 0.5]``.
    """

    uv: Float[Array, "*batch 2"]
    range_m: Float[Array, " *batch"]
    valid: Bool[Array, " *batch"]


def box_edge_pixels(
    camera: AbstractCamera,
    vehicle_to_camera: Pose,
    corners_vehicle: Float[ArrayLike, "*batch K 8 3"],
    samples_per_edge: int = SAMPLES_PER_EDGE,
    *,
    chord_tolerance_px: float = CHORD_TOLERANCE_PX,
) -> BoxEdgePixels:
    """The exact image of every box edge: each edge is sampled at ``samples_per_edge`` points (and
    the midpoints between them), every point projected with ``camera`` after
    ``vehicle_to_camera`` (ISO 8855 vehicle frame -> OpenCV camera frame), so a fisheye's curved
    edges are followed rather than replaced by straight lines between projected corners.

    ``corners_vehicle``: box corners in the vehicle frame, metres, in `CORNER_SIGNS` order (as
    ``box_3d_annotations_ext``'s ``corners_vehicle``); ``samples_per_edge`` (static, >= 2) sets
    the polyline resolution: a chord is drawn only when it stays within ``chord_tolerance_px`` of
    the curve at its midpoint (see `BoxEdgePixels`). Pure, jit- and vmap-safe (``samples_per_edge``
    static); computed in the corners' floating dtype."""
    corners = jnp.asarray(corners_vehicle)
    if corners.ndim < 3 or corners.shape[-2:] != (8, 3):
        raise ValueError(f"box_edge_pixels: corners_vehicle must have shape (..., K, 8, 3), got {corners.shape}")
    n = int(samples_per_edge)
    if n < 2:
        raise ValueError(f"box_edge_pixels: samples_per_edge must be at least 2, got {samples_per_edge}")
    dtype = float_dtype(corners)
    corners = corners.astype(dtype)
    start = corners[..., BOX_EDGES[:, 0], None, :]  # (..., K, 12, 1, 3)
    end = corners[..., BOX_EDGES[:, 1], None, :]
    t = (jnp.arange(2 * n - 1, dtype=dtype) / (2 * (n - 1)))[:, None]  # samples and midpoints interleaved
    points = (1 - t) * start + t * end  # exact corners at t = 0 and 1
    uv, ok = camera.project(vehicle_to_camera.apply(points))
    uv_s, ok_s = uv[..., ::2, :], ok[..., ::2]
    uv_m, ok_m = uv[..., 1::2, :], ok[..., 1::2]
    chord_mid = 0.5 * (uv_s[..., :-1, :] + uv_s[..., 1:, :])
    d = uv_m - chord_mid
    deviation = jnp.sqrt(d[..., 0] * d[..., 0] + d[..., 1] * d[..., 1])
    drawn = ok_s[..., :-1] & ok_s[..., 1:] & ok_m & (deviation <= jnp.asarray(chord_tolerance_px, dtype))
    return BoxEdgePixels(uv=uv_s, valid=ok_s, drawn=drawn)


def project_points(
    camera: AbstractCamera, vehicle_to_camera: Pose, points_vehicle: Float[ArrayLike, "*batch 3"]
) -> ProjectedPoints:
    """Pixels, range and validity of points given in the ISO 8855 vehicle frame (metres), e.g. a
    lidar sweep ``lidar_vehicle[:, :3]`` (see `ProjectedPoints`). Pure, jit- and vmap-safe."""
    p = jnp.asarray(points_vehicle)
    if p.shape[-1:] != (3,):
        raise ValueError(f"project_points: points_vehicle must have shape (..., 3), got {p.shape}")
    cam = vehicle_to_camera.apply(p.astype(float_dtype(p)))
    uv, ok = camera.project(cam)
    range_m = jnp.sqrt(cam[..., 0] * cam[..., 0] + cam[..., 1] * cam[..., 1] + cam[..., 2] * cam[..., 2])
    return ProjectedPoints(uv=uv, range_m=range_m, valid=ok & camera.contains(uv))


# ------------------------------------------------------------------ rasterising (NumPy, host side)
def _clip_segments(p0: np.ndarray, p1: np.ndarray, width: int, height: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Liang-Barsky clipping of segments ``(N, 2)`` to the image ``[-0.5, W - 0.5] x [-0.5, H - 0.5]``:
    the clipped ends and which segments keep a part inside (none with a non-finite end)."""
    d = p1 - p0
    lo = np.zeros(len(p0))
    hi = np.ones(len(p0))
    keep = np.ones(len(p0), bool)
    for axis, size in ((0, width), (1, height)):
        for q_num, sign in (((p0[:, axis] + 0.5), -1.0), ((size - 0.5 - p0[:, axis]), 1.0)):
            den = sign * d[:, axis]
            parallel = den == 0
            keep &= ~(parallel & (q_num < 0))
            with np.errstate(divide="ignore", invalid="ignore"):
                r = np.where(parallel, 0.0, q_num / np.where(parallel, 1.0, den))
            lo = np.where(~parallel & (den < 0), np.maximum(lo, r), lo)
            hi = np.where(~parallel & (den > 0), np.minimum(hi, r), hi)
    keep &= (lo <= hi) & np.all(np.isfinite(p0), axis=-1) & np.all(np.isfinite(p1), axis=-1)
    # Clamped to the image: the clipped ends lie on it up to rounding, which far ends (1e30 px) make large.
    box_lo, box_hi = np.array([-0.5, -0.5]), np.array([width - 0.5, height - 0.5])
    q0 = np.clip(np.nan_to_num(p0 + lo[:, None] * d), box_lo, box_hi)
    q1 = np.clip(np.nan_to_num(p0 + hi[:, None] * d), box_lo, box_hi)
    return q0, q1, keep


def _nearest(x: np.ndarray) -> np.ndarray:
    """The nearest integer pixel coordinate, halves up (monotone, unlike round-half-even, so points
    sampled at most one pixel apart along an axis leave no gap)."""
    return np.floor(x + 0.5).astype(np.int64)


def _splat(image: np.ndarray, u: np.ndarray, v: np.ndarray, colors: np.ndarray, size: int) -> None:
    """Set the pixels of integer coordinates ``(u, v)`` (and a ``size x size`` square around each)
    to ``colors`` (``(N, 3)`` or ``(3,)``), in order (later points over earlier ones)."""
    h, w = image.shape[:2]
    colors = np.broadcast_to(np.asarray(colors, np.uint8), (len(u), 3))
    offsets = np.arange(size) - (size - 1) // 2
    for du in offsets:
        for dv in offsets:
            uu, vv = u + du, v + dv
            ok = (uu >= 0) & (uu < w) & (vv >= 0) & (vv < h)
            image[vv[ok], uu[ok]] = colors[ok]


def draw_polylines(
    image: UInt8[np.ndarray, "H W 3"],
    uv: Float[ArrayLike, "*batch S 2"],
    drawn: Bool[ArrayLike, "*batch S-1"],
    color: tuple[int, int, int] | UInt8[ArrayLike, "*batch 3"],
    *,
    thickness: int = 1,
) -> UInt8[np.ndarray, "H W 3"]:
    """A copy of ``image`` with the chords ``uv[..., s, :] -> uv[..., s + 1, :]`` where ``drawn``
    (e.g. `BoxEdgePixels`) rasterised in ``color`` (one RGB colour, or one per polyline): every
    pixel whose centre is the rounding of a point on the chord, sampled less than one pixel apart,
    clipped to the image (a chord with a non-finite end is skipped); ``thickness`` pixels wide (a
    square brush). NumPy, no anti-aliasing."""
    out = np.array(image, np.uint8, copy=True)
    h, w = out.shape[:2]
    uv = np.asarray(uv, np.float64)
    drawn = np.asarray(drawn, bool)
    if uv.shape[-1:] != (2,) or drawn.shape != uv.shape[:-2] + (uv.shape[-2] - 1,):
        raise ValueError(f"draw_polylines: uv (..., S, 2) and drawn (..., S - 1) expected, got {uv.shape}, {drawn.shape}")
    col = np.broadcast_to(np.asarray(color, np.uint8)[..., None, :], drawn.shape + (3,))
    p0, p1, c = uv[..., :-1, :][drawn], uv[..., 1:, :][drawn], col[drawn]
    p0, p1, keep = _clip_segments(p0, p1, w, h)
    p0, p1, c = p0[keep], p1[keep], c[keep]
    # Samples strictly less than one pixel apart along the major axis: no gap after rounding.
    steps = np.ceil(np.max(np.abs(p1 - p0), axis=-1)).astype(np.int64) + 2
    seg = np.repeat(np.arange(len(steps)), steps)
    first = np.cumsum(steps) - steps
    k = np.arange(len(seg)) - first[seg]
    f = (k / np.maximum(steps[seg] - 1, 1))[:, None]
    pts = p0[seg] + (p1[seg] - p0[seg]) * f
    _splat(out, _nearest(pts[:, 0]), _nearest(pts[:, 1]), c[seg], int(thickness))
    return out


def draw_points(
    image: UInt8[np.ndarray, "H W 3"],
    uv: Float[ArrayLike, "N 2"],
    valid: Bool[ArrayLike, " N"],
    colors: UInt8[ArrayLike, "N 3"],
    *,
    size: int = 1,
    order: Float[ArrayLike, " N"] | None = None,
) -> UInt8[np.ndarray, "H W 3"]:
    """A copy of ``image`` with each valid point drawn at its nearest pixel as a ``size x size``
    square of its colour; with ``order`` (e.g. the range), points of larger ``order`` are drawn
    first, so nearer points cover farther ones."""
    out = np.array(image, np.uint8, copy=True)
    uv = np.asarray(uv, np.float64).reshape(-1, 2)
    ok = np.asarray(valid, bool).reshape(-1) & np.all(np.abs(uv) < 2.0**31, axis=-1)  # finite, and castable
    colors = np.asarray(colors, np.uint8).reshape(-1, 3)
    idx = np.flatnonzero(ok)
    if order is not None:
        idx = idx[np.argsort(-np.asarray(order, np.float64).reshape(-1)[idx], kind="stable")]
    _splat(out, _nearest(uv[idx, 0]), _nearest(uv[idx, 1]), colors[idx], int(size))
    return out


def draw_rectangles(
    image: UInt8[np.ndarray, "H W 3"],
    xyxy: Int[ArrayLike, "N 4"],
    color: tuple[int, int, int],
    *,
    thickness: int = 1,
) -> UInt8[np.ndarray, "H W 3"]:
    """A copy of ``image`` with the outline of each 2D box ``x1, y1, x2, y2`` (inclusive pixel
    coordinates, as ``box_2d_annotations``) drawn in ``color``, ``thickness`` pixels inwards,
    clipped to the image."""
    out = np.array(image, np.uint8, copy=True)
    h, w = out.shape[:2]
    for x1, y1, x2, y2 in np.asarray(xyxy, np.int64).reshape(-1, 4):
        x1, x2 = sorted((int(x1), int(x2)))
        y1, y2 = sorted((int(y1), int(y2)))
        t = max(1, int(thickness))
        for a0, a1, b0, b1 in ((y1, y1 + t, x1, x2 + 1), (y2 - t + 1, y2 + 1, x1, x2 + 1),
                               (y1, y2 + 1, x1, x1 + t), (y1, y2 + 1, x2 - t + 1, x2 + 1)):
            r0, r1, c0, c1 = max(a0, 0), min(a1, h), max(b0, 0), min(b1, w)
            if r0 < r1 and c0 < c1:
                out[r0:r1, c0:c1] = color
    return out
