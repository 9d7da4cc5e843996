"""PNG files at memory speed: an encoder (one filter, one deflate stream) and a decoder with a NumPy
fast path for the files it writes.

**Encoder** (`encode_png`). 8- or 16-bit grey (``C = 1``), grey + alpha (2), RGB (3) or RGBA (4),
never interlaced. Every row carries the "Up" filter (filter byte 2: each byte minus the byte above;
for 16-bit samples bytewise on the big-endian bytes), and the filtered rows are compressed as ONE
zlib stream (`ISAL_LEVELS`: ISA-L through PyPI's ``isal`` where it imports, on states placed by
`jaxfish.io._deflate` so that the bytes depend on the input only; else Python's ``zlib``), split
into IDAT chunks of at most `IDAT_CHUNK_BYTES`. Chunks: IHDR, one ``tEXt`` per
metadata entry (``keyword NUL text``, Latin-1; ``iTXt`` for text outside Latin-1), the IDATs, IEND.
No time, colour-space or gamma chunk: the same pixels, text and level give the same bytes with the
same deflate implementation.

**Decoder** (`decode_png`). Every chunk's CRC is checked and the IHDR validated; then

- 8/16-bit grey, grey + alpha, RGB or RGBA, not interlaced, no ``tRNS``, every row filtered None or
  Up: inflate and a running sum of the rows in uint8 (wrapping modulo 256, which is the Up filter's
  inverse). The inflate is libdeflate's (PyPI ``deflate``) for a stream at least
  `LIBDEFLATE_MIN_RATIO` times smaller than its rows (label maps, encoded depth: faster than
  ISA-L on their long matches), ISA-L's for the others (a textured render: ISA-L is
  slightly faster there), zlib's where neither imports; a stream libdeflate refuses (corrupt, or
  longer than the image) is inflated again by ISA-L or zlib, whose errors name the file;
- the same kinds at 8 bits with other filters or Adam7 interlacing: ``pyspng`` (libspng) where it
  imports;
- anything else (16 bits with other filters, palettes, 1/2/4-bit grey, ``tRNS``, or no pyspng):
  OpenImageIO.

With ``palette_indices=True`` a palette PNG (colour type 3, 1/2/4/8 bits) gives its palette indices
``(H, W, 1)`` uint8 instead of its colours: its IDAT data, which holds the indices as samples of
its bit depth, is decoded as a grey PNG of that depth (the fast path or pyspng at 8 bits, pyspng
at 1/2/4 bits, whose grey samples are scaled by bit replication and are divided back); ``PLTE``
and ``tRNS`` do not apply to indices.

Malformed files raise `ImageError` naming the file and the chunk or field.
"""

from __future__ import annotations

import struct
import zlib
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .._errors import ImageError
from . import _deflate

try:  # ISA-L: the same deflate format, several times faster than zlib at its fastest level
    from isal import isal_zlib as _isal_zlib
except ImportError:  # pragma: no cover - isal is a dependency; zlib is the documented fallback
    _isal_zlib = None

try:  # libdeflate: the fastest inflate of highly compressible streams
    import deflate as _libdeflate
except ImportError:  # pragma: no cover - deflate is a dependency; ISA-L or zlib inflate instead
    _libdeflate = None

try:
    import pyspng as _pyspng
except ImportError:  # pragma: no cover - pyspng is a dependency; OpenImageIO is the fallback
    _pyspng = None

_crc32 = zlib.crc32 if _isal_zlib is None else _isal_zlib.crc32  # ISA-L's: the same CRC, vectorised
_INFLATE_ERRORS: tuple[type[Exception], ...] = (zlib.error,) if _isal_zlib is None else (zlib.error, _isal_zlib.error)

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
"""The first eight bytes of every PNG file."""
IDAT_CHUNK_BYTES = 1 << 30
"""The largest IDAT chunk `encode_png` writes (the format allows 2**31 - 1 bytes)."""
FILTER_UP = 2
"""The PNG row filter byte of every row `encode_png` writes ("Up")."""
ISAL_LEVELS = {0: 0, 1: 1, 2: 1, 3: 1, 4: 2, 5: 2, 6: 2, 7: 3, 8: 3, 9: 3}
"""ISA-L level (0-3) of each ``png_level`` (zlib's 0-9 scale). ``png_level`` 0 is special: the
stream is stored uncompressed (zlib level 0, as with libpng), whichever deflate is used. Levels 1-3
use ISA-L 1 (on a noisy rendered frame it gives zlib level 1's size several times faster), 4-6
ISA-L 2, 7-9 ISA-L 3 (smaller files, slower). Without ISA-L, zlib runs at ``png_level`` itself."""
_COLOR_TYPES = {1: 0, 2: 4, 3: 2, 4: 6}  # channels -> IHDR colour type
_CHANNELS = {0: 1, 2: 3, 3: 1, 4: 2, 6: 4}  # IHDR colour type -> samples per pixel
_BIT_DEPTHS = {0: (1, 2, 4, 8, 16), 2: (8, 16), 3: (1, 2, 4, 8), 4: (8, 16), 6: (8, 16)}


def deflate_name() -> str:
    """The deflate implementation `encode_png` uses: ``"isal <version>"`` (ISA-L on placed states,
    `jaxfish.io._deflate`), ``"isal <version> unplaced"`` (where states cannot be placed: the bytes
    may then vary with the calling thread) or ``"zlib <version>"``. The bytes of a PNG depend on it;
    the pixels never do."""
    if _isal_zlib is not None:
        import isal

        return f"isal {isal.__version__}" + ("" if _deflate.DETERMINISTIC else " unplaced")
    return f"zlib {zlib.ZLIB_RUNTIME_VERSION}"


def _compress(data, png_level: int) -> bytes:
    if png_level == 0 or _isal_zlib is None:
        return zlib.compress(data, png_level)
    return _deflate.compress(data, ISAL_LEVELS[png_level])


LIBDEFLATE_MIN_RATIO = 4
"""A zlib stream whose inflated size is at least this many times its own is inflated by libdeflate
(module docstring)."""
DEFLATE_MAX_RATIO = 1032
"""The most bytes deflate inflates from one byte of stream (a 258-byte match in two bits): the
output buffer is the smaller of this bound and the image's size, so that an IHDR claiming a huge
image over a small IDAT reads as a truncated file instead of allocating the image."""


def uses_libdeflate(size: int, stream_bytes: int) -> bool:
    """Whether `decode_png` inflates a zlib stream of ``stream_bytes`` holding ``size`` bytes of
    filtered rows with libdeflate (module docstring)."""
    return _libdeflate is not None and size >= LIBDEFLATE_MIN_RATIO * stream_bytes


def _decompress(data: bytes, size: int) -> bytes | bytearray:
    """The inflated zlib stream ``data`` of an image whose filtered rows hold ``size`` bytes (the
    stream's own length when it differs: the caller checks)."""
    buffer = max(min(size, DEFLATE_MAX_RATIO * len(data) + 64), 1)
    if uses_libdeflate(size, len(data)):
        try:
            return _libdeflate.zlib_decompress(data, buffer)
        except _libdeflate.DeflateError:
            pass  # corrupt, or longer than ``size`` bytes: the inflate below reads it or says why not
    if _isal_zlib is not None:
        return _isal_zlib.decompress(data, bufsize=buffer)  # a first buffer: a longer stream still inflates whole
    return zlib.decompress(data, bufsize=buffer)


def _chunk(kind: bytes, data: bytes | memoryview) -> bytes:
    crc = _crc32(data, _crc32(kind))
    return b"".join((struct.pack(">I", len(data)), kind, data, struct.pack(">I", crc)))


def _text_chunk(where: str, keyword: str, text: str) -> bytes:
    try:
        key = keyword.encode("latin-1")
    except UnicodeEncodeError:
        key = b""
    if not 1 <= len(key) <= 79 or b"\0" in key or key != key.strip() or b"  " in key:
        raise ImageError(f"{where}: metadata name {keyword!r} is not a PNG text keyword "
                         "(1-79 Latin-1 characters, no leading, trailing or double spaces)")
    try:
        return _chunk(b"tEXt", key + b"\0" + text.encode("latin-1"))
    except UnicodeEncodeError:  # international text: uncompressed iTXt, no language tag
        return _chunk(b"iTXt", key + b"\0\0\0\0\0" + text.encode("utf-8"))


def encode_png(pixels: np.ndarray, *, text: Mapping[str, str] | None = None, png_level: int = 1,
               where: str = "PNG") -> bytes:
    """The bytes of a PNG of ``pixels`` (``(H, W, C)`` uint8 or uint16, ``C`` 1-4), with each
    ``text`` entry as a text chunk (keyword -> text) and the zlib stream at ``png_level`` 0-9
    (`ISAL_LEVELS`). ``where`` names the file in errors. See the module docstring for the layout."""
    a = np.asarray(pixels)
    if a.ndim != 3 or a.shape[2] not in _COLOR_TYPES or a.dtype not in (np.uint8, np.uint16):
        raise ImageError(f"{where}: a PNG stores (H, W, C) uint8/uint16 pixels with C = 1-4, got {a.dtype} {a.shape}")
    h, w, c = a.shape
    if not (0 < h < 2**31 and 0 < w < 2**31):
        raise ImageError(f"{where}: image size {w}x{h} does not fit a PNG (1 to 2**31 - 1 pixels a side)")
    depth = 8 * a.dtype.itemsize
    if depth == 16:
        a = a.astype(">u2", copy=False)
    rows = np.ascontiguousarray(a).view(np.uint8).reshape(h, w * c * a.dtype.itemsize)
    filtered = np.empty((h, rows.shape[1] + 1), np.uint8)
    filtered[:, 0] = FILTER_UP
    filtered[0, 1:] = rows[0]  # the row above the first is zero
    np.subtract(rows[1:], rows[:-1], out=filtered[1:, 1:])  # uint8 arithmetic wraps modulo 256
    stream = _compress(filtered, png_level)
    parts = [PNG_SIGNATURE, _chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, depth, _COLOR_TYPES[c], 0, 0, 0))]
    parts += [_text_chunk(where, k, v) for k, v in (text or {}).items()]
    view = memoryview(stream)
    parts += [_chunk(b"IDAT", view[i:i + IDAT_CHUNK_BYTES]) for i in range(0, max(len(stream), 1), IDAT_CHUNK_BYTES)]
    parts.append(_chunk(b"IEND", b""))
    return b"".join(parts)


@dataclass(frozen=True)
class PngHeader:
    """A PNG's IHDR fields (``interlace`` 1 = Adam7) and whether it has a ``tRNS`` chunk."""

    width: int
    height: int
    bit_depth: int
    color_type: int
    interlace: int
    transparency: bool


def _chunks(data: bytes, where: str):
    """``(type, payload)`` of every chunk up to IEND, each CRC-checked."""
    if data[:8] != PNG_SIGNATURE:
        raise ImageError(f"{where}: not a PNG file (the PNG signature is missing)")
    view = memoryview(data)
    p, n = 8, len(data)
    while True:
        if p + 8 > n:
            raise ImageError(f"{where}: truncated PNG (the file ends at byte {n} before the IEND chunk)")
        length, kind = struct.unpack(">I4s", data[p:p + 8])
        name = kind.decode("latin-1")
        if length > 2**31 - 1 or not kind.isalpha():
            raise ImageError(f"{where}: corrupt PNG: chunk at byte {p} has type {name!r} and length {length}")
        end = p + 12 + length
        if end > n:
            raise ImageError(f"{where}: truncated PNG (chunk {name} at byte {p} needs {length} bytes, the file ends at byte {n})")
        payload = view[p + 8:p + 8 + length]
        (crc,) = struct.unpack(">I", data[end - 4:end])
        if _crc32(payload, _crc32(kind)) != crc:
            raise ImageError(f"{where}: corrupt PNG: bad CRC in chunk {name} at byte {p}")
        yield kind, payload
        if kind == b"IEND":
            return
        p = end


def _header(payload: bytes, where: str) -> PngHeader:
    if len(payload) != 13:
        raise ImageError(f"{where}: bad IHDR: {len(payload)} bytes, expected 13")
    w, h, depth, ctype, comp, filt, inter = struct.unpack(">IIBBBBB", payload)
    for field, value, ok in (("width", w, 0 < w < 2**31), ("height", h, 0 < h < 2**31),
                             ("colour type", ctype, ctype in _BIT_DEPTHS),
                             ("compression method", comp, comp == 0), ("filter method", filt, filt == 0),
                             ("interlace method", inter, inter in (0, 1))):
        if not ok:
            raise ImageError(f"{where}: bad IHDR: field '{field}' is {value}")
    if depth not in _BIT_DEPTHS[ctype]:
        raise ImageError(f"{where}: bad IHDR: field 'bit depth' is {depth}, unsupported for colour type {ctype} "
                         f"(allowed: {', '.join(map(str, _BIT_DEPTHS[ctype]))})")
    return PngHeader(w, h, depth, ctype, inter, False)


@dataclass(frozen=True)
class ParsedPng:
    """The header, concatenated IDAT payload (a view of the file's bytes when it has one IDAT chunk)
    and text entries of a PNG file."""

    header: PngHeader
    idat: bytes | memoryview
    text: dict[str, str]


def parse_png(data: bytes, where: str = "PNG", *, pixels: bool = True) -> ParsedPng:
    """Check every chunk of a PNG (CRCs, IHDR first, IDAT present, IEND) and collect its header,
    IDAT data (``pixels=False``: skipped) and text chunks (``tEXt``, ``zTXt``, ``iTXt``; the first
    of each keyword). `ImageError` names the file and chunk on any fault."""
    header = None
    idat: list[bytes] = []
    text: dict[str, str] = {}
    trns = False
    for kind, payload in _chunks(data, where):
        if header is None:
            if kind != b"IHDR":
                raise ImageError(f"{where}: bad PNG: the first chunk is {kind.decode('latin-1')}, expected IHDR")
            header = _header(bytes(payload), where)
        elif kind == b"IDAT":
            if pixels:
                idat.append(payload)
            else:
                idat.append(b"")
        elif kind == b"tRNS":
            trns = True
        elif kind in (b"tEXt", b"zTXt", b"iTXt"):
            key, value = _text(kind, payload, where)
            text.setdefault(key, value)
    assert header is not None  # _chunks yields at least IEND, and the first chunk was checked
    if not idat:
        raise ImageError(f"{where}: bad PNG: no IDAT chunk (no pixel data)")
    return ParsedPng(PngHeader(header.width, header.height, header.bit_depth, header.color_type, header.interlace,
                               trns), idat[0] if len(idat) == 1 else b"".join(idat), text)


def _text(kind: bytes, payload: bytes, where: str) -> tuple[str, str]:
    name = kind.decode("latin-1")
    key, sep, rest = bytes(payload).partition(b"\0")
    if not sep:
        raise ImageError(f"{where}: corrupt PNG: chunk {name} has no keyword separator")
    try:
        if kind == b"tEXt":
            return key.decode("latin-1"), rest.decode("latin-1")
        if kind == b"zTXt":
            return key.decode("latin-1"), zlib.decompress(rest[1:]).decode("latin-1")
        compressed, rest = rest[0], rest[2:]
        _lang, _, rest = rest.partition(b"\0")
        _translated, _, rest = rest.partition(b"\0")
        return key.decode("latin-1"), (zlib.decompress(rest) if compressed else rest).decode("utf-8")
    except (zlib.error, UnicodeDecodeError, IndexError) as e:
        raise ImageError(f"{where}: corrupt PNG: chunk {name} ({key.decode('latin-1')!r}): {e}") from None


def png_text(data: bytes, where: str = "PNG") -> dict[str, str]:
    """The text entries (``keyword -> text``) of a PNG's ``tEXt``/``zTXt``/``iTXt`` chunks."""
    return parse_png(data, where, pixels=False).text


UNFILTER_BLOCK_ROWS = 32
"""Rows `_unfilter_up` sums at once when every row is filtered Up: the running sums of all blocks
of this many rows advance together, one NumPy call per row of a block, and then each block adds
the last row of the block before it, one call per block (about 70 calls for a 1152-row image
instead of one per row)."""


def _unfilter_up(filtered: np.ndarray) -> np.ndarray:
    """Inverse of rows filtered None (0) or Up (2): a running sum of rows, modulo 256.
    ``filtered``: ``(H, 1 + row bytes)`` uint8, each row's filter byte first; returns the
    ``(H, row bytes)`` unfiltered rows."""
    d = filtered[:, 1:]
    out = np.empty_like(d)
    if d.shape[0] == 0:
        return out
    if np.all(filtered[1:, 0] == FILTER_UP):  # Up on the first row adds a zero row: a None row alike
        return _running_rows(d, out)
    out[0] = d[0]
    add, prev = np.add, out[0]
    # Iterating yields the row views with less overhead per row than indexing.
    for mode, row, unfiltered in zip(filtered[1:, 0].tolist(), d[1:], out[1:], strict=True):
        if mode:
            add(prev, row, out=unfiltered)
        else:
            unfiltered[...] = row
        prev = unfiltered
    return out


def _running_rows(d: np.ndarray, out: np.ndarray) -> np.ndarray:
    """``out[i] = d[0] + ... + d[i]`` (uint8, modulo 256) for ``d`` of shape ``(H, N)``, in blocks
    of `UNFILTER_BLOCK_ROWS` rows (``out`` returned)."""
    k = UNFILTER_BLOCK_ROWS
    blocks = d.shape[0] // k
    whole = blocks * k
    if blocks:
        src, dst = d[:whole].reshape(blocks, k, -1), out[:whole].reshape(blocks, k, -1)
        dst[:, 0] = src[:, 0]
        for j in range(1, k):  # the running sum inside every block at once
            np.add(dst[:, j - 1], src[:, j], out=dst[:, j])
        for b in range(1, blocks):  # then each block continues the one before it
            np.add(dst[b], dst[b - 1, -1], out=dst[b])
    else:
        out[0] = d[0]
    for i in range(max(whole, 1), d.shape[0]):  # the rows after the last whole block
        np.add(out[i - 1], d[i], out=out[i])
    return out


def _palette_as_grey(png: ParsedPng) -> bytes:
    """A grey PNG of the bit depth of the palette PNG ``png`` whose samples are its palette indices:
    the same IDAT data (the rows, filters and interlacing are those of a grey image of that depth),
    with only the IHDR, IDAT and IEND chunks."""
    hd = png.header
    ihdr = struct.pack(">IIBBBBB", hd.width, hd.height, hd.bit_depth, 0, 0, 0, hd.interlace)
    view = memoryview(png.idat)
    idat = [_chunk(b"IDAT", view[i:i + IDAT_CHUNK_BYTES]) for i in range(0, max(len(view), 1), IDAT_CHUNK_BYTES)]
    return b"".join([PNG_SIGNATURE, _chunk(b"IHDR", ihdr), *idat, _chunk(b"IEND", b"")])


def _palette_indices(png: ParsedPng, where: str) -> np.ndarray:
    """The ``(H, W, 1)`` uint8 palette indices of the palette PNG ``png`` (module docstring)."""
    hd = png.header
    grey = _palette_as_grey(png)
    if hd.bit_depth == 8:
        return decode_png(grey, where)
    if _pyspng is None:
        raise ImageError(f"{where}: reading the indices of a {hd.bit_depth}-bit palette PNG needs pyspng")
    try:
        samples = _pyspng.load(grey)
    except Exception as e:  # libspng's message, e.g. "IDAT stream error"
        raise ImageError(f"{where}: corrupt PNG ({e})") from None
    scale = 255 // ((1 << hd.bit_depth) - 1)  # libspng replicates the bits of 1/2/4-bit grey samples
    return (samples.reshape(hd.height, hd.width, 1) // scale).astype(np.uint8)


def decode_png(data: bytes, where: str = "PNG", *, fallback=None, palette_indices: bool = False) -> np.ndarray:
    """Pixels ``(H, W, C)`` (uint8 or uint16, ``C`` = the file's samples per pixel) of PNG bytes.
    ``fallback``: a function of nothing returning the pixels by OpenImageIO, for the files neither
    the fast path nor pyspng decodes (module docstring); without one those raise `ImageError`.
    ``palette_indices=True``: a palette PNG gives its indices ``(H, W, 1)`` uint8, not its colours."""
    png = parse_png(data, where)
    hd = png.header
    if palette_indices and hd.color_type == 3:
        return _palette_indices(png, where)
    channels = _CHANNELS[hd.color_type]
    simple = hd.color_type != 3 and hd.bit_depth in (8, 16) and not hd.transparency
    if not simple:
        if fallback is None:
            raise ImageError(f"{where}: PNG colour type {hd.color_type} at {hd.bit_depth} bits is not decoded here")
        return fallback()
    row = hd.width * channels * hd.bit_depth // 8
    if hd.interlace == 0:
        size = hd.height * (row + 1)
        try:
            raw = _decompress(png.idat, size)
        except _INFLATE_ERRORS as e:
            raise ImageError(f"{where}: corrupt PNG: the IDAT data does not inflate ({e})") from None
        if len(raw) < size:
            raise ImageError(f"{where}: truncated PNG: the IDAT data holds {len(raw)} bytes, "
                             f"the IHDR ({hd.width}x{hd.height}) needs {size}")
        filtered = np.frombuffer(raw, np.uint8, size).reshape(hd.height, row + 1)
        modes = filtered[:, 0]
        if int(modes.max()) > 4:
            bad = int(np.argmax(modes > 4))
            raise ImageError(f"{where}: corrupt PNG: row {bad} has filter type {int(modes[bad])} (0-4 allowed)")
        if np.all((modes == 0) | (modes == FILTER_UP)):
            out = _unfilter_up(filtered)
            if hd.bit_depth == 16:
                out = out.view(">u2").astype(np.uint16)
            return out.reshape(hd.height, hd.width, channels)
    if _pyspng is not None and hd.bit_depth == 8:  # pyspng gives 16-bit grey/RGB an alpha channel
        try:
            out = _pyspng.load(data)
        except Exception as e:  # libspng's message, e.g. "IDAT stream error"
            raise ImageError(f"{where}: corrupt PNG ({e})") from None
        return out.reshape(hd.height, hd.width, channels)
    if fallback is None:
        raise ImageError(f"{where}: PNG with these filters/interlacing needs pyspng or OpenImageIO")
    return fallback()


def read_png_bytes(path: Path) -> bytes:
    """The bytes of ``path`` (`ImageError` naming it when unreadable)."""
    try:
        return path.read_bytes()
    except OSError as e:
        raise ImageError(f"{path}: cannot read ({e.strerror or e})") from None
