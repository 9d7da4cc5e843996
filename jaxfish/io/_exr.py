"""Uncompressed one-channel float32 scanline OpenEXR files, encoded with NumPy: the bytes
OpenImageIO / OpenEXR write for the same image and attributes (tested), in one buffer."""

from __future__ import annotations

import struct
from collections.abc import Mapping

import numpy as np

_MAGIC_VERSION = struct.pack("<iI", 20000630, 2)  # single-part scanline, short names
_FLOAT = 2  # OpenEXR's pixel type FLOAT


def _attribute(name: str, kind: str, value: bytes) -> bytes:
    return name.encode() + b"\0" + kind.encode() + b"\0" + struct.pack("<i", len(value)) + value


def exr_z_bytes(depth: np.ndarray, text: Mapping[str, str] | None = None) -> bytes:
    """An uncompressed scanline OpenEXR of the ``(H, W)`` float32 ``depth`` as channel ``Z``, with
    the string attributes ``text`` (names up to 31 bytes, sorted among the required attributes as
    OpenEXR sorts its header): OpenEXR's required attributes (data and display windows from 0,
    increasing lines, pixel aspect 1, screen window centre 0 and width 1), the offset table, one
    line per block."""
    d = np.ascontiguousarray(depth, "<f4")
    if d.ndim != 2 or 0 in d.shape:
        raise ValueError(f"exr_z_bytes: expected a non-empty (H, W) map, got shape {d.shape}")
    h, w = d.shape
    window = struct.pack("<iiii", 0, 0, w - 1, h - 1)
    attrs = {
        "channels": _attribute("channels", "chlist", b"Z\0" + struct.pack("<iB3xii", _FLOAT, 0, 1, 1) + b"\0"),
        "compression": _attribute("compression", "compression", b"\0"),
        "dataWindow": _attribute("dataWindow", "box2i", window),
        "displayWindow": _attribute("displayWindow", "box2i", window),
        "lineOrder": _attribute("lineOrder", "lineOrder", b"\0"),
        "pixelAspectRatio": _attribute("pixelAspectRatio", "float", struct.pack("<f", 1.0)),
        "screenWindowCenter": _attribute("screenWindowCenter", "v2f", struct.pack("<ff", 0.0, 0.0)),
        "screenWindowWidth": _attribute("screenWindowWidth", "float", struct.pack("<f", 1.0)),
    }
    for name, value in (text or {}).items():
        if name in attrs or not 0 < len(name.encode()) <= 31 or "\0" in name:
            raise ValueError(f"exr_z_bytes: attribute name {name!r} is taken, empty or longer than 31 bytes")
        attrs[name] = _attribute(name, "string", value.encode())
    header = _MAGIC_VERSION + b"".join(attrs[k] for k in sorted(attrs, key=str.encode)) + b"\0"
    line = 8 + 4 * w
    first = len(header) + 8 * h
    out = np.empty(first + h * line, np.uint8)
    out[:len(header)] = np.frombuffer(header, np.uint8)
    out[len(header):first].view("<u8")[:] = first + line * np.arange(h, dtype=np.uint64)
    blocks = out[first:].reshape(h, line)
    blocks[:, :4].view("<i4")[:, 0] = np.arange(h, dtype=np.int32)
    blocks[:, 4:8].view("<i4")[:, 0] = 4 * w
    blocks[:, 8:].view("<f4")[:] = d
    return out.tobytes()
