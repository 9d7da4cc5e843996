"""jaxfish's PNG codec (`jaxfish.io._png`): every kind of PNG jaxfish writes decodes bit-identically
with OpenImageIO, OpenCV and Pillow, and jaxfish reads other encoders' files (Sub, Paeth, mixed
filters, Adam7 interlacing, palettes) as OpenImageIO does."""

from __future__ import annotations

import struct
import zlib

import cv2
import numpy as np
import OpenImageIO as oiio
import pytest
from PIL import Image

from jaxfish import ImageError
from jaxfish.io import _png, read_image, read_image_metadata, write_image
from jaxfish.io._bev import BEV_METADATA_ATTRIBUTE, read_bev_metadata, write_png_with_metadata
from jaxfish.io._flow import read_kitti_flow, write_kitti_flow
from jaxfish.io._labels import PALETTE_ATTRIBUTE, read_label_png, read_palette, write_color_png, write_label_png
from tests.hostile.cases_png import assemble, chunks

KINDS = {  # name: (channels or None for (H, W), dtype): every kind jaxfish writes, and grey + alpha
    "rgb8": (3, np.uint8),  # RGB images, colour renderings (depth, flow, events), colour labels
    "gray8": (None, np.uint8),  # gtLabels, BEV occupancy/height PNGs
    "gray16": (None, np.uint16),  # instance maps with ids above 255
    "rgb16": (3, np.uint16),  # KITTI flow
    "rgba8": (4, np.uint8),  # the capture's BGRA images (rgb, depth, semantic, instance)
    "ga8": (2, np.uint8),
    "ga16": (2, np.uint16),
    "rgba16": (4, np.uint16),
}
SIZES = [(1, 1), (3, 5), (17, 9)]


def pixels(kind: str, size: tuple[int, int], content: str, seed: int = 0) -> np.ndarray:
    c, dtype = KINDS[kind]
    shape = size if c is None else (*size, c)
    if content == "zeros":
        return np.zeros(shape, dtype)
    if content == "max":
        return np.full(shape, np.iinfo(dtype).max, dtype)
    return np.random.default_rng(seed).integers(0, np.iinfo(dtype).max + 1, shape, dtype=dtype)


def hwc(a: np.ndarray) -> np.ndarray:
    return a if a.ndim == 3 else a[..., None]


def read_oiio(path) -> np.ndarray:
    config = oiio.ImageSpec()
    config.attribute("oiio:UnassociatedAlpha", 1)
    inp = oiio.ImageInput.open(str(path), config)
    try:
        return hwc(np.asarray(inp.read_image(0, 0, 0, inp.spec().nchannels, oiio.UNKNOWN)))
    finally:
        inp.close()


def oiio_attribute(path, name: str) -> str:
    inp = oiio.ImageInput.open(str(path))
    try:
        return inp.spec().get_string_attribute(name, "")
    finally:
        inp.close()


def read_cv2(path) -> np.ndarray:
    """OpenCV's pixels in RGB(A) order."""
    a = hwc(cv2.imread(str(path), cv2.IMREAD_UNCHANGED))
    if a.shape[2] == 3:
        return a[..., ::-1]
    if a.shape[2] == 4:
        return a[..., [2, 1, 0, 3]]
    return a


def cv2_expected(a: np.ndarray) -> np.ndarray:
    """What OpenCV gives for jaxfish's pixels (in RGB(A) order): grey + alpha expanded to
    ``(g, g, g, a)`` (OpenCV has no two-channel PNG), everything else as is."""
    a = hwc(a)
    return a[..., [0, 0, 0, 1]] if a.shape[2] == 2 else a


def read_pillow(path) -> np.ndarray:
    with Image.open(path) as im:
        return hwc(np.asarray(im))


def pillow_expected(a: np.ndarray) -> np.ndarray:
    """What Pillow gives for jaxfish's pixels: 16-bit grey as is (mode I;16); 16-bit RGB and RGBA
    reduced to their high bytes, 16-bit grey + alpha to the high bytes of ``(g, g, g, a)`` (mode
    RGBA): Pillow has no 16-bit colour or grey + alpha modes."""
    a = hwc(a)
    if a.dtype == np.uint16 and a.shape[2] > 1:
        return (cv2_expected(a) >> 8).astype(np.uint8)
    return a


def filters_of(path) -> set[int]:
    """The filter bytes of a non-interlaced PNG's rows."""
    data = path.read_bytes()
    parsed = _png.parse_png(data)
    hd = parsed.header
    row = hd.width * _png._CHANNELS[hd.color_type] * hd.bit_depth // 8 + 1
    raw = zlib.decompress(parsed.idat)
    return {raw[i * row] for i in range(hd.height)}


@pytest.mark.parametrize("content", ["zeros", "random", "max"])
@pytest.mark.parametrize("size", SIZES, ids=lambda s: f"{s[0]}x{s[1]}")
@pytest.mark.parametrize("kind", KINDS)
def test_every_kind_decodes_identically_everywhere(tmp_path, kind, size, content):
    a = pixels(kind, size, content)
    path = write_image(tmp_path / "a.png", a)
    assert filters_of(path) == {_png.FILTER_UP}
    want = hwc(a)
    got = read_image(path)
    assert got.dtype == a.dtype and np.array_equal(got, want)
    assert np.array_equal(read_oiio(path), want)
    cv = read_cv2(path)
    assert cv.dtype == a.dtype and np.array_equal(cv, cv2_expected(a))
    assert np.array_equal(read_pillow(path), pillow_expected(a))


@pytest.mark.parametrize("level", range(10))
def test_each_png_level(tmp_path, level):
    for kind in ("rgb8", "rgb16", "gray8"):
        a = pixels(kind, (9, 7), "random", seed=level)
        path = write_image(tmp_path / f"{kind}.png", a, png_level=level)
        want = hwc(a)
        assert np.array_equal(read_image(path), want)
        assert np.array_equal(read_oiio(path), want)
        assert np.array_equal(read_cv2(path), cv2_expected(a))
        assert np.array_equal(read_pillow(path), pillow_expected(a))


def test_levels_map_to_isal_and_zero_stores():
    assert set(_png.ISAL_LEVELS) == set(range(10)) and set(_png.ISAL_LEVELS.values()) <= {0, 1, 2, 3}
    a = pixels("rgb8", (64, 64), "zeros")
    stored = _png.encode_png(a, png_level=0)
    assert len(stored) > a.nbytes  # level 0: stored blocks, no compression
    assert len(_png.encode_png(a, png_level=1)) < a.nbytes // 10


def test_same_pixels_same_bytes_and_text_is_a_tEXt_chunk(tmp_path):
    a = pixels("rgb8", (5, 4), "random")
    one = write_image(tmp_path / "1.png", a, metadata={"jaxfish:palette": {"classes": ["a"]}}).read_bytes()
    two = write_image(tmp_path / "2.png", a.copy(), metadata={"jaxfish:palette": {"classes": ["a"]}}).read_bytes()
    assert one == two
    kinds = [k for k, _ in chunks(one)]
    assert kinds == [b"IHDR", b"tEXt", b"IDAT", b"IEND"]
    assert dict(chunks(one))[b"tEXt"] == b'jaxfish:palette\x00{"classes": ["a"]}'


def test_zlib_fallback_writes_the_same_pixels(tmp_path, monkeypatch):
    a = pixels("rgb16", (6, 5), "random")
    with_isal = _png.encode_png(a)
    monkeypatch.setattr(_png, "_isal_zlib", None)
    assert _png.deflate_name().startswith("zlib")
    path = write_image(tmp_path / "z.png", a)
    assert np.array_equal(read_oiio(path), a) and np.array_equal(read_image(path), a)
    assert path.read_bytes() != with_isal  # another deflate implementation: other bytes, same pixels


# --------------------------------------------------------------------- metadata
def test_writers_metadata_reads_back_everywhere(tmp_path):
    rgb = pixels("rgb8", (3, 5), "random")
    palette = {"classes": ["road", "car"], "colors": [[1, 2, 3], [4, 5, 6]]}
    p = write_color_png(tmp_path / "labels.png", rgb, palette)
    assert read_palette(p) == palette and np.array_equal(read_oiio(p), rgb)
    assert read_image_metadata(p, PALETTE_ATTRIBUTE) == palette
    assert oiio_attribute(p, PALETTE_ATTRIBUTE) == '{"classes": ["road", "car"], "colors": [[1, 2, 3], [4, 5, 6]]}'
    with Image.open(p) as im:
        assert im.info[PALETTE_ATTRIBUTE] == oiio_attribute(p, PALETTE_ATTRIBUTE)

    bev = {"metres_per_pixel": 0.1, "width": 5, "height": 3, "cx": 2.0, "cy": 1.0, "note": "é ünïcode"}
    g = pixels("gray8", (3, 5), "random")
    b = write_png_with_metadata(tmp_path / "bev.png", g, bev)
    assert read_bev_metadata(b) == bev and np.array_equal(read_oiio(b), hwc(g))
    assert oiio_attribute(b, BEV_METADATA_ATTRIBUTE) != ""
    import json

    assert json.loads(oiio_attribute(b, BEV_METADATA_ATTRIBUTE)) == bev


def test_metadata_of_oiio_written_png_reads(tmp_path):
    """Files written by OpenImageIO (jaxfish's earlier datasets) keep their metadata readable."""
    path = tmp_path / "o.png"
    out = oiio.ImageOutput.create(str(path))
    spec = oiio.ImageSpec(4, 3, 3, oiio.UINT8)
    spec.attribute("jaxfish:bev", '{"a": [1, 2]}')
    out.open(str(path), spec)
    out.write_image(np.zeros((3, 4, 3), np.uint8))
    out.close()
    assert read_image_metadata(path, "jaxfish:bev") == {"a": [1, 2]}


def test_ztxt_and_itxt_metadata(tmp_path):
    a = pixels("gray8", (2, 3), "random")
    data = _png.encode_png(hwc(a))
    parts = chunks(data)
    extra = [(b"zTXt", b"jaxfish:z\x00\x00" + zlib.compress(b'{"z": 1}')),
             (b"iTXt", b"jaxfish:i\x00\x01\x00en\x00\x00" + zlib.compress('{"i": "ü"}'.encode()))]
    path = tmp_path / "t.png"
    path.write_bytes(assemble(parts[:1] + extra + parts[1:]))
    assert read_image_metadata(path, "jaxfish:z") == {"z": 1}
    assert read_image_metadata(path, "jaxfish:i") == {"i": "ü"}
    assert np.array_equal(read_image(path), hwc(a))


# --------------------------------------------------------------------- the modality writers
def test_label_flow_writers_read_back_with_every_decoder(tmp_path):
    labels = np.arange(15).reshape(3, 5) * 4681  # above 255: uint16
    p = write_label_png(tmp_path / "inst.png", labels)
    assert np.array_equal(read_label_png(p), labels)
    assert np.array_equal(read_oiio(p)[..., 0], labels) and np.array_equal(read_cv2(p)[..., 0], labels)
    assert np.array_equal(read_pillow(p)[..., 0], labels)
    small = write_label_png(tmp_path / "sem.png", np.arange(15).reshape(3, 5))
    assert read_image(small).dtype == np.uint8

    flow = np.random.default_rng(3).normal(0, 40, (5, 3, 2)).astype(np.float32)
    valid = np.random.default_rng(4).random((5, 3)) > 0.3
    f = write_kitti_flow(tmp_path / "flow.png", flow, valid)
    got, ok = read_kitti_flow(f)
    assert np.array_equal(ok, valid)
    stored = read_oiio(f)
    assert stored.dtype == np.uint16 and np.array_equal(read_cv2(f), stored)
    assert np.array_equal(read_image(f), stored)
    assert np.allclose(got[valid], flow[valid], atol=1 / 128)


# --------------------------------------------------------------------- other encoders' files
def _oiio_write(path, a, png_filter: int) -> None:
    out = oiio.ImageOutput.create(str(path))
    spec = oiio.ImageSpec(a.shape[1], a.shape[0], a.shape[2], oiio.UINT16 if a.dtype == np.uint16 else oiio.UINT8)
    spec.attribute("png:filter", png_filter)
    spec.attribute("oiio:UnassociatedAlpha", 1)
    out.open(str(path), spec)
    out.write_image(a)
    out.close()


def _texture(shape, dtype, seed=0) -> np.ndarray:
    """Smooth gradients plus noise: libpng's adaptive filter picks several filters for it."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[: shape[0], : shape[1]]
    base = (x * 7 + y * 3)[..., None] * np.arange(1, shape[2] + 1)
    scale = 257 if dtype == np.uint16 else 1
    return ((base + rng.integers(0, 4, shape)) * scale % (np.iinfo(dtype).max + 1)).astype(dtype)


@pytest.mark.parametrize("png_filter,name", [(0x08, "none"), (0x10, "sub"), (0x40, "avg"), (0x80, "paeth"),
                                             (0xF8, "all")])
@pytest.mark.parametrize("channels,dtype", [(3, np.uint8), (1, np.uint16), (3, np.uint16), (4, np.uint8)])
def test_reads_oiio_files_of_every_filter(tmp_path, png_filter, name, channels, dtype):
    a = _texture((13, 11, channels), dtype)
    path = tmp_path / f"{name}.png"
    _oiio_write(path, a, png_filter)
    assert np.array_equal(read_oiio(path), a)
    got = read_image(path)
    assert got.dtype == a.dtype and np.array_equal(got, a)


def test_reads_opencv_and_pillow_files(tmp_path):
    a = _texture((20, 31, 3), np.uint8, seed=1)
    cv = tmp_path / "cv.png"
    cv2.imwrite(str(cv), np.ascontiguousarray(a[..., ::-1]))
    assert len(filters_of(cv) - {0, 2}) > 0  # not only None/Up: another decoder than the fast path
    assert np.array_equal(read_image(cv), a)
    for mode, arr in (("RGB", a), ("L", a[..., 0]), ("RGBA", np.dstack([a, a[..., :1]]))):
        p = tmp_path / f"pil_{mode}.png"
        Image.fromarray(arr, mode=None).save(p, optimize=True)
        assert np.array_equal(read_image(p), hwc(arr)), mode
    p16 = tmp_path / "pil16.png"
    Image.fromarray(a[..., 0].astype(np.uint16) * 257).save(p16)
    assert np.array_equal(read_image(p16), read_oiio(p16))


def test_reads_mixed_none_up_rows_by_the_fast_path(tmp_path, monkeypatch):
    a = _texture((6, 4, 3), np.uint8)
    rows = a.reshape(6, 12)
    raw = b""
    for i, r in enumerate(rows):
        up = i % 2 == 1
        raw += bytes([2 if up else 0]) + ((r - rows[i - 1]) if up else r).astype(np.uint8).tobytes()
    path = tmp_path / "mixed.png"
    path.write_bytes(assemble([(b"IHDR", struct.pack(">IIBBBBB", 4, 6, 8, 2, 0, 0, 0)),
                               (b"IDAT", zlib.compress(raw)), (b"IEND", b"")]))
    monkeypatch.setattr(_png, "_pyspng", None)  # the fast path alone must read it
    assert np.array_equal(read_image(path), a) and np.array_equal(read_oiio(path), a)


@pytest.mark.parametrize("height", [1, 2, _png.UNFILTER_BLOCK_ROWS - 1, _png.UNFILTER_BLOCK_ROWS,
                                    _png.UNFILTER_BLOCK_ROWS + 1, 3 * _png.UNFILTER_BLOCK_ROWS + 5])
@pytest.mark.parametrize("kind", ["rgb8", "gray16"])
def test_up_rows_read_back_at_heights_around_the_unfilter_block(tmp_path, monkeypatch, height, kind):
    a = pixels(kind, (height, 7), "random", seed=height)
    path = tmp_path / "up.png"
    write_image(path, a)
    assert filters_of(path) == {_png.FILTER_UP}
    monkeypatch.setattr(_png, "_pyspng", None)  # the fast path alone must read it
    assert np.array_equal(hwc(read_image(path)), hwc(a)) and np.array_equal(read_oiio(path), hwc(a))


@pytest.mark.parametrize("height", [1, _png.UNFILTER_BLOCK_ROWS, 2 * _png.UNFILTER_BLOCK_ROWS + 3])
@pytest.mark.parametrize("modes", ["up", "none first", "mixed"])
def test_unfilter_is_a_running_sum_of_rows_restarted_at_none_rows(height, modes):
    rng = np.random.default_rng(height)
    filtered = rng.integers(0, 256, (height, 1 + 11), dtype=np.uint8)
    filtered[:, 0] = _png.FILTER_UP
    if modes == "none first":
        filtered[0, 0] = 0
    elif modes == "mixed":
        filtered[rng.random(height) < 0.3, 0] = 0
    expected, total = np.empty((height, 11), np.uint8), np.zeros(11, np.int64)
    for i, row in enumerate(filtered):  # the reference: one row at a time, in wide integers
        total = (total if row[0] == _png.FILTER_UP else 0) + row[1:].astype(np.int64)
        expected[i] = total % 256
    assert np.array_equal(_png._unfilter_up(filtered), expected)


def _inflates(monkeypatch) -> list[str]:
    """Record which inflate `decode_png` runs: ``"libdeflate"`` when libdeflate returns the rows,
    ``"fallback"`` when ISA-L / zlib inflates them."""
    calls: list[str] = []
    libdeflate, fallback = _png._libdeflate.zlib_decompress, (_png._isal_zlib or zlib).decompress

    class Spy:
        DeflateError = _png._libdeflate.DeflateError

        @staticmethod
        def zlib_decompress(data, size):
            out = libdeflate(data, size)  # raises DeflateError when it refuses the stream
            calls.append("libdeflate")
            return out

    class Fallback:
        error = getattr(_png._isal_zlib, "error", zlib.error)

        @staticmethod
        def decompress(data, bufsize):
            calls.append("fallback")
            return fallback(data, bufsize=bufsize)

    monkeypatch.setattr(_png, "_libdeflate", Spy)
    monkeypatch.setattr(_png, "_isal_zlib" if _png._isal_zlib is not None else "zlib", Fallback)
    return calls


def test_compressible_streams_inflate_through_libdeflate(monkeypatch):
    """A label map's stream (far smaller than its rows) is inflated by libdeflate, a noisy image's
    by ISA-L; both read the same pixels as without libdeflate."""
    labels = np.repeat(np.arange(12, dtype=np.uint8)[:, None], 40, axis=1)
    noise = _texture((12, 40, 3), np.uint8)
    files = {"labels": _png.encode_png(labels[..., None]), "noise": _png.encode_png(noise)}
    calls = _inflates(monkeypatch)
    got = {name: _png.decode_png(data) for name, data in files.items()}
    assert calls == ["libdeflate", "fallback"]
    monkeypatch.setattr(_png, "_libdeflate", None)
    for name, data in files.items():
        assert np.array_equal(got[name], _png.decode_png(data))
    assert np.array_equal(got["labels"][..., 0], labels) and np.array_equal(got["noise"], noise)


def test_streams_libdeflate_refuses_read_as_without_it(monkeypatch):
    """A stream that inflates to more than the image (extra bytes after the rows) is refused by
    libdeflate and read by ISA-L as before; a corrupt or short one raises ISA-L's errors."""
    rows = np.zeros((8, 17), np.uint8)  # 8 rows of 16 grey pixels, filter None
    header = (b"IHDR", struct.pack(">IIBBBBB", 16, 8, 8, 0, 0, 0, 0))

    def png(stream: bytes) -> bytes:
        return assemble([header, (b"IDAT", stream), (b"IEND", b"")])

    longer = png(zlib.compress(rows.tobytes() + bytes(40)))
    calls = _inflates(monkeypatch)
    assert np.array_equal(_png.decode_png(longer), np.zeros((8, 16, 1), np.uint8))
    assert calls == ["fallback"]
    bad = bytearray(zlib.compress(rows.tobytes()))
    bad[-1] ^= 0xFF  # the Adler-32 check fails
    with pytest.raises(ImageError, match="x.png: corrupt PNG: the IDAT data does not inflate"):
        _png.decode_png(png(bytes(bad)), "x.png")
    with pytest.raises(ImageError, match="x.png: truncated PNG"):
        _png.decode_png(png(zlib.compress(rows.tobytes()[:-17])), "x.png")


def _adam7(a: np.ndarray) -> bytes:
    """An Adam7-interlaced 8-bit PNG of ``a`` (H, W, C), every row filtered None."""
    passes = ((0, 0, 8, 8), (0, 4, 8, 8), (4, 0, 8, 4), (0, 2, 4, 4), (2, 0, 4, 2), (0, 1, 2, 2), (1, 0, 2, 1))
    raw = b""
    for y0, x0, dy, dx in passes:
        sub = a[y0::dy, x0::dx]
        if sub.size:
            raw += b"".join(b"\0" + row.tobytes() for row in sub)
    h, w, c = a.shape
    ihdr = struct.pack(">IIBBBBB", w, h, 8, {1: 0, 3: 2, 4: 6}[c], 0, 0, 1)
    return assemble([(b"IHDR", ihdr), (b"IDAT", zlib.compress(raw)), (b"IEND", b"")])


@pytest.mark.parametrize("without_pyspng", [False, True])
def test_reads_interlaced(tmp_path, monkeypatch, without_pyspng):
    if without_pyspng:
        monkeypatch.setattr(_png, "_pyspng", None)  # then OpenImageIO
    for shape in ((1, 1, 3), (11, 13, 3), (9, 6, 4), (5, 7, 1)):
        a = _texture(shape, np.uint8)
        path = tmp_path / "i.png"
        path.write_bytes(_adam7(a))
        assert np.array_equal(read_oiio(path), a)
        assert np.array_equal(read_image(path), a), shape


def test_paeth_without_pyspng_reads_by_oiio(tmp_path, monkeypatch):
    a = _texture((7, 9, 3), np.uint16)
    path = tmp_path / "p.png"
    _oiio_write(path, a, 0x80)
    monkeypatch.setattr(_png, "_pyspng", None)
    assert np.array_equal(read_image(path), a)


def test_palette_and_low_bit_depth_read_as_oiio_does(tmp_path):
    a = _texture((8, 10, 1), np.uint8)[..., 0] % 4
    pal = tmp_path / "pal.png"
    im = Image.fromarray(a.astype(np.uint8), mode="L").convert("P")
    im.save(pal)
    assert np.array_equal(read_image(pal), read_oiio(pal))
    bits = tmp_path / "bits.png"
    Image.fromarray(a > 1).save(bits)  # 1-bit grey
    assert _png.parse_png(bits.read_bytes()).header.bit_depth == 1
    assert np.array_equal(read_image(bits), read_oiio(bits))
