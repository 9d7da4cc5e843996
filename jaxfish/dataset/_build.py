"""Capture directory in, SynWoodScape-style dataset out: serial, resumable, or on a Dask cluster.

Each sample is a pure function of (capture, frame, options): `build_sample` reads the capture's
frame, computes every camera's ground truth and writes the sample's files atomically, then its
completion marker ``.done/{sample}.json`` (the capture's fingerprint, the options, the files and
their SHA-256) last. `build_dataset` writes only into a new, empty or jaxfish dataset folder, which
it locks; it removes the temporary files a killed run left behind, refuses a folder whose samples
another capture or other options made (unless asked to rebuild them), skips complete samples, runs
the remaining samples serially or on a dask.distributed cluster (the bytes are the same), reports
each failing sample with its reason, and finally writes the dataset-level files (``dataset.json``,
``calibration_data``, ``seg_annotation_info.json``).
"""

from __future__ import annotations

import concurrent.futures
import contextlib
import dataclasses
import hashlib
import json
import math
import os
import pickle
import stat
import threading
import time
import traceback
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from .._errors import JaxfishError
from ._layout import BEV_CAMERA, FISHEYE_CAMERAS, LAYOUT, LAYOUT_VERSION, sample_id
from ._runtime import BUILD_PID_ENV, share_cores, tune_allocator

DONE_DIR = ".done"
"""Folder of the per-sample completion markers."""


_NO_VALUE = object()


class DatasetError(JaxfishError):
    """A dataset build cannot start or a sample cannot be built (names the file and the reason)."""


class BuildInterrupted(KeyboardInterrupt):
    """`build_dataset` stopped by a ``KeyboardInterrupt`` (Ctrl-C; ``jaxfish build`` turns SIGTERM
    into one too). Its local workers have ended before it is raised and the files of the samples
    it cut off are removed, so complete samples stay and re-running the same build resumes.
    ``report``: the `BuildReport` so far; ``complete``: the requested samples that are complete."""

    def __init__(self, report: BuildReport, complete: list[str]):
        super().__init__(f"build interrupted: {len(complete)} of {len(report.samples)} sample(s) complete")
        self.report = report
        self.complete = complete


@dataclasses.dataclass(frozen=True)
class BuildOptions:
    """What a build computes (every option changes the bytes of some file, so `dataset.json`
    records them): ``backward_flow`` also writes ``optical_flow_backward`` (t -> t-1 on the t
    grid); ``bev`` builds the top-view camera's files when the capture has one;
    ``motion_threshold_m`` is the motion-mask threshold on the actor displacement;
    ``png_level`` is the zlib level (0-9) of every PNG (1: fastest; 6-9: ~30 % smaller PNGs, 2-4x
    slower to write); ``write_threads`` writes files in a thread pool while the next camera computes
    (0 = inline); ``tune_allocator`` applies `tune_allocator` in the processes that build samples
    (off by default: no measurable gain for a whole build, whose time is mostly I/O, and 1 GB more
    peak memory; applied anyway in a process whose environment sets ``MALLOC_TRIM_THRESHOLD_``,
    as dask's nannies do, where glibc's dynamic mmap threshold is already off); ``batch_frames``
    computes the fisheye ground truth of that many consecutive samples in one batched call
    (`build_samples`; one dask task each): no faster on CPU, where the cameras and frames are
    looped anyway, but one wide `jax.vmap` program on an accelerator; it holds that many samples in
    memory (~0.5 GB each at full size)."""

    backward_flow: bool = False
    bev: bool = True
    motion_threshold_m: float = 0.5
    png_level: int = 1
    write_threads: int = 2
    tune_allocator: bool = False
    batch_frames: int = 1

    def __post_init__(self) -> None:
        from ..io._images import is_png_level

        if not is_png_level(self.png_level):
            raise DatasetError(f"BuildOptions: png_level must be an integer from 0 to 9, got {self.png_level!r}")
        if self.write_threads < 0:
            raise DatasetError(f"BuildOptions: write_threads must be >= 0, got {self.write_threads}")
        if not isinstance(self.batch_frames, int) or self.batch_frames < 1:
            raise DatasetError(f"BuildOptions: batch_frames must be an integer >= 1, got {self.batch_frames!r}")
        m = self.motion_threshold_m
        if isinstance(m, bool) or not isinstance(m, (int, float)) or not math.isfinite(m) or m < 0:
            raise DatasetError(f"BuildOptions: motion_threshold_m must be a finite number of metres >= 0, got {m!r}")

    def to_dict(self) -> dict[str, Any]:
        """The options that shape the output (``write_threads``, ``tune_allocator`` and, on CPU,
        ``batch_frames`` do not): recorded in ``dataset.json`` and in every completion marker."""
        return {"backward_flow": self.backward_flow, "bev": self.bev, "motion_threshold_m": self.motion_threshold_m,
                "png_level": self.png_level}


@dataclasses.dataclass
class BuildReport:
    """What a build did: the requested ``samples`` (ids), those ``built`` now, ``skipped``
    (complete from an earlier run), ``failed`` ``{sample: reason}``, ``replaced`` (samples another
    capture or other options had made, whose files ``rebuild=True`` removed first; those requested
    are in ``built``), the number of temporary files of killed runs removed, the wall time and the
    rate of built samples per second. ``ok`` is True when nothing failed."""

    out_dir: Path
    samples: list[str]
    built: list[str] = dataclasses.field(default_factory=list)
    skipped: list[str] = dataclasses.field(default_factory=list)
    failed: dict[str, str] = dataclasses.field(default_factory=dict)
    seconds: float = 0.0
    stale_removed: int = 0
    replaced: list[str] = dataclasses.field(default_factory=list)

    @property
    def ok(self) -> bool:
        """True when no sample failed."""
        return not self.failed

    @property
    def samples_per_second(self) -> float:
        """Built samples per second of wall time (0 when nothing was built)."""
        return len(self.built) / self.seconds if self.seconds > 0 and self.built else 0.0

    def summary(self) -> str:
        """One paragraph: counts, the rate of the samples built (or, when none was built, how many
        were skipped as already complete), and one line per failed sample with its reason."""
        skipped = f"{len(self.skipped)} skipped as already complete"
        if self.built:
            rate = f"{self.samples_per_second:.2f} samples/s" + (f"; {skipped}" if self.skipped else "")
        else:
            rate = f"none built; {skipped}" if self.skipped else "none built"
        lines = [f"{len(self.built)} built, {len(self.skipped)} already complete, {len(self.failed)} failed "
                 f"of {len(self.samples)} sample(s) in {self.seconds:.1f} s ({rate}) -> {self.out_dir}"]
        if self.replaced:
            lines.append(f"  {len(self.replaced)} sample(s) made from another capture or with other options "
                         f"were removed first (rebuild): {_span(self.replaced)}")
        lines += [f"  sample {s} failed: {r}" for s, r in sorted(self.failed.items())]
        return "\n".join(lines)


# ----------------------------------------------------------------------------- per-worker constants
_CACHE: dict[Any, Any] = {}
_CACHE_LOCK = threading.Lock()


def _file_key(path: Path) -> str:
    """Content hash of a file: constants depend on what a calibration says, not where it lives."""
    return hashlib.sha256(path.read_bytes()).hexdigest() if path.is_file() else ""


def _camera_constants(reader, camera: str):
    """(LUT, rays, event map) of a fisheye camera: built once per calibration per worker process."""
    import jax.numpy as jnp

    from ..io._labels import fisheye_constants

    key = ("fisheye", _file_key(reader.root / "calibration" / f"{camera}.json"),
           int(reader.meta.get("face_size", 0)), tuple(reader.faces))
    with _CACHE_LOCK:
        if key not in _CACHE:
            if int(reader.meta.get("face_size", 0)) <= 0:
                raise DatasetError(f"{reader.root / 'capture.json'}: field 'face_size' missing or not positive")
            _CACHE[key] = fisheye_constants(reader, camera, reader.rig()[camera].camera.astype(jnp.float32))
        return _CACHE[key]


def _bev_constants(reader):
    from ..io._bev import bev_sensor
    from ..io._labels import compiled_pixel_rays

    cam, _ = bev_sensor(reader)
    key = ("bev", _file_key(reader.root / "sensors.json"))
    with _CACHE_LOCK:
        if key not in _CACHE:
            _CACHE[key] = compiled_pixel_rays(cam)
        return _CACHE[key]


def clear_worker_cache() -> None:
    """Forget the per-calibration constants (LUTs, rays) this process has built."""
    with _CACHE_LOCK:
        _CACHE.clear()


# ------------------------------------------------------------------------------------ fingerprint
def capture_fingerprint(reader) -> dict[str, str]:
    """SHA-256 of the capture-level inputs of every sample of a capture (`jaxfish.io.CaptureReader`):
    ``capture.json`` (its content without the ``frames`` list, which grows as frames are written),
    ``sensors.json`` and ``calibration/{camera}.json`` of every listed camera, keyed by those
    names (an empty string for a missing file)."""
    meta = {k: v for k, v in reader.meta.items() if k != "frames"}
    parts = {"capture.json": hashlib.sha256(json.dumps(meta, sort_keys=True, separators=(",", ":")).encode()).hexdigest(),
             "sensors.json": _file_key(reader.root / "sensors.json")}
    for cam in sorted(reader.cameras):
        parts[f"calibration/{cam}.json"] = _file_key(reader.root / "calibration" / f"{cam}.json")
    return parts


def frame_fingerprint(capture_dir: str | os.PathLike, frame: int) -> str:
    """SHA-256 of a capture frame's folder (``frames/{frame:06d}``): the bytes of its JSON files
    (ego, actors, IMU, GNSS: they differ between any two renders or recordings) and the name and
    size of every other file (images, events, point clouds: stat only, so that resuming a large
    build stays cheap; a path that is not a regular file, by its name and kind, never read). Hidden
    files (and jaxfish's temporaries) are ignored. An image replaced by
    another of exactly the same size is not seen: rebuild such a sample (``rebuild=True``)."""
    from ..io._capture import frame_dir

    d = frame_dir(capture_dir, frame)
    entries = []
    for dirpath, dirs, files in os.walk(d):
        dirs[:] = [x for x in dirs if not x.startswith(".")]
        entries += [os.path.join(dirpath, n) for n in files if not n.startswith(".")]
    h = hashlib.sha256()
    for path in sorted(entries):
        rel = os.path.relpath(path, d).replace(os.sep, "/")
        try:
            st = os.stat(path)
        except OSError as e:  # a broken link, a link loop: the sample's read names it
            h.update(f"{rel}\0unreadable {e.errno}\0".encode())
            continue
        if not stat.S_ISREG(st.st_mode):  # never read a FIFO or a device (it would block): the read names it
            h.update(f"{rel}\0not a regular file {stat.S_IFMT(st.st_mode)}\0".encode())
        elif rel.endswith(".json"):
            data = Path(path).read_bytes()
            h.update(f"{rel}\0{len(data)}\0".encode())
            h.update(data)
        else:
            h.update(f"{rel}\0{st.st_size}\0".encode())
    return h.hexdigest()


def _frame_key(frame: int) -> str:
    return f"frames/{int(frame):06d}"


def _marker_differences(doc: Any, options: dict[str, Any], capture: dict[str, str], capture_dir: Path,
                        frames: set[int]) -> list[str]:
    """What differs between a completion marker and this build (empty when nothing does)."""
    opts, source = (doc.get("options"), doc.get("source")) if isinstance(doc, dict) else (None, None)
    if not isinstance(opts, dict) or not isinstance(source, dict):
        return ["its marker records no capture fingerprint and options (made by an older jaxfish)"]
    diffs = []
    for key in sorted(set(options) | set(opts)):
        there, here = opts.get(key, _NO_VALUE), options.get(key, _NO_VALUE)
        if there != here:
            shown = ["(none)" if v is _NO_VALUE else repr(v) for v in (there, here)]
            diffs.append(f"option {key} is {shown[0]} there, {shown[1]} in this build")
    for key in sorted(set(capture) | {k for k in source if not k.startswith("frames/")}):
        if source.get(key) != capture.get(key):
            diffs.append(f"the capture's {key} differs")
    frame = doc.get("frame")
    if isinstance(frame, int) and frame in frames and source.get(_frame_key(frame)) != frame_fingerprint(capture_dir, frame):
        diffs.append(f"the capture's {_frame_key(frame)} differs")
    return diffs


def _outdated_samples(out: Path, reader, options: BuildOptions) -> dict[str, list[str]]:
    """``{sample: differences}`` of every completion marker in ``out`` (of this `LAYOUT_VERSION`;
    others are rebuilt anyway) that another capture or other options made."""
    done = out / DONE_DIR
    if not done.is_dir():
        return {}
    wanted, capture, frames = options.to_dict(), capture_fingerprint(reader), set(reader.frames)
    outdated = {}
    for marker in sorted(done.glob("*.json")):
        try:
            doc = json.loads(marker.read_text())
        except (OSError, ValueError):  # unreadable: not complete, rebuilt when requested
            continue
        if not isinstance(doc, dict) or doc.get("layout_version") != LAYOUT_VERSION:
            continue
        diffs = _marker_differences(doc, wanted, capture, reader.root, frames)
        if diffs:
            outdated[marker.stem] = diffs
    return outdated


def _span(samples: Sequence[str]) -> str:
    samples = sorted(samples)
    return ", ".join(samples[:5]) + (f" and {len(samples) - 5} more" if len(samples) > 5 else "")


def _outdated_error(out: Path, outdated: dict[str, list[str]]) -> DatasetError:
    reasons: list[str] = []
    frames: list[str] = []
    for diffs in outdated.values():
        for d in diffs:
            if d.startswith("the capture's frames/"):
                frames.append(d.removeprefix("the capture's "))
            elif d not in reasons:
                reasons.append(d)
    if frames:
        reasons.append("the capture's " + _span(frames) + (" differ" if len(frames) > 1 else " differs"))
    return DatasetError(f"{out}: sample(s) {_span(list(outdated))} were made from another capture or with other "
                        f"options ({'; '.join(reasons)}); rebuild them (jaxfish build --rebuild, "
                        f"build_dataset(..., rebuild=True)) or build into another folder")


# ------------------------------------------------------------------- stopping thread workers
_STOP = threading.Event()  # set while an interrupted build stops the samples running in this process's threads
_RUNNING = [0]  # tasks running in this process
_RUNNING_CHANGED = threading.Condition()


class _Stopped(DatasetError):
    """The build that runs this sample was interrupted (raised between two files of a sample)."""


def _check_stop() -> None:
    if _STOP.is_set():
        raise _Stopped("build interrupted")


@contextlib.contextmanager
def _running():
    with _RUNNING_CHANGED:
        _RUNNING[0] += 1
    try:
        yield
    finally:
        with _RUNNING_CHANGED:
            _RUNNING[0] -= 1
            _RUNNING_CHANGED.notify_all()


# ------------------------------------------------------------------------------------- one sample
def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _vehicle_lines(ego: dict[str, Any], instant: str) -> str:
    def vec(name, v):
        return f"{name} " + " ".join(f"{float(x):.9g}" for x in v)

    if instant == "t":
        tr = ego["transform"]
        lines = [f"timestamp_s {float(ego['timestamp_s']):.9g}", vec("location_m", tr["location"]),
                 vec("rotation_deg", tr["rotation"]), vec("velocity_mps", ego["velocity"]),
                 vec("acceleration_mps2", ego["acceleration"]), vec("angular_velocity_degps", ego["angular_velocity"])]
    else:
        tr = ego["transform_prev"]
        lines = [f"timestamp_s {float(ego['timestamp_prev_s']):.9g}", vec("location_m", tr["location"]),
                 vec("rotation_deg", tr["rotation"])]
    header = ("# ego vehicle (CARLA world: x forward, y right, z up, metres; rotation pitch yaw roll, degrees; "
              "velocity / acceleration in the world frame, angular velocity deg/s)")
    return header + "\n" + "\n".join(lines) + "\n"


def _sample_extras(reader, frame: int, out: Path, sid: str) -> list[Path]:
    from ..io import atomic_write_bytes, atomic_write_text
    from ..io._capture import CaptureError

    ego = reader.ego(frame)
    try:
        t_text, p_text = _vehicle_lines(ego, "t"), _vehicle_lines(ego, "t-1")
    except (KeyError, TypeError, ValueError) as e:
        raise CaptureError(f"{reader.root}/frames/{frame:06d}/ego.json: malformed ({e!r})") from e
    paths = [atomic_write_text(out / "vehicle_data" / "rgb_images" / f"{sid}.txt", t_text),
             atomic_write_text(out / "vehicle_data" / "previous_images" / f"{sid}.txt", p_text)]
    lidar = {"points": np.ascontiguousarray(reader.lidar(frame), np.float32),
             "semantic_lidar": np.ascontiguousarray(reader.semantic_lidar(frame)),
             "radar": np.ascontiguousarray(reader.radar(frame)),
             "frame": "lidar sensor's local Unreal frame (x forward, y right, z up), metres; radar: m/s, rad, rad, m"}
    paths.append(atomic_write_bytes(out / "lidar_data" / f"{sid}.pkl", pickle.dumps(lidar, protocol=4)))
    return paths


def has_bev(reader) -> bool:
    """Whether a capture has a BEV top-view camera (``sensors.json`` field ``bev``); a missing or
    malformed ``sensors.json`` raises `jaxfish.io.CaptureError` (it never silently drops the BEV)."""
    return "bev" in reader.sensors()


_BACKWARD_FLOW_PATTERNS = ("optical_flow_backward/raw_data/{sample}_{camera}.flo",
                           "optical_flow_backward/color_coded/{sample}_{camera}.png")


def remove_sample_files(out_dir: str | os.PathLike, sample: str) -> int:
    """Delete every file of ``sample`` that the layout names (`LAYOUT`, backward flow included) and
    its completion marker; returns how many. A sample that fails leaves nothing half-written."""
    out = Path(out_dir)
    patterns = [e["pattern"] for e in LAYOUT] + list(_BACKWARD_FLOW_PATTERNS) + [f"{DONE_DIR}/{{sample}}.json"]
    n = 0
    for pattern in patterns:
        for p in out.glob(pattern.replace("{camera}", "*").replace("{sample}", sample)):
            p.unlink(missing_ok=True)
            n += 1
    return n


def build_sample(capture_dir: str | os.PathLike, out_dir: str | os.PathLike, frame: int,
                 options: BuildOptions | None = None) -> dict[str, Any]:
    """Build one sample (capture frame ``frame``) into ``out_dir`` and write its marker last.

    Pure in (capture, frame, options): the same inputs give the same bytes in any process.
    Returns ``{"sample", "frame", "layout_version", "options", "source", "files"}`` (the marker's
    content): ``options`` as `BuildOptions.to_dict`, ``source`` the capture's fingerprint
    (`capture_fingerprint` plus ``frames/{frame:06d}``: `frame_fingerprint`), ``files``
    ``{relative path: sha256}``.
    Raises on a missing or corrupt capture file (`jaxfish.io.CaptureError` naming the file)."""
    return build_samples(capture_dir, out_dir, [frame], options)[0]


def build_samples(capture_dir: str | os.PathLike, out_dir: str | os.PathLike, frames: Sequence[int],
                  options: BuildOptions | None = None) -> list[dict[str, Any]]:
    """`build_sample` for several frames whose fisheye ground truth is computed in one batched call
    (`jaxfish.io.capture_rig_ground_truth` with a sequence of frames: `rig_ground_truth` mapped
    over the frames and the cameras). On CPU the bytes are those of building each frame alone;
    with an accelerator (`jax.vmap` over the batch) values agree to float32 rounding. Each sample's
    files and marker are written as soon as its ground truth is done; the first error raises
    (samples already marked complete stay complete). Returns the markers, in order."""
    from ..io import CaptureReader, capture_rig_ground_truth

    options = options or BuildOptions()
    out = Path(out_dir)
    reader = CaptureReader(capture_dir, reuse_decoded=True)  # frames built in order decode their t-1 images once
    frames = [int(f) for f in frames]
    for frame in frames:
        if frame not in reader.frames:
            raise DatasetError(f"{reader.root / 'capture.json'}: frame {frame} is not listed in field 'frames'")
    cams = [c for c in FISHEYE_CAMERAS if c in reader.cameras] + [c for c in reader.cameras if c not in FISHEYE_CAMERAS]
    capture = capture_fingerprint(reader)  # before reading the frames: what the samples are made of
    sources = [{**capture, _frame_key(f): frame_fingerprint(reader.root, f)} for f in frames]
    rows = [[]] * len(frames)
    if cams:
        rows = capture_rig_ground_truth(reader, frames, cams, constants={c: _camera_constants(reader, c) for c in cams},
                                        backward_flow=options.backward_flow, motion_threshold_m=options.motion_threshold_m)
    return [_write_sample(reader, out, frame, cams, results, options, source)
            for frame, results, source in zip(frames, rows, sources, strict=True)]


def _write_sample(reader, out: Path, frame: int, cams: list[str], results: list[dict[str, Any]],
                  options: BuildOptions, source: dict[str, str]) -> dict[str, Any]:
    """Write one sample's files (the fisheye ``results`` computed, the BEV computed here while the
    fisheye files are written by the pool), then its marker; returns the marker."""
    from ..io import (
        capture_bev_ground_truth,
        write_bev_ground_truth,
        write_camera_ground_truth,
        write_sample_ground_truth,
    )
    from ..io._json import write_json

    sid = sample_id(frame)
    thr = options.motion_threshold_m
    png = int(options.png_level)
    written: list[tuple[Path, str]] = []  # (file, SHA-256), hashed by the thread that wrote it
    pool = concurrent.futures.ThreadPoolExecutor(options.write_threads) if options.write_threads > 0 else None
    pending: list[concurrent.futures.Future] = []

    def hashed(fn, *args, **kwargs) -> list[tuple[Path, str]]:
        _check_stop()
        return [(p, _sha256(p)) for p in fn(*args, **kwargs)]  # the bytes are still in the page cache

    def write(fn, *args, **kwargs):
        if pool is None:
            written.extend(hashed(fn, *args, **kwargs))
        else:
            pending.append(pool.submit(hashed, fn, *args, **kwargs))

    failed = True
    try:
        first = None
        for cam, res in zip(cams, results, strict=True):
            first = first or res
            write(write_camera_ground_truth, out, sid, cam, res, motion_threshold_m=thr, png_level=png)
            if options.backward_flow:
                write(_write_backward_flow, out, sid, cam, res, png)
        if options.bev and has_bev(reader):
            res = capture_bev_ground_truth(reader, frame, rays=_bev_constants(reader),
                                           backward_flow=options.backward_flow, motion_threshold_m=thr)
            first = first or res
            write(write_camera_ground_truth, out, sid, BEV_CAMERA, res, motion_threshold_m=thr, png_level=png)
            write(write_bev_ground_truth, out, sid, res, png_level=png)
            if options.backward_flow:
                write(_write_backward_flow, out, sid, BEV_CAMERA, res, png)
        if first is None:
            raise DatasetError(f"{reader.root / 'capture.json'}: no camera to build (field 'cameras' is empty)")
        write(write_sample_ground_truth, out, sid, first, motion_threshold_m=thr)
        write(_sample_extras, reader, frame, out, sid)
        for f in pending:
            written.extend(f.result())
        _check_stop()
        failed = False
    finally:
        if pool is not None:
            for f in pending:
                f.cancel()
            pool.shutdown(wait=True)
        if failed:  # the writers have stopped: remove what this sample wrote (the error propagates)
            remove_sample_files(out, sid)
    files = {p.relative_to(out).as_posix(): digest for p, digest in written}
    marker = {"sample": sid, "frame": frame, "layout_version": LAYOUT_VERSION, "options": options.to_dict(),
              "source": source, "files": dict(sorted(files.items()))}
    write_json(out / DONE_DIR / f"{sid}.json", marker, indent=1, error=DatasetError)
    return marker


def _write_backward_flow(root: Path, sid: str, camera: str, result: dict[str, Any], png_level: int) -> list[Path]:
    from ..io import write_flo, write_flow_color

    back = result["truth"].flow_backward
    fl, fv = np.asarray(back.flow), np.asarray(back.valid)
    stem = f"{sid}_{camera}"
    return [write_flo(root / "optical_flow_backward" / "raw_data" / f"{stem}.flo", np.where(fv[..., None], fl, 0.0)),
            write_flow_color(root / "optical_flow_backward" / "color_coded" / f"{stem}.png", fl, fv, png_level=png_level)]


def _prepare_process(options: BuildOptions) -> None:
    if options.tune_allocator or "MALLOC_TRIM_THRESHOLD_" in os.environ:
        # In the process that builds (a dask worker or the serial build's). A fixed trim threshold
        # in the environment (dask's nannies set one) has already turned glibc's dynamic mmap
        # threshold off, so every large buffer would be mapped afresh: tuning is then a clear win.
        tune_allocator()


def _reason(e: Exception) -> str:
    reason = f"{type(e).__name__}: {e}"
    if not isinstance(e, (JaxfishError, OSError, ValueError)):
        reason += " | " + traceback.format_exc(limit=3).strip().splitlines()[-1]
    return reason


def _sample_task(capture_dir: str, out_dir: str, frame: int, options: BuildOptions) -> tuple[str, str | None]:
    """Run `build_sample`, turning any error into a one-line reason (the dask / serial task)."""
    sid = sample_id(frame)
    try:
        _prepare_process(options)
        build_sample(capture_dir, out_dir, frame, options)
        return sid, None
    except Exception as e:  # a failing sample is reported, never stops the others
        return sid, _reason(e)


def _batch_task(capture_dir: str, out_dir: str, frames: list[int], options: BuildOptions) -> list[tuple[str, str | None]]:
    """`build_samples` of a batch of frames; when it fails, each frame not yet complete is built on
    its own, so that a failing sample is reported with its own reason and the others complete."""
    if len(frames) == 1:
        return [_sample_task(capture_dir, out_dir, frames[0], options)]
    try:
        _prepare_process(options)
        build_samples(capture_dir, out_dir, frames, options)
        return [(sample_id(f), None) for f in frames]
    except Exception:  # a failing sample is reported, never stops the others
        return [(sample_id(f), None) if is_complete(out_dir, sample_id(f)) else _sample_task(capture_dir, out_dir, f, options)
                for f in frames]


def _counted_batch_task(capture_dir: str, out_dir: str, frames: list[int],
                        options: BuildOptions) -> list[tuple[str, str | None]]:
    """`_batch_task` counted in ``_RUNNING`` (the serial and dask task): a thread worker of an
    interrupted build writes nothing more."""
    with _running():
        if _STOP.is_set():
            return [(sample_id(f), "build interrupted") for f in frames]
        return _batch_task(capture_dir, out_dir, frames, options)


def _batches(frames: list[int], size: int) -> list[list[int]]:
    return [frames[i:i + size] for i in range(0, len(frames), max(1, int(size)))]


# --------------------------------------------------------------------------------------- the build
def is_complete(out_dir: str | os.PathLike, sample: str) -> bool:
    """Whether ``sample``'s completion marker exists, was written for this `LAYOUT_VERSION` (a sample
    built for another layout is rebuilt when a build resumes), and every file it lists is present."""
    marker = Path(out_dir) / DONE_DIR / f"{sample}.json"
    if not marker.is_file():
        return False
    try:
        doc = json.loads(marker.read_text())
        files = doc["files"]
        if doc.get("layout_version") != LAYOUT_VERSION:
            return False
    except (json.JSONDecodeError, KeyError, TypeError, AttributeError):
        return False
    return all((Path(out_dir) / rel).is_file() for rel in files)


def remove_stale_temporaries(out_dir: str | os.PathLike) -> int:
    """Delete the temporary files jaxfish's atomic writes left in ``out_dir`` when a run was killed
    (``.jaxfish-{run}-{name}.{random}.part{suffix}``; no other file, whatever its name); returns how
    many. Only call it when no other build writes to ``out_dir`` (`build_dataset` holds the
    folder's lock)."""
    from ..io._folder import remove_temporaries

    return remove_temporaries(out_dir)


def _is_dataset_folder(out: Path) -> bool:
    """Whether ``out`` is a folder a jaxfish build started (``.done/``) or wrote (``dataset.json``)."""
    from ._manifest import DATASET_FORMAT

    if (out / DONE_DIR).is_dir():
        return True
    try:
        return json.loads((out / "dataset.json").read_text()).get("format") == DATASET_FORMAT
    except (OSError, ValueError, AttributeError):
        return False


def check_output_folder(out_dir: str | os.PathLike) -> Path:
    """Refuse (`DatasetError`) an output folder that jaxfish must not write into: a path that is not
    a folder, or a folder that holds files and is not a jaxfish dataset (`dataset.json` of format
    ``jaxfish-synwoodscape`` or a ``.done/`` folder). Returns the path."""
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise DatasetError(f"{out}: not a folder (the dataset output must be a folder)")
    if out.is_dir() and any(out.iterdir()) and not _is_dataset_folder(out):
        names = sorted(p.name for p in out.iterdir())
        raise DatasetError(f"{out}: not empty and not a jaxfish dataset (it holds {', '.join(names[:3])}"
                           f"{' ...' if len(names) > 3 else ''}; no dataset.json, no {DONE_DIR}/): build into a new "
                           f"or empty folder")
    return out


def build_dataset(
    capture_dir: str | os.PathLike,
    out_dir: str | os.PathLike,
    *,
    frames: Sequence[int] | None = None,
    options: BuildOptions | None = None,
    scheduler: str | None = None,
    workers: int | None = None,
    processes: bool = True,
    progress: Callable[[str, str | None], None] | None = None,
    rebuild: bool = False,
) -> BuildReport:
    """Build the dataset of a capture (``docs/dataset.md``).

    ``frames``: the capture frames to build (default all, in order); each becomes sample
    ``{frame:05d}``. ``out_dir`` must be new, empty or a jaxfish dataset (`check_output_folder`);
    the build locks it (a second build of the same folder meanwhile raises `DatasetError`) and
    first removes the temporary files of a killed run (only jaxfish's own). Every completion marker
    in the folder must record this capture's fingerprint and these options (``BuildOptions.to_dict``):
    otherwise the build raises `DatasetError` naming what differs, before writing anything, or with
    ``rebuild=True`` removes those samples' files first (`BuildReport.replaced`) and builds the
    requested ones again. Samples already complete are skipped. ``scheduler`` (a
    dask.distributed address) or ``workers`` (start a ``LocalCluster`` of that many workers,
    process workers unless ``processes=False``) run the samples in parallel; the output bytes are
    those of a serial run. ``progress(sample, error)`` is called after each sample (``error`` None
    on success). A failing sample (missing or corrupt capture file) is recorded in the report with
    its reason and does not stop the others. Finally writes ``dataset.json`` (listing the complete
    samples, the capture's fingerprint and the options), ``calibration_data`` and
    ``semantic_annotations/seg_annotation_info.json``.

    A ``KeyboardInterrupt`` while samples run stops the build: the workers of a local cluster end
    (process workers are killed, thread workers stop before their next file), the files of the
    samples cut off and the temporary files are deleted (on an external ``scheduler`` the pending
    tasks are cancelled and files are left to the resume), then `BuildInterrupted` is raised."""
    from ..io import CaptureReader

    options = options or BuildOptions()
    if workers is not None and (isinstance(workers, bool) or not isinstance(workers, int) or workers < 1):
        raise DatasetError(f"workers must be an integer >= 1, got {workers!r}")
    if frames is not None:
        bad = [f for f in frames if isinstance(f, bool) or not isinstance(f, (int, np.integer))]
        if bad:
            raise DatasetError(f"frames must be integer frame numbers, got {bad[0]!r}")
    start = time.perf_counter()
    reader = CaptureReader(capture_dir)  # a missing / malformed header stops the build here
    reader.rig()  # so do the calibrations and (for the BEV) sensors.json, before anything is written
    if options.bev and has_bev(reader):
        from ..io import bev_sensor

        bev_sensor(reader)  # its scale, size and mount
    out = check_output_folder(out_dir)
    (out / DONE_DIR).mkdir(parents=True, exist_ok=True)  # marks the folder as a jaxfish dataset from now on
    from ..io._folder import folder_lock

    with folder_lock(out, DatasetError, "build"):  # the driver's: dask workers write under it
        return _build_locked(reader, out, frames, options, scheduler, workers, processes, progress, rebuild, start)


def _build_locked(reader, out: Path, frames: Sequence[int] | None, options: BuildOptions, scheduler: str | None,
                  workers: int | None, processes: bool, progress: Callable[[str, str | None], None] | None,
                  rebuild: bool, start: float) -> BuildReport:
    available = reader.frames
    wanted = list(available) if frames is None else [int(f) for f in frames]
    missing = [f for f in wanted if f not in available]
    report = BuildReport(out_dir=out, samples=[sample_id(f) for f in wanted])
    report.stale_removed = remove_stale_temporaries(out)
    outdated = _outdated_samples(out, reader, options)
    if outdated and not rebuild:
        raise _outdated_error(out, outdated)
    for sid in sorted(outdated):
        remove_sample_files(out, sid)
        report.replaced.append(sid)
    tick = progress or (lambda _s, _e: None)
    todo = []
    for f in wanted:
        sid = sample_id(f)
        if f in missing:
            report.failed[sid] = f"{reader.root / 'capture.json'}: frame {f} is not in the capture (field 'frames')"
            tick(sid, report.failed[sid])
        elif is_complete(out, sid):
            report.skipped.append(sid)
            tick(sid, None)
        else:
            todo.append(f)

    def record(sid: str, err: str | None) -> None:
        if err is None:
            report.built.append(sid)
        else:
            report.failed[sid] = err
        tick(sid, err)

    try:
        if todo and (scheduler is not None or workers is not None):  # absolute paths: workers may run elsewhere
            _run_dask(str(reader.root.resolve()), str(out.resolve()), todo, options, scheduler, workers, processes,
                      record)
        else:
            for frames_ in _batches(todo, options.batch_frames):
                for result in _counted_batch_task(str(reader.root), str(out), frames_, options):
                    record(*result)
    except KeyboardInterrupt:  # every writer of this build has stopped (remote workers aside): clean up, report
        raise _interrupted(report, out, todo, scheduler is None, start) from None
    from ._manifest import write_dataset_files

    write_dataset_files(reader, out, options)
    report.built.sort()
    report.seconds = time.perf_counter() - start
    return report


def _interrupted(report: BuildReport, out: Path, todo: list[int], clean: bool, start: float) -> BuildInterrupted:
    """After an interrupt, once nothing of this build writes any more (``clean``): remove the files
    of the samples it cut off (those not complete) and the temporary files; complete samples stay."""
    if clean:
        for f in todo:
            if not is_complete(out, sample_id(f)):
                remove_sample_files(out, sample_id(f))
        remove_stale_temporaries(out)
    report.built.sort()
    report.seconds = time.perf_counter() - start
    return BuildInterrupted(report, [s for s in report.samples if is_complete(out, s)])


def _run_dask(capture_dir: str, out_dir: str, frames: list[int], options: BuildOptions, scheduler: str | None,
              workers: int | None, processes: bool, record: Callable[[str, str | None], None]) -> None:
    """Run the samples on a cluster. On a ``KeyboardInterrupt`` the workers of a local cluster stop
    before it propagates: process workers are killed (their running samples are cut off), thread
    workers stop before their next file; on an external ``scheduler`` the pending tasks are
    cancelled and the running ones end on their own."""
    try:
        from distributed import Client, as_completed
    except ImportError as e:  # pragma: no cover - depends on the environment
        raise DatasetError("dask.distributed is not installed: pip install 'jaxfish[distributed]'") from e
    cluster = client = quiet = None
    futures: list = []
    try:
        if scheduler is not None:
            try:
                client = Client(scheduler)
            except (ValueError, OSError, TimeoutError) as e:  # a malformed or unreachable address
                raise DatasetError(f"scheduler {scheduler!r}: cannot connect ({type(e).__name__}: {e})") from None
        else:
            cluster = local_cluster(int(workers or 1), processes=processes)
            client = Client(cluster)
            if processes:
                share_cores(client)
        batches = {f"jaxfish-samples-{sample_id(b[0])}-{sample_id(b[-1])}": b for b in _batches(frames, options.batch_frames)}
        futures = [client.submit(_counted_batch_task, capture_dir, out_dir, b, options, key=key, pure=False)
                   for key, b in batches.items()]
        for fut in as_completed(futures):
            try:
                results = fut.result()
            except Exception as e:  # the worker itself died
                results = [(sample_id(f), f"worker failure: {type(e).__name__}: {e}") for f in batches[str(fut.key)]]
            for sid, err in results:
                record(sid, err)
    except KeyboardInterrupt:
        quiet = _quiet_dask_logs()  # the workers' ends are expected: no warnings, no tracebacks
        _stop_workers(client, cluster, futures, processes)
        raise
    finally:
        try:
            for closable in (client, cluster):
                if closable is not None:  # after an interrupt, an error closing would only hide it
                    with contextlib.suppress(*(() if quiet is None else (Exception,))):
                        closable.close()
        finally:
            _STOP.clear()
            if quiet is not None:
                quiet()


def _quiet_dask_logs() -> Callable[[], None]:
    """Silence dask.distributed's loggers; returns the function that restores them."""
    import logging

    names = ["distributed"] + [n for n in list(logging.root.manager.loggerDict) if n.startswith("distributed.")]
    loggers = [logging.getLogger(n) for n in names]
    levels = [lg.level for lg in loggers]
    for lg in loggers:
        if lg.name == "distributed" or lg.level != logging.NOTSET:
            lg.setLevel(logging.CRITICAL + 1)

    def restore() -> None:
        for lg, level in zip(loggers, levels, strict=True):
            lg.setLevel(level)

    return restore


def _stop_workers(client, cluster, futures: list, processes: bool) -> None:
    """Stop the workers of an interrupted build: when this returns, no sample of it is written any
    more on this machine (local process workers have ended, local thread workers left their tasks)."""
    if cluster is None:  # an external cluster: its workers are not ours to end
        if client is not None and futures:
            with contextlib.suppress(Exception):
                client.cancel(futures)
        return
    if processes:
        _end_local_workers(cluster)
        return
    _STOP.set()  # cleared once the cluster is closed: a task starting before that writes nothing
    with _RUNNING_CHANGED:
        _RUNNING_CHANGED.wait_for(lambda: _RUNNING[0] == 0)


def _end_local_workers(cluster) -> list[int]:
    """Kill the worker processes of a local process cluster (`local_cluster`) now, without letting
    their nannies restart them, and return once they have ended (their process ids). A sample they
    were writing is left cut off."""
    import psutil

    procs = []
    for nanny in list(getattr(cluster, "workers", {}).values()):
        with contextlib.suppress(Exception):
            nanny.close_gracefully("jaxfish build interrupted")  # a nanny restarts a worker that dies, else
        pid = getattr(nanny, "pid", None)
        if pid:
            with contextlib.suppress(psutil.Error):
                procs.append(psutil.Process(pid))
    for proc in procs:
        with contextlib.suppress(psutil.Error):
            proc.kill()
    for proc in procs:  # ended = gone or a zombie (its nanny reaps it; reaping it here would confuse dask)
        while True:
            try:
                if proc.status() == psutil.STATUS_ZOMBIE:
                    break
            except psutil.NoSuchProcess:
                break
            time.sleep(0.01)
    return [p.pid for p in procs]


def local_cluster(workers: int, *, processes: bool = True):
    """A ``distributed.LocalCluster`` of ``workers`` single-threaded workers (processes unless
    ``processes=False``) as `build_dataset` starts it for ``workers=N``.

    Dask's nannies export ``MALLOC_TRIM_THRESHOLD_=65536`` to their workers, which turns off
    glibc's dynamic mmap threshold: every image-sized buffer then becomes a fresh, page-faulting
    mapping, and a sample took 1.75x the CPU time of a serial build. These workers keep glibc's
    defaults. No dashboard; the scheduler's HTTP routes (health, metrics) take a free port, not
    dask's 8787 (another cluster on this machine would make dask warn on stderr).

    Process workers end with the process that calls this (its nannies run in it), however it ends,
    ``kill -9`` included, and ignore SIGINT and SIGTERM (`jaxfish.dataset._runtime.dask_setup`, a
    worker preload added to ``distributed.worker.preload``): stopping them is that process's job."""
    try:
        import dask
        from distributed import LocalCluster
    except ImportError as e:  # pragma: no cover - depends on the environment
        raise DatasetError("dask.distributed is not installed: pip install 'jaxfish[distributed]'") from e
    if workers < 1:
        raise DatasetError(f"workers must be at least 1, got {workers}")
    environ = {k: v for k, v in dask.config.get("distributed.nanny.pre-spawn-environ", {}).items()
               if k != "MALLOC_TRIM_THRESHOLD_"}
    kwargs: dict[str, Any] = {}
    if processes:  # the nannies run in this process: their workers end with it (`_runtime.dask_setup`)
        kwargs["env"] = {BUILD_PID_ENV: str(os.getpid())}  # set in the worker only, over any inherited value
        preload = dask.config.get("distributed.worker.preload", None) or []
        kwargs["preload"] = ([preload] if isinstance(preload, str) else list(preload)) + ["jaxfish.dataset._runtime"]
    with dask.config.set({"distributed.nanny.pre-spawn-environ": environ}):
        return LocalCluster(n_workers=workers, threads_per_worker=1, processes=processes, dashboard_address=None,
                           scheduler_kwargs={"dashboard_address": "127.0.0.1:0"}, **kwargs)
