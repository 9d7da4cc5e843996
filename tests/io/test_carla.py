"""CARLA sensor codecs (CONVENTIONS §3), checked against the documented formulas."""

from __future__ import annotations

import numpy as np
import pytest

from jaxfish import ImageError
from jaxfish.io import (
    CARLA_MAX_DEPTH_M,
    DVS_EVENT_DTYPE,
    bgra_to_rgb,
    decode_depth,
    decode_dvs,
    decode_instance,
    decode_semantic,
    encode_depth,
    encode_instance,
    encode_semantic,
    rgb_to_bgra,
)

RNG = np.random.default_rng(0)


def test_bgra_rgb_round_trip():
    rgb = RNG.integers(0, 256, (6, 7, 3), dtype=np.uint8)
    bgra = rgb_to_bgra(rgb)
    assert bgra.shape == (6, 7, 4) and np.all(bgra[..., 3] == 255)
    np.testing.assert_array_equal(bgra[..., 0], rgb[..., 2])  # blue first
    np.testing.assert_array_equal(bgra_to_rgb(bgra), rgb)
    np.testing.assert_array_equal(bgra_to_rgb(bgra[..., :3]), rgb)
    with pytest.raises(ImageError, match="BGRA uint8"):
        bgra_to_rgb(np.zeros((2, 2, 4), np.float32))


def test_depth_matches_the_documented_formula():
    bgra = RNG.integers(0, 256, (5, 6, 4), dtype=np.uint8)
    b, g, r = (bgra[..., i].astype(np.float64) for i in range(3))
    expected = 1000.0 * (r + g * 256 + b * 256**2) / (256**3 - 1)
    np.testing.assert_allclose(decode_depth(bgra), expected, rtol=1e-7)
    white = np.full((1, 1, 4), 255, np.uint8)
    assert decode_depth(white)[0, 0] == CARLA_MAX_DEPTH_M  # far / sky saturates at exactly 1000 m


def test_depth_is_float64_scaling_of_the_code_rounded_once_to_float32():
    """Bit-exact: the code in integers, one float64 product and quotient, one rounding to float32,
    for BGRA and BGR pixels, images larger than one conversion block, and strided inputs."""
    for shape in [(3, 4, 4), (2, 3, 3), (700, 600, 4)]:
        bgra = RNG.integers(0, 256, shape, dtype=np.uint8)
        code = bgra[..., 2].astype(np.int64) + (bgra[..., 1].astype(np.int64) << 8) + (bgra[..., 0].astype(np.int64) << 16)
        expected = (CARLA_MAX_DEPTH_M * code.astype(np.float64) / (256**3 - 1)).astype(np.float32)
        np.testing.assert_array_equal(decode_depth(bgra), expected)
        np.testing.assert_array_equal(decode_depth(bgra[::2, ::-1]), expected[::2, ::-1])
    assert decode_depth(np.zeros((0, 5, 4), np.uint8)).shape == (0, 5)


@pytest.mark.parametrize("decode, shape, dtype", [(bgra_to_rgb, (5, 6, 3), np.uint8), (decode_depth, (5, 6), np.float32),
                                                  (decode_semantic, (5, 6), np.uint8)])
def test_decoders_write_into_a_given_array(decode, shape, dtype):
    bgra = RNG.integers(0, 256, (5, 6, 4), dtype=np.uint8)
    expected = decode(bgra)
    stack = np.zeros((3,) + shape, dtype)
    assert decode(bgra, stack[1]) is not None
    np.testing.assert_array_equal(stack[1], expected)
    assert not stack[0].any() and not stack[2].any()  # nothing written beside the destination
    strided = np.zeros(shape[::-1], dtype).T if len(shape) == 2 else np.zeros((6, 5, 3), dtype).transpose(1, 0, 2)
    decode(bgra, strided)
    np.testing.assert_array_equal(strided, expected)
    for bad in (np.zeros((4, 6) + shape[2:], dtype), np.zeros(shape, np.float64), np.zeros(shape, dtype)[None]):
        with pytest.raises(ValueError, match="out must be a writable"):
            decode(bgra, bad)
    frozen = np.zeros(shape, dtype)
    frozen.setflags(write=False)
    with pytest.raises(ValueError, match="out must be a writable"):
        decode(bgra, frozen)


def test_depth_round_trip_within_one_level():
    d = np.concatenate([RNG.uniform(0, 1000, 500), [0.0, 1000.0, 1e6, -3.0]]).astype(np.float64)
    back = decode_depth(encode_depth(d[None]))[0]
    quantum = 1000.0 / (256**3 - 1)
    np.testing.assert_allclose(back, np.clip(d, 0, 1000), atol=0.5 * quantum + 1e-4)


def test_semantic_and_instance():
    tags = RNG.integers(0, 29, (4, 5)).astype(np.uint8)
    sem = encode_semantic(tags)
    np.testing.assert_array_equal(sem[..., 2], tags)  # red channel (BGRA index 2)
    np.testing.assert_array_equal(decode_semantic(sem), tags)
    ids = RNG.integers(0, 65536, (4, 5))
    inst = encode_instance(tags, ids)
    t2, i2 = decode_instance(inst)
    np.testing.assert_array_equal(t2, tags)
    np.testing.assert_array_equal(i2, ids)
    np.testing.assert_array_equal(inst[..., 1].astype(int) + 256 * inst[..., 0].astype(int), ids)  # id = G + 256 B
    with pytest.raises(ImageError, match="0..65535"):
        encode_instance(tags, ids + 65536)
    with pytest.raises(ImageError, match="tags"):
        encode_semantic(np.full((2, 2), 300))


def test_dvs_events():
    assert DVS_EVENT_DTYPE.itemsize == 13
    ev = np.zeros(3, DVS_EVENT_DTYPE)
    ev["x"], ev["y"], ev["t"], ev["pol"] = [1, 2, 3], [4, 5, 6], [10**9, 2 * 10**9, 3 * 10**9], [True, False, True]
    back = decode_dvs(ev.tobytes())
    np.testing.assert_array_equal(back, ev)
    assert back["t"][1] == 2 * 10**9  # nanoseconds, int64
    assert decode_dvs(ev) is ev
    with pytest.raises(ImageError, match="13-byte"):
        decode_dvs(b"\x00" * 14)
