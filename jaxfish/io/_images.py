"""Image files, dtype-preserving: PNG (8/16 bit) through jaxfish's own codec (`jaxfish.io._png`:
Up filter, one ISA-L deflate stream; fast inflate, pyspng or OpenImageIO to read), EXR float32/half
(and the other formats) through OpenImageIO.

Library traps handled here (CONVENTIONS §8): 2-D arrays are written as (H, W, 1); pixels are read
with the file's own format (``oiio.UNKNOWN``) so uint8/uint16/half/float survive a round trip;
alpha stays unassociated (RGBA PNGs come back bit-exact, OpenImageIO would premultiply them); a
missing or corrupt file raises `ImageError` naming it; writes are atomic.
"""

from __future__ import annotations

import json
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import OpenImageIO as oiio

from .._errors import ImageError
from ._atomic import atomic_path, atomic_write_bytes
from ._json import regular_file, to_json_text
from ._png import PNG_SIGNATURE, decode_png, encode_png, png_text, read_png_bytes

_WRITABLE = {".png", ".exr", ".tif", ".tiff", ".jpg", ".jpeg"}
PNG_LEVEL = 1
"""Compression level (zlib's 0-9 scale) of the PNGs `write_image` writes by default (1 = fastest
that compresses; ISA-L's level for each is `jaxfish.io._png.ISAL_LEVELS`); the figures are in
``docs/performance.md``."""
PNG_FILTER = 0x20
"""PNG row filter of every written PNG: "Up" (libpng ``PNG_FILTER_UP``; each row minus the row above)."""
_DTYPES = {
    np.dtype(np.uint8): oiio.UINT8,
    np.dtype(np.uint16): oiio.UINT16,
    np.dtype(np.float16): oiio.HALF,
    np.dtype(np.float32): oiio.FLOAT,
}

_SIGNATURES = ((b"\xff\xd8\xff", "JPEG data"), (b"GIF8", "GIF data"), (b"BM", "BMP data"), (b"RIFF", "WebP/RIFF data"),
               (b"v/1\x01", "OpenEXR data"), (b"II*\x00", "TIFF data"), (b"MM\x00*", "TIFF data"))


def _sniff(head: bytes) -> str:
    """What the first bytes of a file that is not a PNG look like."""
    if not head:
        return "an empty file"
    return next((name for sig, name in _SIGNATURES if head.startswith(sig)), "data of another format")


def is_png_level(level: Any) -> bool:
    """Whether ``level`` is a valid zlib level for `write_image` (an integer 0-9, not a bool)."""
    return isinstance(level, int) and not isinstance(level, bool) and 0 <= level <= 9


def read_image(path: str | os.PathLike, *, expect_shape: tuple[int, ...] | None = None,
               lossless: bool = False) -> np.ndarray:
    """Read an image as ``(H, W, C)`` in the file's own dtype (uint8, uint16, float16 or float32).

    ``expect_shape`` (``(H, W)`` or ``(H, W, C)``) raises `ImageError` on a size mismatch.
    ``lossless=True`` (labels, encoded depth): the file must be a PNG (its content, whatever its
    name: a JPEG renamed ``.png`` is refused), else `ImageError` naming it, and its stored samples
    are returned: a palette PNG gives its palette indices ``(H, W, 1)`` uint8 (without
    ``lossless``, its colours, as OpenImageIO reads them). A path that is not a
    regular file (a directory, a FIFO, a device) raises `ImageError` before anything is read.
    """
    path = Path(path)
    try:
        regular_file(path, ImageError, "image file")
    except FileNotFoundError:
        raise ImageError(f"{path}: image file not found") from None
    try:
        with open(path, "rb") as fh:
            head = fh.read(len(PNG_SIGNATURE))
    except OSError as e:
        raise ImageError(f"{path}: cannot read image file ({e.strerror or e})") from None
    pixels = decode_image_bytes(path, read_png_bytes(path) if head == PNG_SIGNATURE else head, lossless=lossless)
    if expect_shape is not None:
        got = pixels.shape[: len(expect_shape)]
        if tuple(got) != tuple(expect_shape):
            raise ImageError(f"{path}: expected an image of shape {tuple(expect_shape)}, got {pixels.shape}")
    return pixels


def decode_image_bytes(path: Path, data: bytes, *, lossless: bool = False) -> np.ndarray:
    """The pixels of the image file ``path`` whose bytes (or at least its first eight) are ``data``:
    PNG bytes are decoded from ``data``, any other format is read from ``path`` by OpenImageIO
    (`read_image`'s rules; ``lossless=True`` refuses anything but a PNG and reads a palette PNG's
    indices)."""
    head = bytes(data[:len(PNG_SIGNATURE)])
    if lossless and head != PNG_SIGNATURE:
        found = _sniff(head)
        raise ImageError(f"{path}: expected a lossless PNG file, found {found} (the PNG signature is missing)")
    if head == PNG_SIGNATURE:
        return decode_png(data, str(path), fallback=lambda: _read_oiio(path), palette_indices=lossless)
    return _read_oiio(path)


def _read_oiio(path: Path) -> np.ndarray:
    """``(H, W, C)`` pixels of ``path`` by OpenImageIO in the file's own format."""
    config = oiio.ImageSpec()
    config.attribute("oiio:UnassociatedAlpha", 1)  # keep RGBA values as stored (no premultiplication)
    inp = oiio.ImageInput.open(str(path), config)
    if inp is None:
        raise ImageError(f"{path}: cannot open image ({oiio.geterror() or 'unknown format'})")
    try:
        spec = inp.spec()
        pixels = inp.read_image(0, 0, 0, spec.nchannels, oiio.UNKNOWN)
        if pixels is None:
            raise ImageError(f"{path}: corrupt or truncated image ({inp.geterror() or oiio.geterror()})")
    finally:
        inp.close()
    err = oiio.geterror()
    pixels = np.asarray(pixels)
    if pixels.ndim == 2:
        pixels = pixels[..., None]
    if pixels.shape[:2] != (spec.height, spec.width):
        raise ImageError(f"{path}: corrupt image (read {pixels.shape}, header says {spec.height}x{spec.width}) {err}")
    return pixels


def write_image(path: str | os.PathLike, pixels: np.ndarray, *, metadata: Mapping[str, Any] | None = None,
                png_level: int = PNG_LEVEL, channel_names: Sequence[str] | None = None,
                exr_compression: str = "zip") -> Path:
    """Write ``(H, W)`` or ``(H, W, C)`` pixels, keeping the dtype (uint8/uint16 PNG, float16/float32
    EXR). ``metadata``: ``{attribute name: JSON-able value}`` stored as JSON text attributes (read
    back with `read_image_metadata`; PNG ``tEXt`` chunks, which OpenImageIO reads as attributes of
    the same name). ``png_level``: compression level 0-9 of a PNG on zlib's scale (default
    `PNG_LEVEL`; 0 stores the rows uncompressed; `jaxfish.io._png.ISAL_LEVELS` maps the others to
    ISA-L's 0-3); every PNG uses the `PNG_FILTER` row filter and one deflate stream (ISA-L, or zlib
    where ``isal`` does not import: other bytes, the same pixels); the same pixels, metadata and
    level always give the same bytes with the same deflate implementation. ``channel_names`` (one per channel, e.g. ``("Z",)`` for an EXR depth map) and
    ``exr_compression`` (OpenEXR's ``"zip"``, ``"none"``, ``"piz"``, ...) apply to EXR files. No
    timestamp is stored: the same arguments always give the same bytes. Atomic: on any error
    nothing is left at ``path``."""
    path = Path(path)
    a, meta = _prepared(path, pixels, metadata, png_level, channel_names)
    if path.suffix.lower() == ".png":
        return atomic_write_bytes(path, encode_png(a, text=meta, png_level=png_level, where=str(path)))
    h, w, c = a.shape
    ext = path.suffix.lower()
    with atomic_path(path) as tmp:
        out = oiio.ImageOutput.create(str(tmp))
        if out is None:
            raise ImageError(f"{path}: cannot create writer ({oiio.geterror()})")
        spec = oiio.ImageSpec(w, h, c, _DTYPES[a.dtype])
        if channel_names is not None:
            spec.channelnames = tuple(str(n) for n in channel_names)
        if ext == ".exr":
            spec.attribute("compression", exr_compression)
        spec.attribute("oiio:UnassociatedAlpha", 1)  # the pixels are written as given
        spec.attribute("DateTime", "")  # no timestamp (OpenEXR's capDate): the same pixels give the same bytes
        for name, value in meta.items():
            spec.attribute(name, value)
        if not out.open(str(tmp), spec):
            raise ImageError(f"{path}: cannot open for writing ({out.geterror()})")
        ok = out.write_image(a)
        out.close()
        if not ok:
            raise ImageError(f"{path}: write failed ({out.geterror()})")
    return path


def png_image_bytes(path: str | os.PathLike, pixels: np.ndarray, *, metadata: Mapping[str, Any] | None = None,
                    png_level: int = PNG_LEVEL) -> bytes:
    """The bytes `write_image` writes to the ``.png`` file ``path`` for ``pixels``, ``metadata``
    and ``png_level`` (nothing is written; ``path`` names the file in errors)."""
    path = Path(path)
    if path.suffix.lower() != ".png":
        raise ImageError(f"{path}: png_image_bytes encodes PNG files, got extension {path.suffix!r}")
    a, meta = _prepared(path, pixels, metadata, png_level, None)
    return encode_png(a, text=meta, png_level=png_level, where=str(path))


def _prepared(path: Path, pixels: np.ndarray, metadata: Mapping[str, Any] | None, png_level: int,
              channel_names: Sequence[str] | None) -> tuple[np.ndarray, dict[str, str]]:
    """`write_image`'s checks: ``(H, W, C)`` C-contiguous pixels in a writable dtype and the
    metadata as JSON text, or `ImageError` naming the file."""
    ext = path.suffix.lower()
    if ext not in _WRITABLE:
        raise ImageError(f"{path}: unsupported image extension {ext!r} (use .png or .exr)")
    a = np.asarray(pixels)
    if a.dtype == np.float64:
        a = a.astype(np.float32)
    if a.dtype == np.bool_:
        a = a.astype(np.uint8) * 255
    if a.dtype not in _DTYPES:
        raise ImageError(f"{path}: unsupported pixel dtype {a.dtype}")
    if ext == ".png" and a.dtype not in (np.uint8, np.uint16):
        raise ImageError(f"{path}: PNG stores uint8/uint16 pixels, got {a.dtype} (use .exr for floats)")
    if not is_png_level(png_level):
        raise ImageError(f"{path}: png_level must be an integer from 0 to 9, got {png_level!r}")
    if a.ndim == 2:
        a = a[..., None]  # OpenImageIO scrambles 2-D arrays (CONVENTIONS §8)
    if a.ndim != 3 or a.shape[0] == 0 or a.shape[1] == 0:
        raise ImageError(f"{path}: expected (H, W) or (H, W, C) pixels, got shape {np.asarray(pixels).shape}")
    a = np.ascontiguousarray(a)
    h, w, c = a.shape
    if channel_names is not None and len(channel_names) != c:
        raise ImageError(f"{path}: {len(channel_names)} channel names for {c} channels")
    return a, metadata_text(path, metadata)


def metadata_text(path: Path, metadata: Mapping[str, Any] | None) -> dict[str, str]:
    """``metadata`` as the text attributes `write_image` stores: each value as one line of JSON
    (`ImageError` naming the file and attribute for a value JSON cannot hold)."""
    return {name: to_json_text(f"{path} (metadata {name!r})", value, error=ImageError).rstrip("\n")
            for name, value in (metadata or {}).items()}


def read_image_metadata(path: str | os.PathLike, name: str) -> Any:
    """The JSON value of the text attribute ``name`` stored by `write_image` (``metadata=``); a
    missing file, attribute or invalid JSON raises `ImageError` naming the file and attribute."""
    path = Path(path)
    try:
        regular_file(path, ImageError, "image file")
    except FileNotFoundError:
        raise ImageError(f"{path}: image file not found") from None
    try:
        with open(path, "rb") as fh:
            head = fh.read(len(PNG_SIGNATURE))
    except OSError as e:
        raise ImageError(f"{path}: cannot read image file ({e.strerror or e})") from None
    if head == PNG_SIGNATURE:
        value = png_text(read_png_bytes(path), str(path)).get(name, "")
    else:
        inp = oiio.ImageInput.open(str(path))
        if inp is None:
            raise ImageError(f"{path}: cannot open ({oiio.geterror()})")
        try:
            value = inp.spec().get_string_attribute(name, "")
        finally:
            inp.close()
    if not value:
        raise ImageError(f"{path}: no '{name}' metadata")
    try:
        return json.loads(value)
    except json.JSONDecodeError as e:
        raise ImageError(f"{path}: metadata '{name}' is not valid JSON ({e})") from e
