"""Colour renderings of ground truth on the host (NumPy): depth and events."""

from __future__ import annotations

import functools

import numpy as np
from jaxtyping import Float, UInt8

from ..reprojection import FAR_DEPTH_M

DEPTH_COLOR_RANGE_M = (0.5, 100.0)
"""Range (metres) spanned by the depth colour map: nearer is brightest, farther darkest."""
_MAGMA = np.asarray([[0, 0, 4], [59, 15, 112], [140, 41, 129], [222, 73, 104], [254, 159, 109], [252, 253, 191]], np.float64)


def depth_to_color(depth_m: Float[np.ndarray, "H W"]) -> UInt8[np.ndarray, "H W 3"]:
    """Colour rendering of a depth map (``depth_maps/colormap``): magma-like ramp on log depth over
    `DEPTH_COLOR_RANGE_M` (near = bright yellow, far = dark purple); 0 (no ray) and the far / sky
    value (`jaxfish.reprojection.FAR_DEPTH_M`) are black. ``(H, W)`` metres -> ``(H, W, 3)`` uint8."""
    d = np.asarray(depth_m, np.float32)
    lo, hi = DEPTH_COLOR_RANGE_M
    # float32: at most one step of the 1024-step ramp from a float64 computation.
    scale = np.float32(1023.0 / (np.log(hi) - np.log(lo)))
    x = np.float32(1023.0) - (np.log(np.clip(d, np.float32(lo), np.float32(hi))) - np.float32(np.log(lo))) * scale
    idx = np.clip(np.rint(x), 0, 1023).astype(np.intp)
    # One 3-byte gather per pixel (a row gather of the (1024, 3) table is slower).
    out = _depth_ramp().view("V3").reshape(-1)[idx].view(np.uint8).reshape(idx.shape + (3,))
    out[~((d > 0) & (d < FAR_DEPTH_M - 1.0))] = 0
    return out


@functools.cache
def _depth_ramp() -> np.ndarray:
    """The 1024 x 3 uint8 colour table of `depth_to_color` (far -> near)."""
    ramp = np.linspace(0.0, len(_MAGMA) - 1, 1024)
    return np.rint(np.stack([np.interp(ramp, np.arange(len(_MAGMA)), _MAGMA[:, c]) for c in range(3)], -1)).astype(np.uint8)


def events_color(events: np.ndarray, *, width: int, height: int) -> UInt8[np.ndarray, "H W 3"]:
    """NumPy twin of `jaxfish.groundtruth.events_to_color` (no recompilation per event count):
    white background, blue ``(0, 0, 255)`` where a pixel's events sum to a net positive polarity,
    red ``(255, 0, 0)`` net negative. ``events``: CARLA (``pol``) or tonic (``p``) dtype.
    Returns ``(height, width, 3)`` uint8."""
    ev = np.asarray(events)
    x, y = ev["x"], ev["y"]
    pol = ev["pol"] if "pol" in (ev.dtype.names or ()) else ev["p"] > 0
    idx = y.astype(np.intp) * width + x
    if x.size and (int(x.min()) < 0 or int(y.min()) < 0 or int(x.max()) >= width or int(y.max()) >= height):
        ok = (x >= 0) & (x < width) & (y >= 0) & (y < height)
        idx, pol = idx[ok], pol[ok]
    # Net polarity per pixel (float64 sums of +-1: exact), then one 3-byte gather per pixel.
    net = np.bincount(idx, weights=np.where(pol, 1.0, -1.0), minlength=width * height)
    key = (net > 0).view(np.uint8) + np.uint8(2) * (net < 0).view(np.uint8)
    return _EVENT_COLORS.view("V3").reshape(-1)[key].view(np.uint8).reshape(height, width, 3)


_EVENT_COLORS = np.asarray([[255, 255, 255], [0, 0, 255], [255, 0, 0]], np.uint8)
"""`events_color`'s colours: no net polarity (white), net positive (blue), net negative (red)."""
