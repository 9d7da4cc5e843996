"""LUTs on disk: exact round trip, keys that follow the calibration, corrupt files rebuilt."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest

import jaxfish as jf
from jaxfish import JaxfishError
from jaxfish.io import cached_lut, load_lut, lut_cache_key, save_lut
from jaxfish.reprojection import Lut


def _equal(a: Lut, b: Lut) -> None:
    for name in ("face", "uv", "valid", "z_to_range", "tap_index", "tap_frac", "nearest_index", "ring_index", "ring_frac", "ring_valid"):
        x, y = np.asarray(getattr(a, name)), np.asarray(getattr(b, name))
        assert x.dtype == y.dtype, name
        np.testing.assert_array_equal(x, y, err_msg=name)
    assert (a.num_faces, a.source_width, a.source_height, a.pad, a.supersample) == (
        b.num_faces, b.source_width, b.source_height, b.pad, b.supersample)


def test_save_load_round_trip(tmp_path, cube_lut):
    _equal(load_lut(save_lut(cube_lut, tmp_path / "l.npz")), cube_lut)
    with pytest.raises(FileNotFoundError, match="missing.npz"):
        load_lut(tmp_path / "missing.npz")
    (tmp_path / "bad.npz").write_bytes(b"junk")
    with pytest.raises(JaxfishError, match="bad.npz"):
        load_lut(tmp_path / "bad.npz")


def test_cache_key_follows_the_calibration(small_rig, small_fisheye):
    key = lut_cache_key(small_rig, small_fisheye)
    assert key == lut_cache_key(small_rig, small_fisheye)
    moved = jf.WoodScapeFisheye(small_fisheye.k, width=160, height=120, cx_offset=small_fisheye.cx_offset + 1e-9,
                                cy_offset=small_fisheye.cy_offset, aspect_ratio=small_fisheye.aspect_ratio)
    others = {
        lut_cache_key(small_rig, moved),
        lut_cache_key(small_rig, small_fisheye, supersample=2),
        lut_cache_key(small_rig, small_fisheye, dtype=jnp.float64),
        lut_cache_key(small_rig, small_fisheye, target_to_source=np.eye(3)),
        lut_cache_key(jf.reprojection.CubeRig(65, dtype=jnp.float64), small_fisheye),
        lut_cache_key(jf.reprojection.CubeRig(64, faces=jf.reprojection.SIX_FACES, dtype=jnp.float64), small_fisheye),
    }
    assert key not in others and len(others) == 6


def test_cached_lut_builds_once_and_rebuilds_corrupt_files(tmp_path):
    cam = jf.Pinhole.from_fov(24, 16, 80.0)
    src = jf.Pinhole.from_fov(30, 20, 100.0)
    first = cached_lut(src, cam, cache_dir=tmp_path)
    files = list(tmp_path.glob("lut-*.npz"))
    assert len(files) == 1
    _equal(cached_lut(src, cam, cache_dir=tmp_path), first)
    files[0].write_bytes(b"corrupt")
    _equal(cached_lut(src, cam, cache_dir=tmp_path), first)
    assert load_lut(files[0]).supersample == 1
