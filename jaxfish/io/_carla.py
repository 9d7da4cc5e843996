"""CARLA sensor encodings (0.9.10 - 0.9.16), both directions, as plain NumPy.

- Raw camera images are **BGRA** uint8 ``(H, W, 4)``.
- Depth: ``metres = 1000 (R + 256 G + 256² B) / (256³ - 1)``, planar z-depth along the camera
  axis; far/sky saturates at 1000 m.
- Semantic segmentation: the tag in the **red** channel (0.9.10-0.9.13 tag table by default).
- Instance segmentation (0.9.14+): R = tag, object id = G + 256 B.
- DVS events: structured array ``x <u2, y <u2, t <i8 (nanoseconds), pol ?`` (13 bytes each).
"""

from __future__ import annotations

import numpy as np

from .._constants import DVS_EVENT_DTYPE as DVS_EVENT_DTYPE
from .._constants import FAR_DEPTH_M
from .._errors import ImageError

CARLA_MAX_DEPTH_M = FAR_DEPTH_M
"""Depth that CARLA's 24-bit encoding saturates at (metres): far and sky;
`jaxfish.reprojection.FAR_DEPTH_M`."""
_DEPTH_SCALE = 256**3 - 1


def _check_bgra(bgra: np.ndarray, what: str) -> np.ndarray:
    a = np.asarray(bgra)
    if a.dtype != np.uint8 or a.ndim != 3 or a.shape[-1] not in (3, 4):
        raise ImageError(f"{what}: expected a BGRA uint8 image (H, W, 4), got {a.dtype} {a.shape}")
    return a


def _destination(out: np.ndarray | None, shape: tuple[int, ...], dtype, what: str) -> np.ndarray:
    """``out`` checked to be a writable ``shape`` array of ``dtype`` (a new array when None)."""
    if out is None:
        return np.empty(shape, dtype)
    if out.shape != shape or out.dtype != dtype or not out.flags.writeable:
        raise ValueError(f"{what}: out must be a writable {np.dtype(dtype)} array of shape {shape}, "
                         f"got {out.dtype} {out.shape}")
    return out


def bgra_to_rgb(bgra: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """CARLA BGRA (or BGR) uint8 -> RGB uint8 ``(H, W, 3)``, into ``out`` when given (returned)."""
    a = _check_bgra(bgra, "bgra_to_rgb")
    rgb = _destination(out, a.shape[:2] + (3,), np.uint8, "bgra_to_rgb")
    for c in range(3):  # one strided copy per channel (a reversed-channel view copies byte by byte)
        rgb[..., c] = a[..., 2 - c]
    return rgb


def rgb_to_bgra(rgb: np.ndarray) -> np.ndarray:
    """RGB uint8 ``(H, W, 3)`` -> CARLA BGRA uint8 with alpha 255."""
    a = np.asarray(rgb)
    if a.dtype != np.uint8 or a.ndim != 3 or a.shape[-1] != 3:
        raise ImageError(f"rgb_to_bgra: expected an RGB uint8 image (H, W, 3), got {a.dtype} {a.shape}")
    alpha = np.full(a.shape[:2] + (1,), 255, np.uint8)
    return np.concatenate([a[..., ::-1], alpha], axis=-1)


def decode_depth(bgra: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """CARLA 24-bit encoded depth (BGRA uint8) -> planar z-depth in metres, float32, into ``out``
    when given (returned)."""
    a = _check_bgra(bgra, "decode_depth")
    depth = _destination(out, a.shape[:2], np.float32, "decode_depth")
    # The 24-bit code in integers (exact), then one float64 scaling: the same values as scaling
    # every channel in float64, without converting the whole BGRA array to float64. Read as a
    # big-endian 32-bit word, BGRA bytes are B << 24 | G << 16 | R << 8 | A: shifted right by 8,
    # the code R + 256 G + 256² B.
    if a.shape[-1] == 4:
        code, shift = np.ascontiguousarray(a).view(">u4").reshape(-1), 8
    else:
        code = a[..., 2].astype(np.uint32) + (a[..., 1].astype(np.uint32) << 8) + (a[..., 0].astype(np.uint32) << 16)
        code, shift = code.reshape(-1), 0
    contiguous = depth.flags.c_contiguous
    flat = depth.reshape(-1) if contiguous else np.empty(depth.size, np.float32)
    block = max(1, min(code.size, _DEPTH_BLOCK))
    shifted, scaled = np.empty(block, np.uint32), np.empty(block, np.float64)
    for start in range(0, code.size, block):  # blocks that stay in the cache
        n = min(block, code.size - start)
        np.right_shift(code[start:start + n], shift, out=shifted[:n], dtype=np.uint32)
        np.multiply(shifted[:n], CARLA_MAX_DEPTH_M, out=scaled[:n])
        np.divide(scaled[:n], _DEPTH_SCALE, out=scaled[:n])
        np.copyto(flat[start:start + n], scaled[:n], casting="same_kind")
    if not contiguous:
        depth[...] = flat.reshape(depth.shape)
    return depth


_DEPTH_BLOCK = 1 << 18
"""Pixels `decode_depth` converts at a time (its float64 block stays in the cache)."""


def encode_depth(depth_m: np.ndarray) -> np.ndarray:
    """Planar z-depth in metres -> CARLA 24-bit BGRA uint8 (clipped to [0, 1000] m, rounded to
    the nearest of the 2²⁴ levels, ~6e-5 m apart)."""
    d = np.clip(np.asarray(depth_m, dtype=np.float64), 0.0, CARLA_MAX_DEPTH_M)
    n = np.rint(d / CARLA_MAX_DEPTH_M * _DEPTH_SCALE).astype(np.int64)
    r, g, b = n % 256, (n // 256) % 256, n // 65536
    alpha = np.full_like(n, 255)
    return np.stack([b, g, r, alpha], axis=-1).astype(np.uint8)


def decode_semantic(bgra: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """CARLA semantic segmentation image -> tag map uint8 ``(H, W)`` (the red channel), into
    ``out`` when given (returned)."""
    a = _check_bgra(bgra, "decode_semantic")
    tags = _destination(out, a.shape[:2], np.uint8, "decode_semantic")
    tags[...] = a[..., 2]
    return tags


def encode_semantic(tags: np.ndarray) -> np.ndarray:
    """Tag map ``(H, W)`` -> CARLA semantic BGRA uint8 (tag in red, alpha 255)."""
    t = np.asarray(tags)
    if t.ndim != 2 or t.min(initial=0) < 0 or t.max(initial=0) > 255:
        raise ImageError(f"encode_semantic: expected (H, W) tags in 0..255, got shape {t.shape}")
    z = np.zeros(t.shape, np.uint8)
    return np.stack([z, z, t.astype(np.uint8), np.full(t.shape, 255, np.uint8)], axis=-1)


def decode_instance(bgra: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """CARLA (0.9.14+) instance image -> ``(tag uint8 (H, W), object id uint16 (H, W) = G + 256 B)``."""
    a = _check_bgra(bgra, "decode_instance")
    ids = a[..., 1].astype(np.uint16) + (a[..., 0].astype(np.uint16) << 8)
    return np.ascontiguousarray(a[..., 2]), ids


def encode_instance(tags: np.ndarray, ids: np.ndarray) -> np.ndarray:
    """``(tag (H, W), object id (H, W) < 65536)`` -> CARLA instance BGRA uint8."""
    t = np.asarray(tags)
    i = np.asarray(ids).astype(np.int64)
    if t.shape != i.shape or t.ndim != 2:
        raise ImageError(f"encode_instance: tags and ids must both be (H, W), got {t.shape} and {i.shape}")
    if i.min(initial=0) < 0 or i.max(initial=0) > 65535:
        raise ImageError("encode_instance: ids must be in 0..65535")
    return np.stack(
        [(i >> 8).astype(np.uint8), (i & 255).astype(np.uint8), t.astype(np.uint8), np.full(t.shape, 255, np.uint8)],
        axis=-1,
    )


def decode_dvs(raw: bytes | np.ndarray) -> np.ndarray:
    """CARLA DVS raw buffer -> structured event array (`DVS_EVENT_DTYPE`, t in ns)."""
    if isinstance(raw, np.ndarray) and raw.dtype == DVS_EVENT_DTYPE:
        return raw
    buf = bytes(raw) if not isinstance(raw, bytes) else raw
    if len(buf) % DVS_EVENT_DTYPE.itemsize:
        raise ImageError(f"decode_dvs: buffer of {len(buf)} bytes is not a whole number of 13-byte events")
    return np.frombuffer(buf, dtype=DVS_EVENT_DTYPE).copy()
