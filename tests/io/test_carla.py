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
