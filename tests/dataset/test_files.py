"""The builder's own file helpers against independent references: NumPy event mapping vs a loop
over the rule (tests/groundtruth/test_files.py checks a capture's event counts against the JAX event map), deterministic
npz, the depth colour map."""

from __future__ import annotations

import time

import numpy as np

from jaxfish.io import write_npz
from jaxfish.pipeline import depth_to_color, map_face_events


def test_numpy_event_mapping_follows_the_rule():
    """Against a plain loop over the rule: each face event goes to every fisheye pixel its face
    pixel feeds (in fisheye-pixel order), all sorted by time, ties in input order."""
    rng = np.random.default_rng(0)
    faces, size, width, m = 2, 4, 7, 3
    n_src = faces * size * size
    fan = rng.integers(0, m + 1, n_src)
    targets = np.full((n_src, m), -1, np.int64)
    for i in range(n_src):
        targets[i, : fan[i]] = np.sort(rng.choice(width * 5, fan[i], replace=False))
    n = 300
    face, x, y = rng.integers(-1, faces, n), rng.integers(-1, size + 1, n), rng.integers(0, size, n)
    t, pol = rng.integers(0, 20, n), rng.random(n) < 0.5  # unsorted, many ties
    want = []
    for k in range(n):
        if 0 <= face[k] and 0 <= x[k] < size:
            for tg in targets[(face[k] * size + y[k]) * size + x[k]]:
                if tg >= 0:
                    want.append((int(t[k]), k, tg % width, tg // width, bool(pol[k])))
    want.sort(key=lambda w: (w[0], w[1]))
    for fanout in (fan, None):
        got = map_face_events(targets, width, size, face, x, y, t, pol, fanout=fanout)
        assert [(int(a), int(b), int(c), bool(d)) for a, b, c, d in zip(got["t"], got["x"], got["y"], got["pol"],
                                                                        strict=True)] == \
            [(w[0], w[2], w[3], w[4]) for w in want]


def test_npz_is_deterministic_and_numpy_readable(tmp_path, monkeypatch):
    arrays = {"events": np.arange(12, dtype=np.int64), "time_unit": np.asarray("us")}
    # A fake clock for each write (the real one is never read): an hour apart, a writer that stamps the
    # time (zipfile's writestr does) would differ.
    monkeypatch.setattr(time, "time", lambda: 1.7e9)
    a = write_npz(tmp_path / "a.npz", **arrays).read_bytes()
    monkeypatch.setattr(time, "time", lambda: 1.7e9 + 3600.0)
    b = write_npz(tmp_path / "b.npz", **arrays).read_bytes()
    assert a == b
    with np.load(tmp_path / "a.npz", allow_pickle=False) as z:
        np.testing.assert_array_equal(z["events"], arrays["events"]) and str(z["time_unit"]) == "us"


def test_depth_colors_near_bright_far_dark_sky_black():
    c = depth_to_color(np.asarray([[0.5, 10.0, 100.0, 1000.0, 0.0]], np.float32)).astype(int)
    assert c.dtype == np.int64 and c.shape == (1, 5, 3)
    lum = c[0].sum(-1)
    assert lum[0] > lum[1] > lum[2] > 0 and lum[3] == 0 and lum[4] == 0
    # float32 evaluation: within one step of the 1024-step ramp of the float64 formula.
    from jaxfish.pipeline import DEPTH_COLOR_RANGE_M
    from jaxfish.pipeline._render import _depth_ramp

    d = np.geomspace(0.01, 998.0, 5000).astype(np.float32)[None]
    lo, hi = DEPTH_COLOR_RANGE_M
    x = 1.0 - (np.log(np.clip(d.astype(np.float64), lo, hi)) - np.log(lo)) / (np.log(hi) - np.log(lo))
    steps = np.rint(x * 1023).astype(int)
    table = _depth_ramp().astype(int)
    got = depth_to_color(d).astype(int)[0]
    near = np.minimum.reduce([np.abs(got - table[np.clip(steps[0] + k, 0, 1023)]).max(-1) for k in (-1, 0, 1)])
    assert np.all(near == 0)


def test_build_options_reject_bad_values_and_record_the_png_level():
    import pytest

    from jaxfish.dataset import BuildOptions, DatasetError

    assert BuildOptions(png_level=6).to_dict()["png_level"] == 6
    for bad in (10, -1, 1.5, True):
        with pytest.raises(DatasetError, match="png_level"):
            BuildOptions(png_level=bad)
    with pytest.raises(DatasetError, match="write_threads"):
        BuildOptions(write_threads=-1)


def test_tune_allocator_is_idempotent_and_optional():
    from jaxfish.dataset import BuildOptions, tune_allocator

    first = tune_allocator()
    assert isinstance(first, bool) and tune_allocator() is first  # glibc here: True; elsewhere a no-op
    assert "tune_allocator" not in BuildOptions(tune_allocator=False).to_dict()  # it never changes bytes


def test_a_marker_of_another_layout_version_is_not_complete(tmp_path):
    import json

    from jaxfish.dataset import LAYOUT_VERSION, is_complete

    (tmp_path / "rgb_images").mkdir()
    (tmp_path / "rgb_images" / "00000_FV.png").write_bytes(b"x")
    (tmp_path / ".done").mkdir()
    marker = tmp_path / ".done" / "00000.json"
    for version, complete in ((LAYOUT_VERSION, True), (LAYOUT_VERSION - 1, False), (None, False)):
        doc = {"sample": "00000", "frame": 0, "files": {"rgb_images/00000_FV.png": "0"}}
        if version is not None:
            doc["layout_version"] = version
        marker.write_text(json.dumps(doc))
        assert is_complete(tmp_path, "00000") is complete, version
