"""Hostile PNG files: truncated, bad CRCs, impossible IHDR fields, IDAT data that does not inflate,
no IDAT; and writer arguments a PNG cannot hold. jaxfish's PNG codec (`jaxfish.io._png`) raises
`ImageError` naming the file and the chunk or field; a build reports the sample as failed."""

from __future__ import annotations

import struct
import zlib
from pathlib import Path

import numpy as np

from .corpus import Case

FACE = Path("capture/frames/000000/cameras/FV/front")
BUILD = "build {capture} {tmp}/out --frames 0 --no-bev"


def chunks(data: bytes) -> list[tuple[bytes, bytes]]:
    """``(type, payload)`` of every chunk of a well-formed PNG."""
    out, p = [], 8
    while p < len(data):
        (n,) = struct.unpack(">I", data[p:p + 4])
        out.append((data[p + 4:p + 8], data[p + 8:p + 8 + n]))
        p += 12 + n
    return out


def assemble(parts: list[tuple[bytes, bytes]]) -> bytes:
    """PNG bytes of ``(type, payload)`` chunks, each with its correct CRC."""
    body = b"".join(struct.pack(">I", len(d)) + k + d + struct.pack(">I", zlib.crc32(d, zlib.crc32(k)))
                    for k, d in parts)
    return b"\x89PNG\r\n\x1a\n" + body


def _edit(relative: Path | str, edit):
    """Setup: the PNG at ``relative`` rewritten as ``edit(bytes)``."""

    def setup(tmp: Path) -> None:
        path = tmp / relative
        path.write_bytes(edit(path.read_bytes()))

    return setup


def truncated(data: bytes) -> bytes:
    return data[: len(data) // 2]


def bad_idat_crc(data: bytes) -> bytes:
    p = data.index(b"IDAT") + 4
    return data[:p] + bytes([data[p] ^ 0xFF]) + data[p + 1:]


def ihdr_field(offset: int, value: int):
    """A valid-CRC file whose IHDR byte ``offset`` (8 = bit depth, 9 = colour type) is ``value``."""

    def edit(data: bytes) -> bytes:
        parts = chunks(data)
        ihdr = bytearray(parts[0][1])
        ihdr[offset] = value
        return assemble([(b"IHDR", bytes(ihdr))] + parts[1:])

    return edit


def ihdr_size(width: int, height: int):
    """A valid-CRC file whose IHDR claims ``width`` x ``height`` pixels (its IDAT unchanged)."""

    def edit(data: bytes) -> bytes:
        parts = chunks(data)
        ihdr = struct.pack(">II", width, height) + parts[0][1][8:]
        return assemble([(b"IHDR", ihdr)] + parts[1:])

    return edit


def replace_idat(payload: bytes | None):
    """A valid-CRC file whose IDAT data is ``payload`` (None: no IDAT chunk)."""

    def edit(data: bytes) -> bytes:
        parts = [p for p in chunks(data) if p[0] != b"IDAT"]
        if payload is not None:
            parts.insert(len(parts) - 1, (b"IDAT", payload))
        return assemble(parts)

    return edit


def _png(tmp: Path, edit) -> Path:
    from jaxfish.io import write_image

    path = write_image(tmp / "x.png", np.arange(60, dtype=np.uint8).reshape(4, 5, 3), metadata={"jaxfish:bev": {"a": 1}})
    path.write_bytes(edit(path.read_bytes()))
    return path


def _read(edit):
    def call(tmp: Path):
        from jaxfish.io import read_image

        return read_image(_png(tmp, edit))

    return call


def _meta(edit):
    def call(tmp: Path):
        from jaxfish.io import read_bev_metadata

        return read_bev_metadata(_png(tmp, edit))

    return call


def _write(pixels, **kwargs):
    def call(tmp: Path):
        from jaxfish.io import write_image

        return write_image(tmp / "w.png", pixels, **kwargs)

    return call


def _bad_text_crc(data: bytes) -> bytes:
    p = data.index(b"tEXt") + 6
    return data[:p] + bytes([data[p] ^ 0x01]) + data[p + 1:]


CASES = [
    # A capture face PNG broken in each way: the build fails that sample, naming file and chunk.
    Case("png-build-truncated-face", BUILD, setup=_edit(FACE / "semantic_curr.png", truncated), exit=1,
         says=("semantic_curr.png", "truncated PNG")),
    Case("png-build-idat-bad-crc", BUILD, setup=_edit(FACE / "depth_curr.png", bad_idat_crc), exit=1,
         says=("depth_curr.png", "bad CRC in chunk IDAT")),
    Case("png-build-ihdr-bit-depth-7", BUILD, setup=_edit(FACE / "rgb_curr.png", ihdr_field(8, 7)), exit=1,
         says=("rgb_curr.png", "bad IHDR", "bit depth")),
    # The same faults and others through the library reader.
    Case("png-read-ihdr-colour-type-5", call=_read(ihdr_field(9, 5)), says=("x.png", "bad IHDR", "colour type")),
    Case("png-read-idat-not-deflate", call=_read(replace_idat(b"not a zlib stream")),
         says=("x.png", "IDAT", "does not inflate")),
    Case("png-read-no-idat", call=_read(replace_idat(None)), says=("x.png", "no IDAT")),
    Case("png-read-truncated", call=_read(truncated), says=("x.png", "truncated PNG")),
    Case("png-read-header-only", call=_read(lambda d: d[:20]), says=("x.png", "truncated PNG", "IHDR")),
    Case("png-read-signature-only", call=_read(lambda d: d[:8]), says=("x.png", "truncated PNG")),
    Case("png-read-bad-idat-crc", call=_read(bad_idat_crc), says=("x.png", "bad CRC in chunk IDAT")),
    Case("png-read-ihdr-bit-depth-16-palette", call=_read(lambda d: ihdr_field(8, 16)(ihdr_field(9, 3)(d))),
         says=("x.png", "bad IHDR", "bit depth", "16")),
    Case("png-read-ihdr-bit-depth-32", call=_read(ihdr_field(8, 32)), says=("x.png", "bit depth", "32")),
    Case("png-read-ihdr-interlace-2", call=_read(ihdr_field(12, 2)), says=("x.png", "interlace method")),
    Case("png-read-ihdr-width-0", call=_read(ihdr_field(3, 0)), says=("x.png", "bad IHDR", "width")),
    # An IHDR claiming a huge image over a small IDAT: read as truncated, the image never allocated.
    Case("png-read-ihdr-huge-image", call=_read(ihdr_size(2**31 - 1, 2**31 - 1)), says=("x.png", "truncated PNG")),
    Case("png-read-ihdr-40-gb-image", call=_read(ihdr_size(100_000, 100_000)), says=("x.png", "truncated PNG")),
    Case("png-read-ihdr-huge-image-bad-idat",
         call=_read(lambda d: replace_idat(b"not a zlib stream")(ihdr_size(2**31 - 1, 2**31 - 1)(d))),
         says=("x.png", "IDAT", "does not inflate")),
    Case("png-read-idat-short", call=_read(replace_idat(zlib.compress(b"\x02" * 10))),
         says=("x.png", "truncated PNG", "IDAT")),
    Case("png-read-filter-type-9", call=_read(replace_idat(zlib.compress(b"\x09" + b"\0" * 15 + b"\x02" * 48))),
         says=("x.png", "filter type 9")),
    Case("png-read-first-chunk-not-ihdr", call=_read(lambda d: assemble(chunks(d)[1:])),
         says=("x.png", "expected IHDR")),
    Case("png-metadata-bad-text-crc", call=_meta(_bad_text_crc), says=("x.png", "bad CRC in chunk tEXt")),
    Case("png-metadata-truncated", call=_meta(truncated), says=("x.png", "truncated PNG")),
    # Writer arguments a PNG cannot hold: refused before anything is written.
    Case("png-write-five-channels", call=_write(np.zeros((2, 2, 5), np.uint8)), says=("w.png", "C = 1-4")),
    Case("png-write-level-10", call=_write(np.zeros((2, 2), np.uint8), png_level=10), says=("w.png", "png_level")),
    Case("png-write-level-true", call=_write(np.zeros((2, 2), np.uint8), png_level=True), says=("w.png", "png_level")),
    Case("png-write-long-keyword", call=_write(np.zeros((2, 2), np.uint8), metadata={"k" * 80: 1}),
         says=("w.png", "keyword")),
    Case("png-write-empty-keyword", call=_write(np.zeros((2, 2), np.uint8), metadata={"": 1}),
         says=("w.png", "keyword")),
    Case("png-write-float-pixels", call=_write(np.zeros((2, 2), np.float32)), says=("w.png", "uint8/uint16")),
]
