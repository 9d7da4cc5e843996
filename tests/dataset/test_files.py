"""The builder's own file helpers against independent references: NumPy event mapping vs a loop
over the rule (tests/groundtruth/test_files.py checks a capture's event counts against the JAX event map), deterministic
npz, the depth colour map."""

from __future__ import annotations

import os
import time

import numpy as np
import pytest

from jaxfish._constants import DVS_EVENT_DTYPE
from jaxfish.groundtruth import EventMap
from jaxfish.io import write_npz
from jaxfish.pipeline import (
    FaceEventTable,
    camera_events,
    depth_to_color,
    events_color,
    face_event_table,
    map_face_events,
)


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


@pytest.mark.parametrize("few_runs", [0, None, 10**9])
def test_time_order_is_the_stable_argsort(monkeypatch, few_runs):
    """The merge of a few ascending runs, the packed-key sort and its fallback (spans too long to
    pack) give NumPy's stable order; each path is forced on every case through `_FEW_RUNS`."""
    from jaxfish.pipeline import _events
    from jaxfish.pipeline._events import _time_order

    if few_runs is not None:
        monkeypatch.setattr(_events, "_FEW_RUNS", few_runs)
    rng = np.random.default_rng(3)
    cases = [np.zeros(0, np.int64), np.array([5], np.int64), rng.integers(0, 30, 5000),  # many ties
             np.concatenate([np.sort(rng.integers(-10**9, 10**9, 700)) for _ in range(5)]),  # sorted runs
             np.concatenate([np.sort(rng.integers(0, 40, 90)) for _ in range(7)]),  # runs with ties across them
             np.concatenate([np.sort(rng.integers(0, 10**6, 20)) for _ in range(400)]),  # more runs than merged
             rng.integers(-2**62, 2**62, 3000),  # too long a span: the fallback
             np.array([np.iinfo(np.int64).min, np.iinfo(np.int64).max, 0, 0])]
    for t in cases:
        order, ts = _time_order(t.astype(np.int64))
        want = np.argsort(t, kind="stable")
        np.testing.assert_array_equal(order, want)
        np.testing.assert_array_equal(ts, t[want])


def test_camera_events_face_by_face_equal_the_mapping_of_all_faces():
    """`camera_events` (each face mapped on its own) gives the events of `map_face_events` of the
    concatenated faces: same order (time, then face, event and fisheye pixel), out-of-face events
    dropped, empty faces, fan-outs of 0 to 3, faces beyond the map's."""
    rng = np.random.default_rng(1)
    faces, size, width, height, m = 3, 5, 9, 6, 3
    n_src = faces * size * size
    fan = rng.integers(0, m + 1, n_src)
    targets = np.full((n_src, m), -1, np.int32)
    for i in range(n_src):
        targets[i, : fan[i]] = np.sort(rng.choice(width * height, fan[i], replace=False))
    emap = EventMap(targets=targets, fanout=fan.astype(np.int32), width=width, height=height, face_size=size,
                    num_faces=faces, max_fanout=m)
    per_face = []
    for k in (40, 0, 55, 7):  # the fourth face is beyond the map: its events feed nothing
        ev = np.zeros(k, DVS_EVENT_DTYPE)
        ev["x"], ev["y"] = rng.integers(0, size + 2, k), rng.integers(0, size, k)  # some x outside the face
        ev["t"], ev["pol"] = np.sort(rng.integers(0, 30, k)), rng.random(k) < 0.5
        per_face.append(ev)
    got = camera_events(per_face, emap)
    assert camera_events(per_face, face_event_table(emap)).tobytes() == got.tobytes()  # the map's table: the same events
    cat = np.concatenate(per_face)
    face = np.concatenate([np.full(len(ev), i) for i, ev in enumerate(per_face)])
    want = map_face_events(targets, width, size, face, cat["x"], cat["y"], cat["t"], cat["pol"], fanout=fan)
    assert got.dtype == DVS_EVENT_DTYPE and got.tobytes() == want.tobytes() and len(got) > 0
    assert camera_events([np.zeros(0, DVS_EVENT_DTYPE)] * 3, emap).shape == (0,)


def test_face_event_table_is_the_event_map_compacted():
    """Per face pixel its only target, -1 for none, ``-2 - j`` pointing at row ``j`` of the pixels
    that feed several (their targets in slot order and their count); read-only, and smaller than
    the dense map when few pixels feed several."""
    targets = np.asarray([[3, 5], [-1, -1], [4, -1], [0, 1], [7, -1], [2, 6]], np.int32)  # six faces of one pixel
    emap = EventMap(targets=targets, fanout=np.asarray([2, 0, 1, 2, 1, 1], np.int32), width=4, height=2, face_size=1,
                    num_faces=6, max_fanout=2)
    table = face_event_table(emap)
    assert table.first.tolist() == [-2, -1, 4, -3, 7, 2]  # the last pixel's fan-out of 1 keeps its first target only
    assert table.many.tolist() == [[3, 5], [0, 1]] and table.many_count.tolist() == [2, 2]
    assert (table.width, table.face_size) == (4, 1)
    assert not any(a.flags.writeable for a in (table.first, table.many, table.many_count))


def test_rig_constants_keep_the_compact_table_not_the_dense_map():
    from jaxfish import default_rig
    from jaxfish.groundtruth import event_map_from_lut
    from jaxfish.pipeline import camera_constants

    calibration = default_rig(width=160, height=120)["FV"]
    k = camera_constants("FV", calibration, faces=("front", "left", "right", "top", "bottom"), face_size=96)
    emap = event_map_from_lut(k.lut)
    table = k.event_table
    assert isinstance(table, FaceEventTable) and not hasattr(k, "event_map")
    assert table.first.tobytes() == face_event_table(emap).first.tobytes()
    dense = np.asarray(emap.targets).nbytes + np.asarray(emap.fanout).nbytes
    assert table.first.nbytes + table.many.nbytes + table.many_count.nbytes < dense / 2


def test_camera_events_keep_one_host_map_per_event_map_while_it_lives():
    import gc

    import jaxfish.pipeline._events as events_module

    targets = np.asarray([[3, 5], [-1, -1], [4, -1], [0, 1]], np.int32)  # 1 face of 2 x 2 pixels
    emap = EventMap(targets=targets, fanout=np.asarray([2, 0, 1, 1], np.int32), width=3, height=2, face_size=2,
                    num_faces=1, max_fanout=2)
    ev = np.zeros(4, DVS_EVENT_DTYPE)
    ev["x"], ev["y"], ev["t"] = [0, 1, 0, 1], [0, 0, 1, 1], [1, 2, 3, 3]
    got = camera_events([ev], emap)
    assert [(int(a), int(b), int(c)) for a, b, c in zip(got["t"], got["x"], got["y"], strict=True)] == \
        [(1, 0, 1), (1, 2, 1), (3, 1, 1), (3, 0, 0)]  # pixel 0 feeds two, pixel 1 none
    table = events_module._host_map_of(emap)
    assert events_module._host_map_of(emap) is table and table.first.tolist() == [-2, -1, 4, 0]
    key = id(emap.targets)
    del emap, targets
    gc.collect()
    assert key not in events_module._HOST_MAPS


def test_events_color_is_the_net_polarity_per_pixel():
    ev = np.zeros(6, DVS_EVENT_DTYPE)
    ev["x"], ev["y"] = [0, 0, 1, 2, 2, 7], [0, 0, 0, 1, 1, 0]  # the last one outside a 3 x 2 image
    ev["pol"] = [True, True, False, True, False, True]
    img = events_color(ev, width=3, height=2)
    assert img.shape == (2, 3, 3) and img.dtype == np.uint8
    assert img[0, 0].tolist() == [0, 0, 255] and img[0, 1].tolist() == [255, 0, 0]
    assert img[1, 2].tolist() == [255, 255, 255] and img[1, 0].tolist() == [255, 255, 255]  # net 0, none


@pytest.mark.parametrize("tonic", [False, True])
def test_events_color_equals_its_jax_twin(tonic):
    """The host rendering equals `jaxfish.groundtruth.events_to_color` on random events, ties,
    and (tonic's signed coordinates) events outside the image on every side."""
    from jaxfish.groundtruth import events_to_color
    from jaxfish.io._events import TONIC_EVENT_DTYPE

    rng = np.random.default_rng(3)
    n, w, h = 4000, 17, 11
    ev = np.zeros(n, TONIC_EVENT_DTYPE if tonic else DVS_EVENT_DTYPE)
    lo = -3 if tonic else 0
    ev["x"], ev["y"] = rng.integers(lo, w + 3, n), rng.integers(lo, h + 3, n)
    pol = rng.random(n) < 0.5
    if tonic:
        ev["p"] = pol
    else:
        ev["pol"] = pol
    want = np.asarray(events_to_color(ev["x"], ev["y"], pol, width=w, height=h))
    np.testing.assert_array_equal(events_color(ev, width=w, height=h), want)


def test_a_sequence_writes_its_previous_images_from_the_kept_png(tmp_path, monkeypatch):
    """The RGB at t is kept with its PNG bytes; the next sample's image at t-1, the same array,
    is written from them: `write_image`'s bytes, no second encode. Another array (even with
    equal pixels) or another level is encoded."""
    from jaxfish.dataset import _sink
    from jaxfish.io import write_image

    encodes = []
    encode = _sink.png_image_bytes
    monkeypatch.setattr(_sink, "png_image_bytes", lambda *a, **k: (encodes.append(1), encode(*a, **k))[1])
    last = _sink._LastRgb()
    rgb = np.random.default_rng(0).integers(0, 256, (9, 7, 3), dtype=np.uint8)
    last.write(tmp_path / "t.png", "FV", rgb, 1, keep=True)
    last.write(tmp_path / "prev.png", "FV", rgb, 1)
    assert len(encodes) == 1
    expected = write_image(tmp_path / "ref.png", rgb, png_level=1).read_bytes()
    assert (tmp_path / "t.png").read_bytes() == (tmp_path / "prev.png").read_bytes() == expected
    for other, level in ((rgb.copy(), 1), (rgb, 2)):
        last.write(tmp_path / "x.png", "FV", other, level)
    last.write(tmp_path / "y.png", "MVL", rgb, 1)
    assert len(encodes) == 4
    last.clear()
    last.write(tmp_path / "prev.png", "FV", rgb, 1)
    assert len(encodes) == 5
    # A worker's caches are dropped together (`clear_worker_cache`).
    from jaxfish.dataset import clear_worker_cache

    _sink._LAST_RGB.write(tmp_path / "z.png", "FV", rgb, 1, keep=True)
    clear_worker_cache()
    _sink._LAST_RGB.write(tmp_path / "z.png", "FV", rgb, 1)
    assert len(encodes) == 7


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


def _npz_by_numpy_writer(path, **arrays):
    """The reference layout: each array through ``np.lib.format.write_array`` into a stored zip64
    member stamped 1980-01-01, as ``np.savez`` lays them out."""
    import zipfile

    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_STORED) as zf:
        for name, arr in arrays.items():
            info = zipfile.ZipInfo(f"{name}.npy", date_time=(1980, 1, 1, 0, 0, 0))
            with zf.open(info, "w", force_zip64=True) as fh:
                np.lib.format.write_array(fh, np.asanyarray(arr), allow_pickle=False)
    return path.read_bytes()


def test_npz_bytes_are_numpys_for_every_array_layout(tmp_path):
    from jaxfish.io._npz import NpzMember

    rng = np.random.default_rng(3)
    events = np.zeros(1000, [("x", "<i8"), ("y", "<i8"), ("t", "<i8"), ("p", "<i8")])
    events["t"] = rng.integers(0, 10**9, 1000)
    arrays = {"events": events, "time_unit": np.asarray("us"), "empty": np.zeros((0, 3), np.float32),
              "fortran": np.asfortranarray(rng.random((4, 5))), "strided": rng.random((6, 8))[::2, ::3],
              "bool": rng.random((3, 3)) < 0.5, "long_header": np.zeros(2, [(f"f{i}", "<u2") for i in range(4000)])}
    with pytest.warns(UserWarning, match="format 2.0"):  # the long header needs .npy version 2, as in NumPy
        ours = write_npz(tmp_path / "a.npz", **arrays).read_bytes()
    with pytest.warns(UserWarning, match="format 2.0"):
        assert ours == _npz_by_numpy_writer(tmp_path / "ref.npz", **arrays)

    def chunks():  # the same events in uneven chunks
        raw = events.view(np.uint8)
        return (raw[i:i + 7000] for i in range(0, raw.size, 7000))

    streamed = write_npz(tmp_path / "s.npz", events=NpzMember(events.dtype, events.shape, chunks), time_unit=np.asarray("us"))
    assert streamed.read_bytes() == _npz_by_numpy_writer(tmp_path / "ref2.npz", events=events, time_unit=np.asarray("us"))
    with pytest.raises(ValueError, match="chunks hold 7000 bytes"):
        write_npz(tmp_path / "short.npz", events=NpzMember(events.dtype, events.shape, lambda: [events.view(np.uint8)[:7000]]))
    assert not (tmp_path / "short.npz").exists()  # atomic: nothing half-written
    with pytest.raises(ValueError, match="allow_pickle=False"):
        write_npz(tmp_path / "obj.npz", a=np.asarray([{}], object))


def test_depth_colors_near_bright_far_dark_sky_black():
    c = depth_to_color(np.asarray([[0.5, 10.0, 100.0, 1000.0, 0.0]], np.float32)).astype(int)
    assert c.dtype == np.int64 and c.shape == (1, 5, 3)
    lum = c[0].sum(-1)
    assert lum[0] > lum[1] > lum[2] > 0 and lum[3] == 0 and lum[4] == 0
    assert not depth_to_color(np.asarray([np.nan, -1.0, np.inf], np.float32)).any()  # any shape; not a depth: black
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


_HEAPS_SCRIPT = """
import ctypes, os, sys, tempfile, threading
import numpy as np
tune = sys.argv[1] == "tune"
if tune:
    from jaxfish.dataset import tune_allocator
    assert tune_allocator()
barrier = threading.Barrier(8)
def work():
    a = np.ones(1 << 20, np.uint8)  # each thread allocates while the others hold theirs
    barrier.wait()
    del a
threads = [threading.Thread(target=work) for _ in range(8)]
for t in threads: t.start()
for t in threads: t.join()
libc = ctypes.CDLL("libc.so.6")
libc.fopen.restype = ctypes.c_void_p
libc.fopen.argtypes, libc.malloc_info.argtypes, libc.fclose.argtypes = [ctypes.c_char_p] * 2, [ctypes.c_int, ctypes.c_void_p], [ctypes.c_void_p]
path = os.path.join(tempfile.mkdtemp(), "info.xml")
fp = libc.fopen(path.encode(), b"w")
libc.malloc_info(0, fp)
libc.fclose(fp)
print(open(path).read().count("<heap nr="))
"""


def test_tuned_threads_share_at_most_malloc_arenas_heaps():
    """`tune_allocator` caps glibc's heaps at `MALLOC_ARENAS` for threads that allocate after it
    (glibc's default gives each of eight concurrent threads a heap of its own)."""
    import subprocess
    import sys

    from jaxfish.dataset._runtime import MALLOC_ARENAS

    env = {k: v for k, v in os.environ.items() if not k.startswith("MALLOC_")}
    heaps = {mode: int(subprocess.run([sys.executable, "-c", _HEAPS_SCRIPT, mode], capture_output=True, text=True,
                                      check=True, env=env).stdout.strip().splitlines()[-1])
             for mode in ("tune", "default")}
    assert heaps["default"] > MALLOC_ARENAS  # the measurement sees the threads' heaps
    assert 1 <= heaps["tune"] <= MALLOC_ARENAS


@pytest.mark.parametrize("tune, env, applied", [(None, False, True), (False, False, False), (False, True, True)])
def test_a_building_process_tunes_the_allocator_unless_told_not_to(monkeypatch, tune, env, applied):
    """`BuildOptions.tune_allocator` is on by default; off, the allocator is still tuned where the
    environment sets ``MALLOC_TRIM_THRESHOLD_`` (dask's nannies)."""
    from jaxfish.dataset import BuildOptions, _build

    calls = []
    monkeypatch.setattr(_build, "tune_allocator", lambda: calls.append(1) or True)
    monkeypatch.setattr(_build, "use_compile_cache", lambda cache: None)
    if env:
        monkeypatch.setenv("MALLOC_TRIM_THRESHOLD_", "65536")
    else:
        monkeypatch.delenv("MALLOC_TRIM_THRESHOLD_", raising=False)
    options = BuildOptions() if tune is None else BuildOptions(tune_allocator=tune)
    _build._prepare_process(options)
    assert bool(calls) is applied


def test_a_building_process_reads_and_writes_openexr_in_the_calling_thread(monkeypatch, tmp_path):
    """The builder's own threads write the files: OpenEXR gets no thread pool of its own, and an
    EXR's bytes do not depend on it."""
    import OpenImageIO as oiio

    from jaxfish.dataset import BuildOptions, _build
    from jaxfish.io import write_depth_exr

    monkeypatch.setattr(_build, "tune_allocator", lambda: True)
    monkeypatch.setattr(_build, "use_compile_cache", lambda cache: None)
    depth = np.random.default_rng(0).uniform(0.5, 1000.0, (67, 45)).astype(np.float32)
    before = oiio.get_int_attribute("exr_threads")
    try:
        oiio.attribute("exr_threads", 2)
        pooled = write_depth_exr(tmp_path / "pooled.exr", depth, {"unit": "m"}).read_bytes()
        _build._prepare_process(BuildOptions())
        assert oiio.get_int_attribute("exr_threads") == -1
        assert write_depth_exr(tmp_path / "caller.exr", depth, {"unit": "m"}).read_bytes() == pooled
    finally:
        oiio.attribute("exr_threads", before)


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
