"""The dataset builder: a 2-sample build read back by a loader written from dataset.json alone, a
crashed-and-resumed build and a dask build equal to the serial build byte for byte, and clear
per-sample errors for missing or corrupt capture files."""

from __future__ import annotations

import json
import os
import pickle
import shutil
import signal
import struct
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import OpenImageIO as oiio
import pytest

from jaxfish.dataset import LAYOUT, build_dataset, is_complete, sample_files, sample_id
from jaxfish.io._folder import is_temporary
from tests.helpers import assert_same_tree

SAMPLES = ("00000", "00001")


# ------------------------------------------------------------------ a loader from dataset.json alone
def _load(path: Path, fmt: str):
    """Decode one file knowing only its format (as dataset.json states it)."""
    if fmt == "png":
        a = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        assert a is not None, path
        return a[..., ::-1] if a.ndim == 3 else a  # cv2 is BGR
    if fmt == "npy":
        return np.load(path, allow_pickle=False)
    if fmt == "exr":  # OpenImageIO itself (the opencv wheel has no EXR support)
        inp = oiio.ImageInput.open(str(path))
        assert inp is not None, path
        spec = inp.spec()
        a = np.asarray(inp.read_image(0, 0, 0, spec.nchannels, spec.format))
        inp.close()
        return a.reshape(spec.height, spec.width, spec.nchannels), tuple(spec.channelnames)
    if fmt == "npz":
        with np.load(path, allow_pickle=False) as z:
            return {k: z[k] for k in z.files}
    if fmt == "flo":
        raw = path.read_bytes()
        tag, w, h = struct.unpack("<fii", raw[:12])
        assert tag == 202021.25
        return np.frombuffer(raw[12:], "<f4").reshape(h, w, 2)
    if fmt == "pickle":
        with open(path, "rb") as fh:
            return pickle.load(fh)
    if fmt == "csv":
        return [line.split(",") for line in path.read_text().splitlines() if line.strip()]
    if fmt == "json":
        return json.loads(path.read_text())
    if fmt == "text":
        return path.read_text().splitlines()
    raise AssertionError(f"unknown format {fmt}")


def test_every_file_is_there_and_reads_back_from_the_layout_alone(reference_build):
    out, report = reference_build
    assert report.built == list(SAMPLES) and not report.failed
    manifest = json.loads((out / "dataset.json").read_text())
    assert manifest["samples"] == list(SAMPLES)
    conv = manifest["conventions"]
    assert conv["depth"]["sky_m"] == 1000.0 and "range" in conv["depth"]["raw_data"]
    assert conv["optical_flow"]["direction"].startswith("forward") and "t-1" in conv["optical_flow"]["grid"]
    assert conv["events"]["raw_data"]["time_unit"] == "ns" and conv["events"]["tonic"]["time_unit"] == "us"
    assert conv["bev"]["metres_per_pixel"] > 0 and len(manifest["classes"]["names"]) == 25
    sizes = {k: tuple(v) for k, v in manifest["image_size_wh"].items()}
    fisheye, cams = manifest["fisheye_cameras"], manifest["cameras"]
    assert fisheye == ["FV", "RV", "MVL", "MVR"] and cams == fisheye + ["BEV"]
    per_cam = {"fisheye": fisheye, "all": cams, "BEV": ["BEV"], "sample": [None]}
    seen = 0
    for entry in manifest["layout"]:
        for sample in manifest["samples"]:
            for cam in per_cam[entry["cameras"]]:
                path = out / entry["pattern"].format(sample=sample, camera=cam)
                assert path.is_file(), path
                data = _load(path, entry["format"])
                seen += 1
                if entry["format"] in ("png", "npy", "flo") and entry["shape"].startswith("(H, W"):
                    w, h = sizes[cam]
                    want = tuple(int(s) for s in entry["shape"].strip("()").replace("H", str(h)).replace("W", str(w)).split(","))
                    assert data.shape == want, (path, data.shape, want)
                    assert str(data.dtype) in entry["dtype"], (path, data.dtype, entry["dtype"])
                if entry["key"] == "events":
                    assert data.dtype.names == ("x", "y", "t", "pol") and np.all(np.diff(data["t"]) >= 0)
                if entry["key"] == "boxes_3d":
                    assert data and all(isinstance(k, int) and v.shape == (8, 3) and v.dtype == np.float64
                                        for k, v in data.items())
                if entry["key"] == "depth_exr":
                    pixels, channels = data
                    assert channels == ("Z",) and pixels.dtype == np.float32
                    raw = np.load(out / f"depth_maps/raw_data/{sample}_{cam}.npy")
                    np.testing.assert_array_equal(pixels[..., 0], raw)
                if entry["key"] == "depth":
                    assert data.max() <= 1000.0 and data.min() >= 0 and (cam == "BEV" or np.any(data == 1000.0))
                if entry["key"] == "motion":
                    assert set(np.unique(data)) <= {0, 255}
                if entry["key"] == "lidar":
                    assert data["points"].dtype == np.float32 and data["points"].shape[1] == 4
    assert seen == 2 * len(sample_files("00000"))
    assert sorted(p.relative_to(out).as_posix() for p in out.rglob("*") if p.is_file() and p.parts[-2] != ".done"
                  and not any(p.match(x) for x in ("dataset.json", "sequence.json", "calibration_data/*",
                                                "*/seg_annotation_info.json"))
                  ) == sorted(sample_files("00000") + sample_files("00001"))
    assert len({e["key"] for e in LAYOUT}) == len(LAYOUT)
    info = json.loads((out / "semantic_annotations/seg_annotation_info.json").read_text())
    assert info["classes"] == manifest["classes"]["names"]
    assert {p.name for p in (out / "calibration_data").iterdir()} == {"FV.json", "RV.json", "MVL.json", "MVR.json", "BEV.json"}


def test_killed_build_resumes_to_the_same_bytes(small_capture, reference_build, tmp_path, monkeypatch):
    out = tmp_path / "dataset"
    real_replace = os.replace
    calls = {"n": 0}

    def crashing_replace(src, dst):
        calls["n"] += 1
        if calls["n"] > 60:  # the process "dies" in the middle of sample 0's files
            raise KeyboardInterrupt("simulated kill")
        return real_replace(src, dst)

    monkeypatch.setattr(os, "replace", crashing_replace)
    with pytest.raises(KeyboardInterrupt):
        build_dataset(small_capture, out, options=None)
    monkeypatch.setattr(os, "replace", real_replace)
    assert not is_complete(out, "00000") and not (out / "dataset.json").exists()
    stale = out / "rgb_images" / ".jaxfish-0badc0de-00000_FV.abcd1234.part.png"  # what a SIGKILL leaves behind
    assert is_temporary(stale.name)  # the name atomic_path gives (tests/io/test_folder.py)
    stale.parent.mkdir(parents=True, exist_ok=True)
    stale.write_bytes(b"half a png")
    report = build_dataset(small_capture, out)
    assert report.ok and report.built == list(SAMPLES) and report.stale_removed >= 1
    assert_same_tree(reference_build[0], out)
    again = build_dataset(small_capture, out)  # everything complete: nothing rebuilt
    assert again.skipped == list(SAMPLES) and not again.built
    assert_same_tree(reference_build[0], out)


def test_dask_local_cluster_build_equals_the_serial_build(small_capture, reference_build, tmp_path):
    pytest.importorskip("distributed")
    out = tmp_path / "dataset"
    # Thread workers (processes=False): process workers give the same bytes but each would start and
    # compile JAX afresh, too slow for a unit test (scripts/bench_build.py times them).
    report = build_dataset(small_capture, out, workers=2, processes=False)
    assert report.ok and sorted(report.built) == list(SAMPLES)
    assert_same_tree(reference_build[0], out)
    from jaxfish.dataset._build import _KEPT

    assert not _KEPT  # the thread workers' kept source (this process's) is dropped with the cluster
    from distributed import LocalCluster

    # HTTP routes on a free port, not 8787: another cluster on the machine must not make it warn.
    with LocalCluster(n_workers=1, threads_per_worker=2, processes=False, dashboard_address=None,
                      scheduler_kwargs={"dashboard_address": "127.0.0.1:0"}) as cluster:
        report = build_dataset(small_capture, tmp_path / "via_scheduler", scheduler=cluster.scheduler_address)
    assert report.ok and sorted(report.built) == list(SAMPLES)
    assert not _KEPT  # its thread workers run in this process too
    assert_same_tree(reference_build[0], tmp_path / "via_scheduler")


def _copy(capture: Path, tmp_path: Path, name: str) -> Path:
    dst = tmp_path / name
    shutil.copytree(capture, dst)
    return dst


def test_missing_or_corrupt_capture_files_fail_their_sample_only(small_capture, reference_build, tmp_path):
    corrupt = _copy(small_capture, tmp_path, "corrupt")
    bad = corrupt / "frames/000001/cameras/RV/left/rgb_curr.png"
    bad.write_bytes(b"\x89PNG not really")
    report = build_dataset(corrupt, tmp_path / "out_corrupt")
    assert report.built == ["00000"] and list(report.failed) == ["00001"]
    assert "rgb_curr.png" in report.failed["00001"] and "RV" in report.failed["00001"]
    assert json.loads((tmp_path / "out_corrupt/dataset.json").read_text())["samples"] == ["00000"]
    ref = reference_build[0]
    for rel in sample_files("00000"):
        assert (tmp_path / "out_corrupt" / rel).read_bytes() == (ref / rel).read_bytes(), rel

    missing = _copy(small_capture, tmp_path, "missing")
    (missing / "frames/000000/actors.json").unlink()
    (missing / "frames/000001/cameras/MVL/top/dvs.npy").unlink()
    report = build_dataset(missing, tmp_path / "out_missing", frames=[0, 1, 7])
    assert not report.built and sorted(report.failed) == ["00000", "00001", "00007"]
    assert "actors.json" in report.failed["00000"] and "file missing" in report.failed["00000"]
    assert "MVL/top/dvs.npy" in report.failed["00001"]
    assert "frame 7" in report.failed["00007"]
    assert "failed" in report.summary() and "actors.json" in report.summary()


_KILL_SCRIPT = """
import os, sys, threading
import jax
jax.config.update("jax_enable_x64", True)  # as tests/conftest.py, so bytes match the reference build
jax.config.update("jax_numpy_dtype_promotion", "strict")
from jaxfish.dataset import build_dataset, sample_files

# The build stops for good where the rename of sample 00001's PAUSE_AT-th file into place would
# be: that file stays a written temporary (.part), the files before it are in place, its marker is
# never written. This process then says "paused <temporary>" and waits for the test's SIGKILL.
PAUSE_AT = len(sample_files("00001")) // 2
real_replace, lock, renamed = os.replace, threading.Lock(), [0]

def replace(src, dst):
    if os.path.basename(os.fspath(dst)).startswith("00001"):
        with lock:
            renamed[0] += 1
            n = renamed[0]
        if n >= PAUSE_AT:  # this one and any later one (other write threads) never complete
            if n == PAUSE_AT:
                print("paused", os.fspath(src), flush=True)
            threading.Event().wait()
    return real_replace(src, dst)

os.replace = replace
build_dataset(sys.argv[1], sys.argv[2])
print("finished: the build never paused", flush=True)
"""


def test_sigkilled_build_resumes_to_the_same_bytes(small_capture, reference_build, tmp_path):
    """A real `kill -9` while the second sample's files are being written, then a resume. The
    build process says when it is there (a line on its stdout): no clock decides when to kill."""
    from tests.helpers import wait_for_line

    out = tmp_path / "dataset"
    log = tmp_path / "stderr.txt"
    with open(log, "wb") as err:
        proc = subprocess.Popen([sys.executable, "-c", _KILL_SCRIPT, str(small_capture), str(out)],
                                stdout=subprocess.PIPE, stderr=err)
        try:
            line = wait_for_line(proc, ("paused ", "finished"))  # None: it died
        finally:
            proc.kill()  # SIGKILL; nothing else happens meanwhile: the build is waiting for it
            proc.wait()  # a SIGKILLed process always ends
            proc.stdout.close()
    assert line is not None and line.startswith("paused "), (line, log.read_text()[-2000:])
    assert proc.returncode == -signal.SIGKILL
    half_written = Path(line.removeprefix("paused "))
    assert half_written.is_file() and ".part" in half_written.name  # what the kill left behind
    assert is_complete(out, "00000") and not is_complete(out, "00001")
    assert 0 < len([p for p in out.rglob("00001*") if p.is_file()]) < len(sample_files("00001"))
    report = build_dataset(small_capture, out)
    assert report.ok and report.skipped == ["00000"] and report.built == ["00001"] and report.stale_removed >= 1
    assert not half_written.exists()
    assert_same_tree(reference_build[0], out)


def test_backward_flow_option_writes_the_t_to_t_minus_1_flow(small_capture, reference_build, tmp_path):
    """``backward_flow``: the extra folder, on the t grid; the static ego body (zero forward flow)
    has zero backward flow too; the other files equal the default build."""
    from jaxfish.dataset import BuildOptions, build_sample
    from jaxfish.io import read_flo, read_label_png

    out = tmp_path / "dataset"
    marker = build_sample(small_capture, out, 1, BuildOptions(backward_flow=True))
    ref = reference_build[0]
    for cam in ("FV", "RV", "MVL", "MVR"):
        back = read_flo(out / "optical_flow_backward" / "raw_data" / f"00001_{cam}.flo")
        fwd = read_flo(ref / "optical_flow" / "raw_data" / f"00001_{cam}.flo")
        assert back.shape == fwd.shape and back.dtype == np.float32 and np.all(np.isfinite(back))
        assert (out / "optical_flow_backward" / "color_coded" / f"00001_{cam}.png").is_file()
        ego = read_label_png(ref / "semantic_annotations" / "gtLabels" / f"00001_{cam}.png") == 24
        np.testing.assert_allclose(back[ego], 0.0, atol=1e-3)
        assert np.abs(back).max() > 0  # the rest of the scene moves
    for rel in marker["files"]:
        if not rel.startswith("optical_flow_backward/"):
            assert (out / rel).read_bytes() == (ref / rel).read_bytes(), rel


def test_consecutive_frames_reuse_decoded_images_with_the_same_bytes(small_capture, tmp_path):
    """A capture whose frame-1 ``*_prev.png`` are byte copies of frame 0's ``*_curr.png`` (what the
    CARLA capture program writes for consecutive ticks): building the frames in order reuses the
    decoded t images as the next t-1 images, and gives the bytes of building each frame afresh."""
    from jaxfish.dataset import build_sample
    from jaxfish.io import forget_decoded_images

    cap = tmp_path / "cap"
    shutil.copytree(small_capture, cap)
    for curr in (cap / "frames" / "000000").rglob("*_curr.png"):
        if not curr.name.startswith(("instance", "height")):
            rel = curr.relative_to(cap / "frames" / "000000")
            shutil.copyfile(curr, cap / "frames" / "000001" / rel.parent / curr.name.replace("_curr", "_prev"))
    forget_decoded_images()
    in_order = [build_sample(cap, tmp_path / "in_order", f) for f in (0, 1)]
    fresh = []
    for f in (0, 1):
        forget_decoded_images()
        fresh.append(build_sample(cap, tmp_path / "fresh", f))
    forget_decoded_images()
    assert in_order == fresh  # the markers list every file with its SHA-256


def _worker_environ():
    return {k: os.environ.get(k) for k in ("MALLOC_TRIM_THRESHOLD_", "MALLOC_ARENA_MAX", "OMP_NUM_THREADS",
                                       "XLA_PYTHON_CLIENT_PREALLOCATE")}


def _affinity() -> tuple[int, ...]:
    return tuple(sorted(os.sched_getaffinity(0)))


def test_local_cluster_workers_keep_glibcs_dynamic_mmap_threshold_and_get_their_own_cores(monkeypatch):
    from distributed import Client

    from jaxfish.dataset import DatasetError, core_shares, local_cluster, share_cores
    from jaxfish.dataset._runtime import ARENA_MAX_ENV, MALLOC_ARENAS

    monkeypatch.delenv("XLA_PYTHON_CLIENT_PREALLOCATE", raising=False)
    monkeypatch.delenv(ARENA_MAX_ENV, raising=False)
    with pytest.raises(DatasetError, match="at least 1"):
        local_cluster(0)
    with local_cluster(2) as cluster, Client(cluster) as client:
        envs = list(client.run(_worker_environ).values())
        pinned = share_cores(client)
        if hasattr(os, "sched_getaffinity"):  # each worker on its own share of this process's cores
            assert sorted(pinned.values()) == sorted(core_shares(2, sorted(os.sched_getaffinity(0))))
            assert client.run(_affinity) == pinned
        else:
            assert pinned == {}
    for env in envs:
        assert env["MALLOC_TRIM_THRESHOLD_"] is None  # dask's nannies would set 65536
        assert env["MALLOC_ARENA_MAX"] == str(MALLOC_ARENAS)  # capped from the start, as tune_allocator caps
        assert env["OMP_NUM_THREADS"] == "1"  # the rest of dask's worker environment is kept
        assert env["XLA_PYTHON_CLIENT_PREALLOCATE"] == "false"  # the workers can share one GPU


def test_local_cluster_workers_keep_a_heap_limit_the_environment_sets(monkeypatch):
    from distributed import Client

    from jaxfish.dataset import local_cluster

    monkeypatch.setenv("MALLOC_ARENA_MAX", "5")
    with local_cluster(1) as cluster, Client(cluster) as client:
        assert [env["MALLOC_ARENA_MAX"] for env in client.run(_worker_environ).values()] == ["5"]


def test_processes_sharing_a_gpu_allocate_as_they_need_unless_the_environment_says(monkeypatch):
    """`accelerator_sharing_env` (the workers') and `share_accelerator` (the building process's)
    keep a value the environment sets; unset, the workers get ``false``, and a process whose JAX
    has started keeps its backends (here the CPU's: nothing to share, nothing set)."""
    import jax

    from jaxfish.dataset._runtime import PREALLOCATE_ENV, accelerator_sharing_env, share_accelerator

    assert PREALLOCATE_ENV == "XLA_PYTHON_CLIENT_PREALLOCATE"
    jax.devices()  # JAX has started in this process
    monkeypatch.setenv(PREALLOCATE_ENV, "true")
    assert accelerator_sharing_env() == {} and share_accelerator() is False
    monkeypatch.setenv(PREALLOCATE_ENV, "false")
    assert accelerator_sharing_env() == {} and share_accelerator() is True
    monkeypatch.delenv(PREALLOCATE_ENV)
    assert accelerator_sharing_env() == {PREALLOCATE_ENV: "false"}
    assert share_accelerator() is (jax.default_backend() != "gpu")
    assert PREALLOCATE_ENV not in os.environ  # too late to set it here
    env = {k: v for k, v in os.environ.items() if k != PREALLOCATE_ENV}
    fresh = ("import os; from jaxfish.dataset._runtime import share_accelerator as s; "
             "assert s() is True and os.environ['XLA_PYTHON_CLIENT_PREALLOCATE'] == 'false'")
    subprocess.run([sys.executable, "-c", fresh], env=env, check=True, timeout=300)  # before JAX starts: set


def test_core_shares_split_the_cores_disjointly_or_round_robin():
    from jaxfish.dataset import core_shares

    assert core_shares(1, [0, 1]) == [(0, 1)]
    assert core_shares(2, [0, 1]) == [(0,), (1,)]
    assert core_shares(2, [0, 1, 2, 3]) == [(0, 1), (2, 3)]
    assert core_shares(3, [4, 5, 6, 7, 8]) == [(4, 5), (6,), (7, 8)]
    assert core_shares(3, [0, 1]) == [(0,), (1,), (0,)]
    with pytest.raises(ValueError, match="at least one worker"):
        core_shares(0, [0])


class _Scheduler:
    """A stand-in for a dask client: only ``scheduler_info`` (``None``: the query fails)."""

    def __init__(self, workers: dict | None):
        self.workers = workers

    def scheduler_info(self) -> dict:
        if self.workers is None:
            raise OSError("no scheduler")
        return {"workers": self.workers}


def test_dask_workers_build_contiguous_runs_of_frames_in_order():
    """With two workers or more, each worker is handed a contiguous run of the batches (in frame
    order, run i on worker i by name), submitted step by step across the runs, so that a worker's
    samples follow each other as in a serial build; fewer workers, or none known, place nothing."""
    from jaxfish.dataset._build import _placement, _worker_runs

    keys = [f"k{i}" for i in range(7)]
    two = _Scheduler({"tcp://b": {"name": 1}, "tcp://a": {"name": 0}})
    assert _worker_runs(two, keys) == [("k0", "tcp://a"), ("k4", "tcp://b"), ("k1", "tcp://a"), ("k5", "tcp://b"),
                                       ("k2", "tcp://a"), ("k6", "tcp://b"), ("k3", "tcp://a")]
    three = _Scheduler({f"tcp://{n}": {"name": n} for n in range(3)})
    runs = _worker_runs(three, keys[:4])
    assert sorted(runs) == [("k0", "tcp://0"), ("k1", "tcp://1"), ("k2", "tcp://1"), ("k3", "tcp://2")]
    assert [k for k, w in runs if w == "tcp://1"] == ["k1", "k2"]  # a run in frame order
    for client in (_Scheduler({"tcp://a": {"name": 0}}), _Scheduler({}), _Scheduler(None)):
        assert _worker_runs(client, keys) == [(k, None) for k in keys]
    assert _worker_runs(two, []) == []
    assert _placement(None) == {}
    assert _placement("tcp://a") == {"workers": ["tcp://a"], "allow_other_workers": True}


def test_each_dask_worker_runs_its_frames_in_frame_order(monkeypatch):
    """On a real cluster (of thread workers, behind its scheduler's address), the submitted runs
    reach the workers in frame order:
    each worker builds its contiguous run first to last (dask alone would run the later
    submissions first). Work stealing is off so that no batch changes worker."""
    pytest.importorskip("distributed")
    import threading

    import dask
    from distributed import get_worker

    from jaxfish.dataset import BuildOptions, _build

    ran: list[tuple[str, int]] = []
    lock = threading.Lock()

    def task(source, out_dir, frames, options):
        with lock:
            ran.extend((str(get_worker().name), f) for f in frames)
        return [(sample_id(f), None) for f in frames]

    monkeypatch.setattr(_build, "_counted_batch_task", task)
    recorded: list[str] = []
    with dask.config.set({"distributed.scheduler.work-stealing": False}), \
            _build.local_cluster(2, processes=False) as cluster:
        _build._run_dask("a source", "out", list(range(10)), BuildOptions(), cluster.scheduler_address, None,
                         lambda sid, err: recorded.append(sid))
    assert sorted(recorded) == [sample_id(f) for f in range(10)]
    runs = {}
    for worker, frame in ran:
        runs.setdefault(worker, []).append(frame)
    assert sorted(runs.values()) == [[0, 1, 2, 3, 4], [5, 6, 7, 8, 9]]


def test_a_worker_keeps_the_source_its_tasks_are_handed(small_capture, tmp_path):
    """Every dask task unpickles its own copy of the source; `_kept_source` hands the worker's
    tasks the first instance of an equal source (same pickled state), so that its kept decodes
    serve the next frame, and forgets it for another source and with `clear_worker_cache`."""
    from jaxfish.dataset import CaptureSource, clear_worker_cache
    from jaxfish.dataset._build import _kept_source

    clear_worker_cache()
    first = _kept_source(CaptureSource(small_capture))
    assert _kept_source(pickle.loads(pickle.dumps(first))) is first
    other = CaptureSource(_copy(small_capture, tmp_path, "other"))
    assert _kept_source(other) is other
    assert _kept_source(pickle.loads(pickle.dumps(first))) is not first  # only the last source is kept
    clear_worker_cache()
    fresh = CaptureSource(small_capture)
    assert _kept_source(fresh) is fresh


def test_batched_frames_build_equals_the_serial_build_and_isolates_failures(small_capture, reference_build, tmp_path):
    """``batch_frames=2``: both samples' ground truth in one `sample_truths` call (serial, and as
    one dask task): the bytes of the per-sample build; a corrupt file fails its own sample only."""
    from jaxfish.dataset import BuildOptions, DatasetError

    opts = BuildOptions(batch_frames=2)
    report = build_dataset(small_capture, tmp_path / "batched", options=opts)
    assert report.ok and sorted(report.built) == list(SAMPLES)
    assert_same_tree(reference_build[0], tmp_path / "batched")
    pytest.importorskip("distributed")
    report = build_dataset(small_capture, tmp_path / "batched_dask", options=opts, workers=1, processes=False)
    assert report.ok and sorted(report.built) == list(SAMPLES)
    assert_same_tree(reference_build[0], tmp_path / "batched_dask")

    corrupt = _copy(small_capture, tmp_path, "corrupt")
    (corrupt / "frames/000001/cameras/RV/left/rgb_curr.png").write_bytes(b"\x89PNG not really")
    report = build_dataset(corrupt, tmp_path / "out_corrupt", options=opts)
    assert report.built == ["00000"] and list(report.failed) == ["00001"]
    assert "rgb_curr.png" in report.failed["00001"] and "RV" in report.failed["00001"]
    with pytest.raises(DatasetError, match="batch_frames"):
        BuildOptions(batch_frames=0)


class _SlowRig:
    """A source whose first frames are read while `rig_constants_of` builds its constants."""

    face_size, faces, where = 8, ("front",), "<fake source>"

    def __init__(self, read):
        self._read = read

    def constants_key(self):
        return ("fake source", id(self))

    def has_bev(self):
        return False

    def rig(self):
        return {}

    def read(self, frame, bev=True):
        return self._read(frame)


def test_the_first_frames_are_read_while_the_constants_build(monkeypatch):
    import threading

    from jaxfish.dataset import _build

    building, read_done = threading.Event(), threading.Event()

    def constants(*args, **kwargs):
        building.set()
        assert read_done.wait(30), "the frames were not read while the constants were built"
        return "constants"

    def read(frame):
        assert building.wait(30), "the constants were not being built during the read"
        read_done.set()
        return frame

    monkeypatch.setattr(_build, "rig_constants", constants)
    source = _SlowRig(read)
    try:
        assert _build._constants_and_frames(source, [3, 4], True) == ("constants", [3, 4])
        assert _build._constants_and_frames(source, [5], True) == ("constants", [5])  # built once: kept
    finally:
        _build._CACHE.pop(source.constants_key(), None)


def test_a_constants_error_is_raised_before_a_read_error(monkeypatch):
    from jaxfish.dataset import DatasetError, _build

    def constants(*args, **kwargs):
        raise DatasetError("<fake source>: field 'intrinsic': no ray")

    def read(frame):
        raise ValueError("frame unreadable")

    monkeypatch.setattr(_build, "rig_constants", constants)
    source = _SlowRig(read)
    with pytest.raises(DatasetError, match="intrinsic"):
        _build._constants_and_frames(source, [0], True)
    assert source.constants_key() not in _build._CACHE


def test_local_workers_are_threads_up_to_the_limit_unless_told():
    from jaxfish.dataset import THREAD_WORKERS_MAX, local_processes

    assert not local_processes(THREAD_WORKERS_MAX, None) and local_processes(THREAD_WORKERS_MAX + 1, None)
    assert local_processes(1, True) and not local_processes(8, False)


def test_thread_workers_build_contiguous_runs_in_frame_order_and_share_out_the_rest(monkeypatch):
    """`_run_threads`: this thread builds the first frame, each thread a contiguous run after it in
    frame order; a thread done early takes the later half of the longest run left; every frame is
    built once, the results are recorded in this thread, and the sequence slots are restored."""
    import threading

    from jaxfish.dataset import BuildOptions, _build
    from jaxfish.pipeline import sequence_slots

    ran: list[tuple[str, int]] = []
    recorded: list[tuple[str, str]] = []
    lock = threading.Lock()

    took_over = threading.Event()

    def task(source, out_dir, frames, options):
        name = threading.current_thread().name
        with lock:
            ran.extend((name, f) for f in frames)
        if name == "jaxfish-build-0" and frames[0] > 11:
            took_over.set()
        if name == "jaxfish-build-1":  # a slow worker: held in its first frame until the other takes over
            assert took_over.wait(60), "hang guard: the idle thread did not take over frames"
        return [(sample_id(f), None) for f in frames]

    monkeypatch.setattr(_build, "_counted_batch_task", task)
    before = sequence_slots()
    _build._run_threads("a source", "out", list(range(21)), BuildOptions(), 2,
                        lambda sid, err: recorded.append((threading.current_thread().name, sid)))
    assert sequence_slots() == before
    assert sorted(f for _, f in ran) == list(range(21))
    assert {name for name, _ in recorded} == {threading.current_thread().name}
    by_thread: dict[str, list[int]] = {}
    for name, frame in ran:
        by_thread.setdefault(name, []).append(frame)
    assert by_thread[threading.current_thread().name] == [0]
    first, second = by_thread["jaxfish-build-0"], by_thread["jaxfish-build-1"]
    assert first[:10] == list(range(1, 11)) and second[0] == 11  # the two runs, each from its start
    assert len(first) > 10  # the fast thread took over the slow one's later frames
    assert second == list(range(11, 11 + len(second)))  # the slow one kept the start of its run
    stretches = 1 + sum(b != a + 1 for a, b in zip(first, first[1:], strict=False))
    assert stretches <= 5  # its own run, then later halves of the slow one's, each in frame order
