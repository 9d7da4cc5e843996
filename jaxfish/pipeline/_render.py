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
    np.rint(x, out=x)
    np.clip(x, np.float32(0), np.float32(1023), out=x)  # float32 bounds: Python ints take a slow path
    x[~((d > 0) & (d < FAR_DEPTH_M - 1.0))] = 1024  # the table's black entry (NaN depths included)
    idx = x.astype(np.int32)
    # One uint8 gather per channel (a 3-byte gather per pixel is slower).
    table = _depth_table()
    out = np.empty(d.shape + (3,), np.uint8)
    for c in range(3):
        out[..., c] = table[c].take(idx)
    return out


@functools.cache
def _depth_ramp() -> np.ndarray:
    """The 1024 x 3 uint8 colour table of `depth_to_color` (far -> near)."""
    ramp = np.linspace(0.0, len(_MAGMA) - 1, 1024)
    return np.rint(np.stack([np.interp(ramp, np.arange(len(_MAGMA)), _MAGMA[:, c]) for c in range(3)], -1)).astype(np.uint8)


@functools.cache
def _depth_table() -> np.ndarray:
    """`_depth_ramp` channel by channel ``(3, 1025)``, with black at index 1024."""
    table = np.zeros((3, 1025), np.uint8)
    table[:, :1024] = _depth_ramp().T
    return table


def events_color(events: np.ndarray, *, width: int, height: int) -> UInt8[np.ndarray, "H W 3"]:
    """NumPy twin of `jaxfish.groundtruth.events_to_color` (no recompilation per event count):
    white background, blue ``(0, 0, 255)`` where a pixel's events sum to a net positive polarity,
    red ``(255, 0, 0)`` net negative. ``events``: CARLA (``pol``) or tonic (``p``) dtype.
    Returns ``(height, width, 3)`` uint8."""
    ev = np.asarray(events)
    x, y = ev["x"], ev["y"]
    pol = ev["pol"] if "pol" in (ev.dtype.names or ()) else ev["p"] > 0
    idx = y.astype(np.intp) * width + x
    signed = x.dtype.kind != "u" or y.dtype.kind != "u"  # CARLA's are unsigned: no minimum to check
    if x.size and (int(x.max()) >= width or int(y.max()) >= height or (signed and (int(x.min()) < 0 or int(y.min()) < 0))):
        ok = (x >= 0) & (x < width) & (y >= 0) & (y < height)
        idx, pol = idx[ok], pol[ok]
    # Each pixel's negative and positive events counted in one integer pass (slot 2 i + polarity),
    # then one uint8 plane per channel: R = 255 unless net positive, G = 255 where no net
    # polarity, B = 255 unless net negative.
    slot = idx * 2
    slot += pol
    counts = np.bincount(slot, minlength=2 * width * height).reshape(height, width, 2)
    pos, neg = counts[..., 1] > counts[..., 0], counts[..., 1] < counts[..., 0]
    out = np.empty((height, width, 3), np.uint8)
    out[..., 0] = (~pos).view(np.uint8) * np.uint8(255)
    out[..., 1] = (~(pos | neg)).view(np.uint8) * np.uint8(255)
    out[..., 2] = (~neg).view(np.uint8) * np.uint8(255)
    return out
