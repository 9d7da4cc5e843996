"""Flow files: Middlebury .flo and KITTI 16-bit PNG round trips, malformed files, colour PNG."""

from __future__ import annotations

import numpy as np
import pytest

from jaxfish import ImageError
from jaxfish.groundtruth import flow_to_color
from jaxfish.io import read_flo, read_image, read_kitti_flow, write_flo, write_image, write_kitti_flow
from tests import tolerances as tol


def _flow(h=7, w=9, seed=0):
    return np.random.default_rng(seed).normal(scale=20.0, size=(h, w, 2)).astype(np.float32)


def test_flo_round_trip_is_exact(tmp_path):
    f = _flow()
    write_flo(tmp_path / "a.flo", f)
    np.testing.assert_array_equal(read_flo(tmp_path / "a.flo"), f)
    raw = (tmp_path / "a.flo").read_bytes()
    assert raw[:4] == b"PIEH" and len(raw) == 12 + 7 * 9 * 8
    assert np.frombuffer(raw[4:12], "<i4").tolist() == [9, 7]  # width, then height


def test_flo_layout_is_u_v_interleaved_row_major(tmp_path):
    f = np.zeros((2, 3, 2), np.float32)
    f[0, 1] = (1.5, -2.5)
    write_flo(tmp_path / "b.flo", f)
    body = np.frombuffer((tmp_path / "b.flo").read_bytes()[12:], "<f4")
    assert body[2:4].tolist() == [1.5, -2.5]


def test_flo_rejects_malformed_files(tmp_path):
    (tmp_path / "bad.flo").write_bytes(b"BADT" + b"\0" * 8)
    with pytest.raises(ImageError, match="bad.flo"):
        read_flo(tmp_path / "bad.flo")
    write_flo(tmp_path / "c.flo", _flow())
    (tmp_path / "c.flo").write_bytes((tmp_path / "c.flo").read_bytes()[:-4])
    with pytest.raises(ImageError, match="size"):
        read_flo(tmp_path / "c.flo")
    with pytest.raises(ImageError):
        write_flo(tmp_path / "d.flo", np.zeros((3, 3)))


def test_kitti_round_trip(tmp_path):
    f = _flow()
    valid = np.random.default_rng(1).random((7, 9)) < 0.7
    write_kitti_flow(tmp_path / "k.png", f, valid)
    raw = read_image(tmp_path / "k.png")
    assert raw.dtype == np.uint16 and raw.shape == (7, 9, 3)
    g, v = read_kitti_flow(tmp_path / "k.png")
    np.testing.assert_array_equal(v, valid)
    np.testing.assert_allclose(g[valid], f[valid], atol=tol.KITTI_FLOW_PX)
    assert np.all(g[~valid] == 0)
    np.testing.assert_array_equal(raw[..., 0][valid], np.rint(f[..., 0][valid].astype(np.float64) * 64 + 2**15).astype(np.uint16))


def test_flow_colour_png(tmp_path):
    write_image(tmp_path / "c.png", np.asarray(flow_to_color(_flow())))
    img = read_image(tmp_path / "c.png")
    assert img.dtype == np.uint8 and img.shape == (7, 9, 3)


def test_kitti_quantisation_equals_float64_rounding_at_ties_and_limits(tmp_path):
    # Half-integer multiples of 1/64 (ties round to even) and values beyond the uint16 range.
    vals = np.asarray([0.5, 1.5, -0.5, -1.5, 2.5, 100.25, 511.99, 512.0, 600.0, -512.0, -600.0, 0.0078125, -0.0078125],
                      np.float32) / np.float32(1.0)
    vals = np.concatenate([vals, (np.arange(-40, 40) + 0.5).astype(np.float32) / 64])
    f = np.stack([vals, -vals], -1)[None]
    write_kitti_flow(tmp_path / "k.png", f)
    raw = read_image(tmp_path / "k.png")
    want = np.clip(np.rint(f.astype(np.float64) * 64 + 2**15), 0, 65535).astype(np.uint16)
    np.testing.assert_array_equal(raw[..., :2], want)
    assert np.all(raw[..., 2] == 1)



@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_kitti_pixels_in_row_blocks_equal_the_whole_array_formula(monkeypatch, dtype):
    """Block by block (several blocks, the last one short) the pixels are the whole-array formula's,
    invalid pixels 0 in every channel, NaN and huge values included."""
    import jaxfish.io._flow as flow_module

    rng = np.random.default_rng(5)
    f = rng.normal(0.0, 300.0, (37, 11, 2)).astype(dtype)
    f[3, 4, 0], f[5, 6, 1], f[7, 8] = np.nan, 1e30, -1e30
    valid = rng.random((37, 11)) < 0.8
    valid[3, 4] = valid[5, 6] = valid[7, 8] = True
    monkeypatch.setattr(flow_module, "_KITTI_BLOCK", 50)  # blocks of 4 rows
    got = flow_module.kitti_flow_pixels(f, valid)
    with np.errstate(invalid="ignore"):
        q = np.clip(np.rint(np.clip(f * 64, -2**15 - 1, 2**15)).astype(np.int32) + 2**15, 0, 65535)
    finite = np.isfinite(f).all(-1) | ~valid  # a NaN's integer is the cast's choice: compare the rest
    np.testing.assert_array_equal(got[finite][..., :2], np.where(valid[..., None], q, 0)[finite])
    np.testing.assert_array_equal(got[..., 2], valid)
    assert got[5, 6, 1] == 65535 and got[7, 8, 0] == got[7, 8, 1] == 0
