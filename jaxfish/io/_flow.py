"""Optical-flow files: Middlebury ``.flo`` and KITTI 16-bit PNG (plus the colour coding PNG).

Both store flow as ``(u, v)`` pixels, u right and v down; jaxfish writes **forward** flow (t-1 ->
t, on the t-1 grid) unless the file name says otherwise (``docs/groundtruth.md``).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from .._errors import ImageError
from ._atomic import atomic_path
from ._images import PNG_LEVEL, read_image, write_image

FLO_TAG = 202021.25
"""The ``.flo`` header tag (float32 202021.25, the bytes "PIEH")."""
KITTI_FLOW_SCALE = 64.0
"""KITTI flow PNG scale and offset: ``value = (stored - 2**15) / 64``."""
KITTI_FLOW_OFFSET = 2**15


def write_flo(path: str | os.PathLike, flow: np.ndarray) -> Path:
    """Write ``(H, W, 2)`` flow as Middlebury ``.flo`` (little-endian float32; atomic)."""
    path = Path(path)
    f = np.asarray(flow, np.float32)
    if f.ndim != 3 or f.shape[-1] != 2:
        raise ImageError(f"{path}: flow must have shape (H, W, 2), got {f.shape}")
    h, w = f.shape[:2]
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        np.asarray([FLO_TAG], "<f4").tofile(fh)
        np.asarray([w, h], "<i4").tofile(fh)
        np.ascontiguousarray(f, dtype="<f4").tofile(fh)
    return path


def read_flo(path: str | os.PathLike) -> np.ndarray:
    """Read a Middlebury ``.flo`` file as ``(H, W, 2)`` float32."""
    path = Path(path)
    if not path.is_file():
        raise ImageError(f"{path}: file missing")
    data = path.read_bytes()
    if len(data) < 12:
        raise ImageError(f"{path}: too short for a .flo header ({len(data)} bytes)")
    tag = np.frombuffer(data[:4], "<f4")[0]
    if tag != np.float32(FLO_TAG):
        raise ImageError(f"{path}: header tag is {tag}, expected {FLO_TAG} ('PIEH'): not a .flo file")
    w, h = (int(v) for v in np.frombuffer(data[4:12], "<i4"))
    if w <= 0 or h <= 0 or len(data) != 12 + 8 * w * h:
        raise ImageError(f"{path}: size field {w} x {h} does not match the {len(data)} bytes of the file")
    return np.frombuffer(data[12:], "<f4").reshape(h, w, 2).astype(np.float32)


def write_kitti_flow(path: str | os.PathLike, flow: np.ndarray, valid: np.ndarray | None = None, *,
                     png_level: int = PNG_LEVEL) -> Path:
    """Write KITTI's 16-bit PNG: channels ``(u, v, valid)`` as uint16 with
    ``stored = round(64 value + 2**15)`` (clipped to the uint16 range, i.e. |flow| < 512 px);
    invalid pixels store 0 in every channel."""
    f = np.asarray(flow)
    if f.ndim != 3 or f.shape[-1] != 2:
        raise ImageError(f"{path}: flow must have shape (H, W, 2), got {f.shape}")
    ok = np.ones(f.shape[:2], bool) if valid is None else np.asarray(valid, bool)
    # Scaling by 64 is exact in the flow's own float type, so rounding there and adding the offset
    # in integers gives float64's result (a float32 sum would round the fraction first).
    f = f if f.dtype in (np.float32, np.float64) else f.astype(np.float64)
    scaled = np.rint(np.clip(f * KITTI_FLOW_SCALE, -KITTI_FLOW_OFFSET - 1, KITTI_FLOW_OFFSET))
    q = np.clip(scaled.astype(np.int32) + KITTI_FLOW_OFFSET, 0, 65535)
    out = np.empty(f.shape[:2] + (3,), np.uint16)
    out[..., :2] = np.where(ok[..., None], q, 0)
    out[..., 2] = ok
    return write_image(path, out, png_level=png_level)


def read_kitti_flow(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """Read a KITTI flow PNG: ``(flow (H, W, 2) float32 pixels, valid (H, W) bool)``."""
    a = read_image(path)
    if a.dtype != np.uint16 or a.ndim != 3 or a.shape[-1] < 3:
        raise ImageError(f"{path}: a KITTI flow PNG has 3 uint16 channels, got {a.dtype} {a.shape}")
    valid = a[..., 2] > 0
    flow = (a[..., :2].astype(np.float32) - KITTI_FLOW_OFFSET) / KITTI_FLOW_SCALE
    return np.where(valid[..., None], flow, 0.0).astype(np.float32), valid
