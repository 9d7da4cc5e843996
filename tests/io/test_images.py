"""Image files through OpenImageIO: dtype-preserving round trips, clear errors, atomic writes."""

from __future__ import annotations

import os
import stat

import numpy as np
import pytest

from jaxfish import ImageError
from jaxfish.io import read_image, read_image_metadata, write_image

RNG = np.random.default_rng(0)


@pytest.mark.parametrize(
    "ext, dtype, channels",
    [(".png", np.uint8, 1), (".png", np.uint8, 3), (".png", np.uint8, 4), (".png", np.uint16, 1), (".png", np.uint16, 3),
     (".exr", np.float32, 1), (".exr", np.float32, 3), (".exr", np.float16, 3), (".exr", np.float16, 4)],
)
def test_round_trip_is_bit_exact(tmp_path, ext, dtype, channels):
    shape = (37, 53, channels)  # odd sizes on purpose
    if np.issubdtype(dtype, np.integer):
        a = RNG.integers(0, np.iinfo(dtype).max, shape, endpoint=True).astype(dtype)
    else:
        a = (RNG.normal(size=shape) * 100).astype(dtype)
    path = write_image(tmp_path / f"x{ext}", a)
    b = read_image(path)
    assert b.dtype == dtype and b.shape == shape
    np.testing.assert_array_equal(b, a)


def test_two_dimensional_arrays_are_not_scrambled(tmp_path):
    """OpenImageIO scrambles (H, W) writes (CONVENTIONS §8): they must come back intact."""
    a = RNG.random((40, 30)).astype(np.float32)
    b = read_image(write_image(tmp_path / "d.exr", a))
    assert b.shape == (40, 30, 1)
    np.testing.assert_array_equal(b[..., 0], a)
    full = RNG.random((966, 1280)).astype(np.float32)  # full frame: the heap-corruption trap
    np.testing.assert_array_equal(read_image(write_image(tmp_path / "f.exr", full))[..., 0], full)


def test_bool_and_float64_are_converted(tmp_path):
    m = RNG.random((5, 6)) > 0.5
    np.testing.assert_array_equal(read_image(write_image(tmp_path / "m.png", m))[..., 0], m.astype(np.uint8) * 255)
    d = RNG.random((5, 6))
    b = read_image(write_image(tmp_path / "d.exr", d))
    assert b.dtype == np.float32
    np.testing.assert_array_equal(b[..., 0], d.astype(np.float32))


def test_expect_shape(tmp_path):
    p = write_image(tmp_path / "a.png", np.zeros((4, 5, 3), np.uint8))
    assert read_image(p, expect_shape=(4, 5)).shape == (4, 5, 3)
    with pytest.raises(ImageError, match=r"a\.png.*expected an image of shape \(5, 5\)"):
        read_image(p, expect_shape=(5, 5))


def test_missing_and_corrupt_files_name_the_file(tmp_path):
    with pytest.raises(ImageError, match="nope.png: image file not found"):
        read_image(tmp_path / "nope.png")
    bad = tmp_path / "bad.png"
    bad.write_bytes(b"\x89PNG\r\n\x1a\n" + b"garbage" * 10)
    with pytest.raises(ImageError, match="bad.png"):
        read_image(bad)
    text = tmp_path / "text.exr"
    text.write_text("not an image")
    with pytest.raises(ImageError, match="text.exr"):
        read_image(text)


@pytest.mark.parametrize(
    "name, pixels, match",
    [("a.png", np.zeros((4, 4), np.float32), "PNG stores uint8/uint16"),
     ("a.bmpx", np.zeros((4, 4), np.uint8), "unsupported image extension"),
     ("a.exr", np.zeros((4, 4), np.int32), "unsupported pixel dtype"),
     ("a.png", np.zeros((0, 4), np.uint8), "expected"),
     ("a.png", np.zeros((2, 2, 2, 2), np.uint8), "expected")],
)
def test_write_errors_leave_nothing_behind(tmp_path, name, pixels, match):
    with pytest.raises(ImageError, match=match):
        write_image(tmp_path / name, pixels)
    assert list(tmp_path.iterdir()) == []


def test_write_replaces_atomically(tmp_path):
    p = tmp_path / "x.png"
    write_image(p, np.full((3, 3), 7, np.uint8))
    write_image(p, np.full((3, 3), 9, np.uint8))
    assert read_image(p).max() == 9
    assert sorted(x.name for x in tmp_path.iterdir()) == ["x.png"]


def test_written_files_get_the_umask_permissions_not_the_temporary_files(tmp_path):
    from jaxfish.io._atomic import FILE_MODE, atomic_write_text

    mask = os.umask(0)
    os.umask(mask)
    for p in (write_image(tmp_path / "x.png", np.zeros((2, 2), np.uint8)), atomic_write_text(tmp_path / "x.json", "{}")):
        assert stat.S_IMODE(p.stat().st_mode) == FILE_MODE == 0o666 & ~mask  # mkstemp alone gives 0o600


@pytest.mark.parametrize("ext", [".png", ".exr"])
def test_same_pixels_give_the_same_bytes_at_another_time(tmp_path, ext):
    import time

    import OpenImageIO as oiio

    a = (np.arange(12 * 10 * 3).reshape(12, 10, 3) % 251).astype(np.uint8 if ext == ".png" else np.float32)
    write_image(tmp_path / f"a{ext}", a)
    written = int(time.time())  # OpenImageIO stamps the second of writing (OpenEXR's capDate) unless told not to
    while int(time.time()) <= written:  # the event: the clock shows a later second (however long that takes)
        time.sleep(0.01)
    write_image(tmp_path / f"b{ext}", a)
    assert (tmp_path / f"a{ext}").read_bytes() == (tmp_path / f"b{ext}").read_bytes()
    inp = oiio.ImageInput.open(str(tmp_path / f"a{ext}"))
    assert inp.spec().get_string_attribute("DateTime", "") == ""
    inp.close()


def test_png_level_and_depth_exr(tmp_path):
    from jaxfish.io import DEPTH_ATTRIBUTE, read_depth_exr, write_depth_exr

    a = (np.arange(64 * 48 * 3).reshape(64, 48, 3) % 7).astype(np.uint8)
    small, fast = write_image(tmp_path / "s.png", a, png_level=9), write_image(tmp_path / "f.png", a, png_level=1)
    assert np.array_equal(read_image(small), a) and np.array_equal(read_image(fast), a)
    with pytest.raises(ImageError, match="png_level"):
        write_image(tmp_path / "bad.png", a, png_level=10)
    d = np.linspace(0.5, 1000.0, 48 * 64, dtype=np.float32).reshape(48, 64)
    p = write_depth_exr(tmp_path / "d.exr", d, {"unit": "m"})
    assert np.array_equal(read_depth_exr(p), d) and read_image_metadata(p, DEPTH_ATTRIBUTE) == {"unit": "m"}
    with pytest.raises(ImageError, match="channel names"):
        write_image(tmp_path / "c.exr", d, channel_names=("Z", "W"))


@pytest.mark.parametrize("shape", [(1, 1), (3, 1000), (966, 1280)])
def test_depth_exr_has_the_bytes_openimageio_writes(tmp_path, shape):
    """`write_depth_exr` encodes with NumPy the file `write_image` (OpenImageIO) writes for the
    same map and definition: non-finite values and signed zeros kept bit for bit."""
    from jaxfish.io import DEPTH_ATTRIBUTE, read_depth_exr, write_depth_exr

    d = np.random.default_rng(shape[1]).random(shape, dtype=np.float32) * 1000
    d.flat[: min(d.size, 4)] = np.array([np.nan, np.inf, -0.0, -np.inf], np.float32)[: min(d.size, 4)]
    for definition in (None, {"kind": "range", "unit": "m"}, {"note": "é ∞ \"quoted\""}):
        got = write_depth_exr(tmp_path / "fast.exr", d, definition)
        want = write_image(tmp_path / "oiio.exr", d, channel_names=("Z",), exr_compression="none",
                           metadata=None if definition is None else {DEPTH_ATTRIBUTE: definition})
        assert got.read_bytes() == want.read_bytes()
        np.testing.assert_array_equal(read_depth_exr(got).view(np.uint32), d.view(np.uint32))
    with pytest.raises(ImageError, match="depth must be"):
        write_depth_exr(tmp_path / "bad.exr", d[None])


def _jpeg_named_png(tmp_path):
    import OpenImageIO as oiio

    pixels = np.random.default_rng(0).integers(0, 23, (16, 16, 3), dtype=np.uint8)
    jpeg = tmp_path / "x.jpg"
    out = oiio.ImageOutput.create(str(jpeg))
    out.open(str(jpeg), oiio.ImageSpec(16, 16, 3, oiio.UINT8))
    out.write_image(pixels)
    out.close()
    path = tmp_path / "semantic.png"
    os.replace(jpeg, path)
    return path, pixels


def test_lossless_reads_refuse_a_jpeg_renamed_png(tmp_path):
    path, pixels = _jpeg_named_png(tmp_path)
    lossy = read_image(path)  # OpenImageIO reads by content: the JPEG decodes, with wrong values
    assert lossy.shape == pixels.shape and not np.array_equal(lossy, pixels)
    with pytest.raises(ImageError, match=r"semantic\.png: expected a lossless PNG file, found JPEG data"):
        read_image(path, lossless=True)
    empty = tmp_path / "empty.png"
    empty.write_bytes(b"")
    with pytest.raises(ImageError, match=r"empty\.png: expected a lossless PNG file, found an empty file"):
        read_image(empty, lossless=True)
    png = write_image(tmp_path / "ok.png", pixels)
    assert np.array_equal(read_image(png, lossless=True), pixels)


def test_paths_that_are_not_regular_files_are_refused_before_reading(tmp_path):
    os.mkfifo(tmp_path / "face.png")  # reading it would block forever
    with pytest.raises(ImageError, match=r"face\.png: is a FIFO \(named pipe\), expected a regular image file"):
        read_image(tmp_path / "face.png")
    with pytest.raises(ImageError, match=r"face\.png: is a FIFO"):
        read_image_metadata(tmp_path / "face.png", "x")
    (tmp_path / "dir.png").mkdir()
    with pytest.raises(ImageError, match=r"dir\.png: is a directory"):
        read_image(tmp_path / "dir.png")
