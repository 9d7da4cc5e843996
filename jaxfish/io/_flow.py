"""Optical-flow files: Middlebury ``.flo`` and KITTI 16-bit PNG (plus the colour coding PNG).

Both store flow as ``(u, v)`` pixels, u right and v down; jaxfish writes **forward** flow (t-1 ->
t, on the t-1 grid) unless the file name says otherwise (``docs/groundtruth.md``).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from .._errors import ImageError
from ._atomic import atomic_path, write_sliced
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
        write_sliced(fh, np.ascontiguousarray(f, dtype="<f4"))
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
    return write_image(path, kitti_flow_pixels(f, valid), png_level=png_level)


def kitti_flow_pixels(flow: np.ndarray, valid: np.ndarray | None = None) -> np.ndarray:
    """The ``(H, W, 3)`` uint16 pixels `write_kitti_flow` stores for ``(H, W, 2)`` flow: ``(u, v)``
    as ``round(64 value + 2**15)`` clipped to 0..65535 (0 where not ``valid``), then ``valid``."""
    f = np.asarray(flow)
    ok = np.ones(f.shape[:2], bool) if valid is None else np.asarray(valid, bool)
    # Scaling by 64 is exact in the flow's own float type, so rounding there and adding the offset
    # in integers gives float64's result (a float32 sum would round the fraction first).
    f = f if f.dtype in (np.float32, np.float64) else f.astype(np.float64)
    out = np.empty(f.shape[:2] + (3,), np.uint16)
    out[..., 2] = ok
    keep = ok.astype(np.int32)
    rows = max(1, _KITTI_BLOCK // max(1, f.shape[1]))
    scaled = np.empty((rows, f.shape[1]), f.dtype)
    q = np.empty((rows, f.shape[1]), np.int32)
    for r in range(0, f.shape[0], rows):  # row blocks that stay in the cache, one channel at a time
        n = min(rows, f.shape[0] - r)
        s, qn = scaled[:n], q[:n]
        for c in range(2):
            np.multiply(f[r:r + n, :, c], KITTI_FLOW_SCALE, out=s)
            np.clip(s, -KITTI_FLOW_OFFSET - 1, KITTI_FLOW_OFFSET, out=s)
            np.rint(s, out=s)
            with np.errstate(invalid="ignore"):  # NaN: any integer, clipped, and stored only where valid
                np.copyto(qn, s, casting="unsafe")
            qn += KITTI_FLOW_OFFSET
            np.clip(qn, 0, 65535, out=qn)
            qn *= keep[r:r + n]  # 0 where not valid
            out[r:r + n, :, c] = qn
    return out


_KITTI_BLOCK = 1 << 15
"""Pixels per block of `kitti_flow_pixels`."""


def read_kitti_flow(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """Read a KITTI flow PNG: ``(flow (H, W, 2) float32 pixels, valid (H, W) bool)``."""
    a = read_image(path)
    if a.dtype != np.uint16 or a.ndim != 3 or a.shape[-1] < 3:
        raise ImageError(f"{path}: a KITTI flow PNG has 3 uint16 channels, got {a.dtype} {a.shape}")
    valid = a[..., 2] > 0
    flow = (a[..., :2].astype(np.float32) - KITTI_FLOW_OFFSET) / KITTI_FLOW_SCALE
    return np.where(valid[..., None], flow, 0.0).astype(np.float32), valid
