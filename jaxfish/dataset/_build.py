"""Capture directory in, SynWoodScape-style dataset out: serial, resumable, or on a Dask cluster.

Each sample is a pure function of (capture, frame, options): `build_sample` reads the capture's
frame, computes every camera's ground truth and writes the sample's files atomically, then its
completion marker ``.done/{sample}.json`` (the capture's fingerprint, the options, the files and
their BLAKE3 digests) last. `build_dataset` writes only into a new, empty or jaxfish dataset folder, which
it locks; it removes the temporary files a killed run left behind, refuses a folder whose samples
another capture or other options made (unless asked to rebuild them), skips complete samples, runs
the remaining samples serially or on a dask.distributed cluster (the bytes are the same), reports
each failing sample with its reason, and finally writes the dataset-level files (``dataset.json``,
``calibration_data``, ``seg_annotation_info.json``). A shard build (``shard=(I, N)``) builds its
1/N of the samples under its shard's lock and writes its shard record instead; `merge_shards`
(``_merge.py``) ends the folder as a whole build does (`finish_dataset`).
"""

from __future__ import annotations

import collections
import concurrent.futures
import contextlib
import hashlib
import json
import os
import pickle
import queue
import threading
import time
import traceback
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, NamedTuple

import blake3
import numpy as np

from .._errors import JaxfishError
from .._sequences import sequence_slots, set_sequence_slots
from ..pipeline import EmptyCameraError, Frame, RigConstants, SampleTruth, SensorRecords, rig_constants, sample_truths
from ._fingerprint import frame_fingerprint as frame_fingerprint
from ._layout import LAYOUT, LAYOUT_VERSION, sample_id
from ._options import DONE_DIR as DONE_DIR
from ._options import BuildInterrupted as BuildInterrupted
from ._options import BuildOptions as BuildOptions
from ._options import BuildReport as BuildReport
from ._options import DatasetError as DatasetError
from ._options import sample_span
from ._runtime import (
    BUILD_PID_ENV,
    CORE_SHARES_ENV,
    accelerator_sharing_env,
    allocator_env,
    core_shares,
    encode_shares,
    openexr_in_calling_thread,
    share_accelerator,
    tune_allocator,
    use_compile_cache,
)
from ._shards import SHARD_FORMAT, SHARD_RULE, SHARDS_DIR, Shard, as_shard, remove_shard_records, source_origin
from ._sink import LayoutSink, forget_last_rgb, write_sensor_files, written_part
from ._sources import CaptureSource, FrameSource, as_source

_NO_VALUE = object()


# ----------------------------------------------------------------------------- per-process constants
_CACHE: dict[Any, Any] = {}
_CACHE_LOCK = threading.Lock()


def rig_constants_of(source) -> RigConstants:
    """The `jaxfish.pipeline.RigConstants` of a source's rig (LUTs, rays, event maps, the BEV's),
    built once per process and content of its calibrations (`FrameSource.constants_key`)."""
    key = source.constants_key()
    with _CACHE_LOCK:
        if key not in _CACHE:
            if source.face_size <= 0:
                raise DatasetError(f"{source.where}: field 'face_size' missing or not positive")
            bev = source.bev_sensor() if source.has_bev() else None
            try:
                _CACHE[key] = rig_constants(source.rig(), faces=source.faces, face_size=source.face_size, bev=bev)
            except EmptyCameraError as e:
                from ..io import CaptureError

                where = source.calibration_path(e.camera) if hasattr(source, "calibration_path") else source.where
                raise CaptureError(f"{where}: field 'intrinsic': {e}") from None
        return _CACHE[key]


def clear_worker_cache() -> None:
    """Forget the per-calibration constants (LUTs, rays) this process has built, the source its
    dask tasks share (`_kept_source`), and the images, labels and RGB PNGs kept for the next
    sample of a sequence (`jaxfish.pipeline.forget_last_images`, the sink's)."""
    from ..pipeline import forget_last_images

    with _CACHE_LOCK:
        _CACHE.clear()
        _KEPT.clear()
    forget_last_images()
    forget_last_rgb()


_KEPT: list[tuple[bytes, Any]] = []


def _kept_source(source):
    """This process's instance of ``source``: the first task of a worker keeps the source it was
    handed, and later tasks handed an equal one (the same pickled state) use the kept instance.
    Every dask task unpickles its own copy of the source, which would start without the decodes and
    renders a source keeps of its last frame (`CaptureSource` ``reuse_decoded``, `EmbeddedSource`);
    with the kept instance, a worker's consecutive samples reuse them as a serial build's do.
    Only the last source is kept."""
    try:
        key = pickle.dumps(source)
    except Exception:  # noqa: BLE001 - a source that does not pickle is used as it is
        return source
    with _CACHE_LOCK:
        if not _KEPT or _KEPT[0][0] != key:
            _KEPT[:] = [(key, source)]
        return _KEPT[0][1]


# ------------------------------------------------------------------------------------ fingerprint
def capture_fingerprint(reader) -> dict[str, str]:
    """SHA-256 of the capture-level inputs of every sample of a capture (a `jaxfish.io.CaptureReader`
    or a `CaptureSource`): ``capture.json`` (without its ``frames`` list), ``sensors.json`` and
    ``calibration/{camera}.json`` of every listed camera, keyed by those names."""
    return (reader if isinstance(reader, CaptureSource) else CaptureSource(reader.root)).fingerprint()


def _frame_key(frame: int) -> str:
    return f"frames/{int(frame):06d}"


def marker_differences(doc: Any, options: dict[str, Any], capture: dict[str, str], source,
                       frames: set[int]) -> list[str]:
    """What differs between a completion marker and this build (empty when nothing does)."""
    opts, recorded = (doc.get("options"), doc.get("source")) if isinstance(doc, dict) else (None, None)
    if not isinstance(opts, dict) or not isinstance(recorded, dict):
        return ["its marker records no capture fingerprint and options (made by an older jaxfish)"]
    diffs = []
    for key in sorted(set(options) | set(opts)):
        there, here = opts.get(key, _NO_VALUE), options.get(key, _NO_VALUE)
        if there != here:
            shown = ["(none)" if v is _NO_VALUE else repr(v) for v in (there, here)]
            diffs.append(f"option {key} is {shown[0]} there, {shown[1]} in this build")
    for key in sorted(set(capture) | {k for k in recorded if not k.startswith("frames/")}):
        if recorded.get(key) != capture.get(key):
            diffs.append(f"the capture's {key} differs")
    frame = doc.get("frame")
    if isinstance(frame, int) and frame in frames and recorded.get(_frame_key(frame)) != source.frame_fingerprint(frame):
        diffs.append(f"the capture's {_frame_key(frame)} differs")
    return diffs


def _outdated_samples(out: Path, source, options: BuildOptions) -> dict[str, list[str]]:
    """``{sample: differences}`` of every completion marker in ``out`` (of this `LAYOUT_VERSION`;
    others are rebuilt anyway) that another source or other options made."""
    done = out / DONE_DIR
    if not done.is_dir():
        return {}
    wanted, capture, frames = options.to_dict(), source.fingerprint(), set(source.frames)
    outdated = {}
    for marker in sorted(done.glob("*.json")):
        try:
            doc = json.loads(marker.read_text())
        except (OSError, ValueError):  # unreadable: not complete, rebuilt when requested
            continue
        if not isinstance(doc, dict) or doc.get("layout_version") != LAYOUT_VERSION:
            continue
        diffs = marker_differences(doc, wanted, capture, source, frames)
        if diffs:
            outdated[marker.stem] = diffs
    return outdated


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
        reasons.append("the capture's " + sample_span(frames) + (" differ" if len(frames) > 1 else " differs"))
    return DatasetError(f"{out}: sample(s) {sample_span(list(outdated))} were made from another capture or with other "
                        f"options ({'; '.join(reasons)}); rebuild them (jaxfish build --rebuild, "
                        f"build_dataset(..., rebuild=True)) or build into another folder")


# ------------------------------------------------------------------- stopping thread workers
_STOP = threading.Event()  # set while an interrupted build stops the samples running in this process's threads


class _Stopped(DatasetError):
    """The build that runs this sample was interrupted (raised between two files of a sample)."""


def _check_stop() -> None:
    if _STOP.is_set():
        raise _Stopped("build interrupted")



# ------------------------------------------------------------------------------------- one sample
MARKER_DIGEST = "blake3"
"""The digest a completion marker records for each of its sample's files (its field ``digest``;
a marker without that field records SHA-256, `MARKER_DIGESTS`)."""
MARKER_DIGESTS: dict[str, Callable[[], Any]] = {"blake3": blake3.blake3, "sha256": hashlib.sha256}
"""The digests a marker may record, by name: hashlib-style constructors."""


def file_digest(path: Path, algorithm: str = MARKER_DIGEST) -> str:
    """Hex digest of a file's bytes by ``algorithm`` (a key of `MARKER_DIGESTS`; read through one
    small reused buffer, not into one large new object)."""
    with open(path, "rb") as fh:
        return hashlib.file_digest(fh, MARKER_DIGESTS[algorithm]).hexdigest()


class _Extras(NamedTuple):
    """What `_sample_extras` writes: the sample's other sensors and the file their ego record came from."""

    sensors: SensorRecords
    where: str


def _sample_extras(extras: _Extras, frame: int, out: Path, sid: str) -> list[Path]:
    """Write a sample's sensor files (`jaxfish.dataset._sink.write_sensor_files`): the last write
    of every sample."""
    return write_sensor_files(out, sid, extras.sensors, extras.where)


def has_bev(reader) -> bool:
    """Whether a capture has a BEV top-view camera (``sensors.json`` field ``bev``); a missing or
    malformed ``sensors.json`` raises `jaxfish.io.CaptureError` (it never silently drops the BEV)."""
    return "bev" in reader.sensors() if hasattr(reader, "sensors") else reader.has_bev()


_BACKWARD_FLOW_PATTERNS = ("optical_flow_backward/raw_data/{sample}_{camera}.flo",
                           "optical_flow_backward/color_coded/{sample}_{camera}.png",
                           "optical_flow_backward/valid_mask/{sample}_{camera}.png",
                           "optical_flow_backward/occlusion_mask/{sample}_{camera}.png")


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


def build_sample(source, out_dir: str | os.PathLike, frame: int, options: BuildOptions | None = None) -> dict[str, Any]:
    """Build one sample (frame ``frame`` of ``source``: a `FrameSource` or a capture directory)
    into ``out_dir`` and write its marker last.

    Pure in (source, frame, options): the same inputs give the same bytes in any process.
    Returns ``{"sample", "frame", "layout_version", "options", "source", "digest", "files"}`` (the
    marker's content): ``options`` as `BuildOptions.to_dict`, ``source`` the source's fingerprint
    plus ``frames/{frame:06d}`` (`FrameSource.frame_fingerprint`), ``digest`` `MARKER_DIGEST`,
    ``files`` ``{relative path: hex digest}``.
    Raises on a missing or corrupt capture file (`jaxfish.io.CaptureError` naming the file)."""
    return build_samples(source, out_dir, [frame], options)[0]


def build_samples(source, out_dir: str | os.PathLike, frames: Sequence[int],
                  options: BuildOptions | None = None) -> list[dict[str, Any]]:
    """`build_sample` for several frames whose ground truth is computed in one batched call
    (`jaxfish.pipeline.sample_truths`: `rig_ground_truth` mapped over the frames and the cameras).
    On CPU the bytes are those of building each frame alone; with an accelerator (`jax.vmap` over
    the batch) values agree to float32 rounding. Each sample's files and marker are written once
    its ground truth is done; the first error raises (samples already marked complete stay
    complete). Returns the markers, in order."""
    options = options or BuildOptions()
    source = as_source(source)
    out = Path(out_dir)
    frames = [int(f) for f in frames]
    available = set(source.frames)
    for frame in frames:
        if frame not in available:
            raise DatasetError(f"{source.where}: frame {frame} is not listed in field 'frames'")
    capture = source.fingerprint()  # before reading the frames: what the samples are made of
    records = [{**capture, _frame_key(f): source.frame_fingerprint(f)} for f in frames]
    if not source.cameras and not (options.bev and source.has_bev()):
        raise DatasetError(f"{source.where}: no camera to build (field 'cameras' is empty)")
    gt_options = options.ground_truth()
    constants, loaded = _constants_and_frames(source, frames, options.bev)
    truths = [written_part(t) for t in sample_truths(loaded, constants, gt_options)]
    del loaded  # the frames' cube faces at t-1 and face events are not written: freed before the files are
    return [_write_sample(source, out, truth, options, record) for truth, record in zip(truths, records, strict=True)]


def _constants_and_frames(source, frames: list[int], bev: bool) -> tuple[RigConstants, list[Frame]]:
    """The rig constants and the decoded ``frames``. Constants not yet built in this process are
    built on a second thread while the frames are read (compiling is mostly one core's work, a read
    decodes or renders on the others); an error of the constants is raised before one of the reads,
    as if they were built first."""
    if source.constants_key() in _CACHE:
        return rig_constants_of(source), [source.read(f, bev=bev) for f in frames]
    pool = concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="jaxfish-constants")
    try:
        pending = pool.submit(rig_constants_of, source)
        try:
            loaded = [source.read(f, bev=bev) for f in frames]
        except Exception:
            pending.result()  # the constants' own error first
            raise
        return pending.result(), loaded
    finally:  # an interrupt does not wait for the constants
        pool.shutdown(wait=False)


def _write_sample(source, out: Path, truth: SampleTruth, options: BuildOptions, record: dict[str, str]) -> dict[str, Any]:
    """Write one sample's files (`LayoutSink`, in a pool of ``write_threads`` threads), then its
    marker; returns the marker. A sample that fails leaves no file."""
    from ..io._json import write_json

    frame = truth.index
    sid = sample_id(frame)
    sink = LayoutSink(out, png_level=options.png_level, motion_threshold_m=options.motion_threshold_m,
                      backward_flow=options.backward_flow)
    written: list[tuple[Path, str]] = []  # (file, digest), hashed by the thread that wrote it
    pool = concurrent.futures.ThreadPoolExecutor(options.write_threads) if options.write_threads > 0 else None
    pending: list[concurrent.futures.Future] = []

    def hashed(fn, *args) -> list[tuple[Path, str]]:
        _check_stop()
        return [(p, file_digest(p)) for p in fn(*args)]  # the bytes are still in the page cache

    jobs = sink.jobs(sid, truth)[:-1]  # the sensor files go through the `_sample_extras` hook
    extras = _Extras(truth.sensors, f"{source.where}: frame {frame} ego record")
    if isinstance(source, CaptureSource):
        extras = _Extras(truth.sensors, f"{source.root}/frames/{frame:06d}/ego.json")
    calls = [(job,) for job in jobs] + [(_sample_extras, extras, frame, out, sid)]
    failed = True
    try:
        for call in calls:
            if pool is None:
                written.extend(hashed(*call))
            else:
                pending.append(pool.submit(hashed, *call))
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
              "source": record, "digest": MARKER_DIGEST, "files": dict(sorted(files.items()))}
    write_json(out / DONE_DIR / f"{sid}.json", marker, indent=1, error=DatasetError)
    return marker


def _prepare_process(options: BuildOptions) -> None:
    use_compile_cache(options.compile_cache)  # idempotent: configured before this process's first program
    openexr_in_calling_thread()  # the builder's own threads write and read the files
    _tune_allocator(options)


def _tune_allocator(options: BuildOptions) -> None:
    """`tune_allocator` unless ``options`` say not to (a nanny's trim threshold overrides them)."""
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


def _sample_task(source, out_dir: str, frame: int, options: BuildOptions) -> tuple[str, str | None]:
    """Run `build_sample`, turning any error into a one-line reason (the dask / serial task)."""
    sid = sample_id(frame)
    try:
        _prepare_process(options)
        build_sample(source, out_dir, frame, options)
        return sid, None
    except Exception as e:  # a failing sample is reported, never stops the others
        return sid, _reason(e)


def _batch_task(source, out_dir: str, frames: list[int], options: BuildOptions) -> list[tuple[str, str | None]]:
    """`build_samples` of a batch of frames; when it fails, each frame not yet complete is built on
    its own, so that a failing sample is reported with its own reason and the others complete."""
    if len(frames) == 1:
        return [_sample_task(source, out_dir, frames[0], options)]
    try:
        _prepare_process(options)
        build_samples(source, out_dir, frames, options)
        return [(sample_id(f), None) for f in frames]
    except Exception:  # a failing sample is reported, never stops the others
        return [(sample_id(f), None) if is_complete(out_dir, sample_id(f)) else _sample_task(source, out_dir, f, options)
                for f in frames]


def _worker_batch_task(source, out_dir: str, frames: list[int],
                       options: BuildOptions) -> list[tuple[str, str | None]]:
    """`_counted_batch_task` on the worker's kept instance of ``source`` (`_kept_source`): the dask
    task. A worker of several threads keeps a sequence for each (`set_sequence_slots`)."""
    with contextlib.suppress(Exception):  # outside a worker: the process's setting
        from distributed import get_worker

        threads = int(get_worker().state.nthreads)
        if threads > sequence_slots():
            set_sequence_slots(threads)
    return _counted_batch_task(_kept_source(source), out_dir, frames, options)


def _counted_batch_task(source, out_dir: str, frames: list[int],
                        options: BuildOptions) -> list[tuple[str, str | None]]:
    """`_batch_task`, unless this process's build was interrupted (`_STOP`): a thread worker of an
    interrupted build starts nothing more (the serial, thread and dask task)."""
    if _STOP.is_set():
        return [(sample_id(f), "build interrupted") for f in frames]
    return _batch_task(source, out_dir, frames, options)


def _batches(frames: list[int], size: int) -> list[list[int]]:
    return [frames[i:i + size] for i in range(0, len(frames), max(1, int(size)))]


# --------------------------------------------------------------------------------------- the build
def is_complete(out_dir: str | os.PathLike, sample: str) -> bool:
    """Whether ``sample``'s completion marker exists, was written for this `LAYOUT_VERSION` (a sample
    built for another layout is rebuilt when a build resumes), and every file it lists is present."""
    doc = read_marker(Path(out_dir) / DONE_DIR / f"{sample}.json")
    return doc is not None and marker_is_complete(out_dir, doc)


def read_marker(marker: Path) -> Any:
    """The parsed JSON of a completion marker file, or None when it is missing, not a regular file
    (a FIFO or a device, whose read would block or never end), unreadable, not UTF-8 or not JSON."""
    if not marker.is_file():
        return None
    try:
        return json.loads(marker.read_text())
    except (OSError, ValueError):
        return None


def marker_is_complete(out_dir: str | os.PathLike, doc: Any) -> bool:
    """`is_complete` of a completion marker already parsed (``doc``, the JSON value of its file)."""
    try:
        files = doc["files"]
        if doc.get("layout_version") != LAYOUT_VERSION:
            return False
    except (KeyError, TypeError, AttributeError):
        return False
    return all((Path(out_dir) / rel).is_file() for rel in files)


def remove_stale_temporaries(out_dir: str | os.PathLike, *, owned: Callable[[Path], bool] | None = None) -> int:
    """Delete the temporary files jaxfish's atomic writes left in ``out_dir`` when a run was killed
    (``.jaxfish-{run}-{name}.{random}.part{suffix}``; no other file, whatever its name); returns how
    many. Only call it when no other build writes to ``out_dir`` (`build_dataset` holds the
    folder's lock). ``owned``: only those whose destination (``folder / stem`` relative to
    ``out_dir``) it accepts (a shard build's own, `jaxfish.io._folder.remove_temporaries`)."""
    from ..io._folder import remove_temporaries

    return remove_temporaries(out_dir, owned=owned)


def finish_dataset(source, out_dir: str | os.PathLike, options: BuildOptions) -> None:
    """The end of a whole build, and of `merge_shards`: write the dataset-level files
    (`write_dataset_files`: ``dataset.json`` listing every complete sample, ``calibration_data``,
    ``seg_annotation_info.json``) and remove the shard records (``.shards/``), which the
    dataset-level files supersede. Call it holding the folder's exclusive lock."""
    from ._manifest import write_dataset_files

    write_dataset_files(source, out_dir, options)
    remove_shard_records(out_dir)


def write_shard_record(source, out_dir: str | os.PathLike, options: BuildOptions, shard: Shard,
                       requested: Sequence[int], samples: Sequence[str]) -> Path:
    """Write shard ``shard``'s record ``.shards/{I}-of-{N}.json`` (atomically; the last write of a
    shard build whose samples are all complete): the rule, the ``requested`` frames' sample ids,
    its own ``samples``, the layout version, ``options`` (`BuildOptions.to_dict`), the source's
    fingerprint and ``origin`` (where `merge_shards` finds the source again)."""
    from ..io._json import write_json

    record = {"format": SHARD_FORMAT, "kind": "dataset", "shard": [shard.index, shard.count], "rule": SHARD_RULE,
              "requested": [sample_id(f) for f in sorted(set(requested))], "samples": list(samples),
              "layout_version": LAYOUT_VERSION, "options": options.to_dict(), "source": source.fingerprint(),
              "origin": source_origin(source)}
    path = shard.record_path(out_dir)
    write_json(path, record, indent=1, error=DatasetError)
    return path


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
    source: FrameSource | str | os.PathLike,
    out_dir: str | os.PathLike,
    *,
    frames: Sequence[int] | None = None,
    options: BuildOptions | None = None,
    scheduler: str | None = None,
    workers: int | None = None,
    processes: bool | None = None,
    progress: Callable[[str, str | None], None] | None = None,
    rebuild: bool = False,
    shard: Shard | tuple[int, int] | None = None,
) -> BuildReport:
    """Build the dataset of a source of frames (``docs/dataset.md``): a capture directory (its
    path or a `CaptureSource`), the embedded scene in memory (`EmbeddedSource`) or any other
    `FrameSource`. Each frame flows source -> `jaxfish.pipeline.sample_truth` -> `LayoutSink`.

    ``frames``: the source's frames to build (default all, in order); each becomes sample
    ``{frame:05d}``. ``out_dir`` must be new, empty or a jaxfish dataset (`check_output_folder`);
    the build locks it (a second build of the same folder meanwhile raises `DatasetError`) and
    first removes the temporary files of a killed run (only jaxfish's own). Every completion marker
    in the folder must record this capture's fingerprint and these options (``BuildOptions.to_dict``):
    otherwise the build raises `DatasetError` naming what differs, before writing anything, or with
    ``rebuild=True`` removes those samples' files first (`BuildReport.replaced`) and builds the
    requested ones again. Samples already complete are skipped. ``scheduler`` (a
    dask.distributed address) or ``workers`` (that many local workers: threads of this process
    with ``processes=False``, a dask ``LocalCluster`` of process workers with ``processes=True``;
    by default threads up to `THREAD_WORKERS_MAX` workers, processes beyond) run the samples in
    parallel; the output bytes are those of a serial run. Process workers and this process share a GPU: they allocate its memory
    as they need it (`jaxfish.dataset._runtime.share_accelerator`, unless the environment sets
    ``XLA_PYTHON_CLIENT_PREALLOCATE``; in this process only if JAX has not started before the
    call). ``progress(sample, error)`` is called after each sample (``error`` None
    on success). A failing sample (missing or corrupt capture file) is recorded in the report with
    its reason and does not stop the others. Finally writes ``dataset.json`` (listing the complete
    samples, the capture's fingerprint and the options), ``calibration_data`` and
    ``semantic_annotations/seg_annotation_info.json``.

    A ``KeyboardInterrupt`` while samples run stops the build: local workers end (process workers
    are killed, thread workers stop before their next file), the files of the
    samples cut off and the temporary files are deleted (on an external ``scheduler`` the pending
    tasks are cancelled and files are left to the resume), then `BuildInterrupted` is raised.

    ``shard=(I, N)`` (a `Shard`) builds only shard I of N of the requested frames (the frames,
    sorted, numbered k = 0, 1, ...: frame k goes to shard k mod N), so that N builds, on as many
    machines sharing ``out_dir``, build every sample once. A shard build locks only its shard (a
    build of the same shard, of the whole folder or of shards of another N meanwhile raises
    `DatasetError`), removes only its own samples' temporary files, checks (and with ``rebuild``
    removes) only its own samples, and instead of the dataset-level files writes its shard record
    ``.shards/{I}-of-{N}.json`` last, when all its samples are complete; `merge_shards`
    (``jaxfish merge``) then writes them once every shard's record is there."""
    options = options or BuildOptions()
    shard = as_shard(shard)
    if workers is not None and (isinstance(workers, bool) or not isinstance(workers, int) or workers < 1):
        raise DatasetError(f"workers must be an integer >= 1, got {workers!r}")
    if frames is not None:
        bad = [f for f in frames if isinstance(f, bool) or not isinstance(f, (int, np.integer))]
        if bad:
            raise DatasetError(f"frames must be integer frame numbers, got {bad[0]!r}")
    start = time.perf_counter()
    if workers is not None and scheduler is None and local_processes(workers, processes):
        share_accelerator()  # before the rig below starts JAX: the workers share this process's GPU
    _tune_allocator(options)  # before this build's threads allocate: they then share the tuned heaps
    source = as_source(source)  # a capture with a missing / malformed header stops the build here
    source.rig()  # so do the calibrations and (for the BEV) sensors.json, before anything is written
    if options.bev and source.has_bev():
        source.bev_sensor()  # its scale, size and mount
    out = check_output_folder(out_dir)
    use_compile_cache(options.compile_cache)  # the driver's (an unusable folder warns once, here)
    (out / DONE_DIR).mkdir(parents=True, exist_ok=True)  # marks the folder as a jaxfish dataset from now on
    from ..io._folder import folder_lock, shard_lock

    lock = (folder_lock(out, DatasetError, "build") if shard is None else
            shard_lock(out, out / SHARDS_DIR, shard.index, shard.count, DatasetError, "build"))
    with lock:  # the driver's: dask workers write under it
        return _build_locked(source, out, frames, options, scheduler, workers, processes, progress, rebuild, start,
                             shard)


def _shard_owner(shard: Shard, samples: Sequence[str]) -> Callable[[Path], bool]:
    """Whether a temporary file's destination (``folder / stem``, relative to the dataset) is one
    of ``samples``' files or ``shard``'s record: what a shard build may clean up."""
    own = set(samples)
    record = Path(SHARDS_DIR) / shard.name

    def owned(dest: Path) -> bool:
        return dest == record or dest.name.split("_", 1)[0] in own

    return owned


def _build_locked(source, out: Path, frames: Sequence[int] | None, options: BuildOptions, scheduler: str | None,
                  workers: int | None, processes: bool | None, progress: Callable[[str, str | None], None] | None,
                  rebuild: bool, start: float, shard: Shard | None = None) -> BuildReport:
    available = source.frames
    wanted = list(available) if frames is None else [int(f) for f in frames]
    requested = sorted(set(wanted))
    owned = None
    if shard is not None:
        wanted = shard.select(wanted)
        owned = _shard_owner(shard, [sample_id(f) for f in wanted])
        shard.record_path(out).unlink(missing_ok=True)  # written again once this shard is complete
    missing = [f for f in wanted if f not in available]
    report = BuildReport(out_dir=out, samples=[sample_id(f) for f in wanted])
    report.stale_removed = remove_stale_temporaries(out, owned=owned)
    outdated = _outdated_samples(out, source, options)
    if shard is not None:  # a shard judges (and replaces) only its own samples
        outdated = {sid: diffs for sid, diffs in outdated.items() if sid in set(report.samples)}
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
            report.failed[sid] = f"{source.where}: frame {f} is not in the capture (field 'frames')"
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
        if todo and scheduler is None and workers is not None and not local_processes(workers, processes):
            _run_threads(source, str(out), todo, options, workers, record)
        elif todo and (scheduler is not None or workers is not None):  # absolute paths: workers may run elsewhere
            _run_dask(_for_workers(source), str(out.resolve()), todo, options, scheduler, workers, record)
        else:
            for frames_ in _batches(todo, options.batch_frames):
                for result in _counted_batch_task(source, str(out), frames_, options):
                    record(*result)
    except KeyboardInterrupt:  # every writer of this build has stopped (remote workers aside): clean up, report
        raise _interrupted(report, out, todo, scheduler is None, start, owned) from None
    if shard is None:
        finish_dataset(source, out, options)
    elif report.ok:
        write_shard_record(source, out, options, shard, requested, report.samples)
    report.built.sort()
    report.seconds = time.perf_counter() - start
    return report


def _interrupted(report: BuildReport, out: Path, todo: list[int], clean: bool, start: float,
                 owned: Callable[[Path], bool] | None = None) -> BuildInterrupted:
    """After an interrupt, once nothing of this build writes any more (``clean``): remove the files
    of the samples it cut off (those not complete) and the temporary files (``owned`` only: a
    shard's); complete samples stay."""
    if clean:
        for f in todo:
            if not is_complete(out, sample_id(f)):
                remove_sample_files(out, sample_id(f))
        remove_stale_temporaries(out, owned=owned)
    report.built.sort()
    report.seconds = time.perf_counter() - start
    return BuildInterrupted(report, [s for s in report.samples if is_complete(out, s)])


THREAD_WORKERS_MAX = 2
"""The most local workers `build_dataset` runs as threads of its own process when ``processes`` is
None (more run as process workers): threads share the process's compiled programs and rig
constants and start at once, but a sample holds Python's global interpreter lock for part of its
time, which bounds how many of them help (docs/performance.md)."""


def local_processes(workers: int, processes: bool | None) -> bool:
    """Whether `build_dataset`'s ``workers`` local workers are processes (a dask ``LocalCluster``) or
    threads of the building process: ``processes`` when given, else processes beyond
    `THREAD_WORKERS_MAX` workers."""
    return bool(processes) if processes is not None else int(workers) > THREAD_WORKERS_MAX


def _contiguous_runs(items: list, n: int) -> list[list]:
    """``items`` (in frame order) split into ``n`` contiguous runs of sizes differing by at most one."""
    bounds = [round(i * len(items) / n) for i in range(n + 1)]
    return [items[a:b] for a, b in zip(bounds[:-1], bounds[1:], strict=True)]


def _run_threads(source, out_dir: str, frames: list[int], options: BuildOptions, workers: int,
                 record: Callable[[str, str | None], None]) -> None:
    """Run the samples on ``workers`` threads of this process, which share its compiled programs,
    rig constants and source. This thread builds the first batch (each program of a sample is then
    compiled once), then each thread builds a contiguous run of the remaining batches in frame
    order, so that each sample after the first of a run reuses its predecessor's images at t
    (`set_sequence_slots`: one kept frame per thread); a thread whose run is done takes the later
    half of the longest run left. ``record`` is called in this thread. On a ``KeyboardInterrupt``
    the threads stop before their next file and it propagates once they have ended."""
    batches = _batches(frames, options.batch_frames)
    for result in _counted_batch_task(source, out_dir, batches[0], options):
        record(*result)
    runs = [collections.deque(run) for run in _contiguous_runs(batches[1:], workers)]
    lock = threading.Lock()
    results: queue.SimpleQueue = queue.SimpleQueue()

    def take(i: int) -> list[int] | None:
        with lock:
            if not runs[i]:
                longest = max(runs, key=len)
                runs[i].extend(longest.pop() for _ in range(len(longest) // 2))
                runs[i].reverse()  # popped from the end: back in frame order
            return runs[i].popleft() if runs[i] else None

    def work(i: int) -> None:
        try:
            while (batch := take(i)) is not None:
                results.put(_counted_batch_task(source, out_dir, batch, options))
        except BaseException as e:  # noqa: BLE001 - handed to the building thread, which raises it
            results.put(e)
        finally:
            results.put(None)

    slots = set_sequence_slots(max(sequence_slots(), workers))
    threads = [threading.Thread(target=work, args=(i,), name=f"jaxfish-build-{i}", daemon=True) for i in range(workers)]
    try:
        for t in threads:
            t.start()
        ended = 0
        while ended < len(threads):
            item = results.get()
            if item is None:
                ended += 1
            elif isinstance(item, BaseException):
                raise item
            else:
                for result in item:
                    record(*result)
    except BaseException:
        _STOP.set()  # the threads leave their samples before the next file
        for t in threads:
            if t.is_alive():
                t.join()
        raise
    finally:
        _STOP.clear()
        set_sequence_slots(slots)


def _for_workers(source):
    """The source as workers that may run elsewhere see it (a capture by its absolute path)."""
    return CaptureSource(source.root.resolve()) if isinstance(source, CaptureSource) else source


def _run_dask(source, out_dir: str, frames: list[int], options: BuildOptions, scheduler: str | None,
              workers: int | None, record: Callable[[str, str | None], None]) -> None:
    """Run the samples on a cluster: ``scheduler``'s, else a local cluster of ``workers`` process
    workers. On a ``KeyboardInterrupt`` the workers of a local cluster are killed before it
    propagates (their running samples are cut off); on an external ``scheduler`` the pending tasks
    are cancelled and the running ones end on their own."""
    try:
        from distributed import Client, as_completed
    except ImportError as e:  # pragma: no cover - depends on the environment
        raise DatasetError("dask.distributed is not installed: pip install 'jaxfish[distributed]'") from e
    cluster = client = quiet = None
    futures: list = []
    warming: list = []  # held until the end: a released future is cancelled
    try:
        if scheduler is not None:
            try:
                client = Client(scheduler)
            except (ValueError, OSError, TimeoutError) as e:  # a malformed or unreachable address
                raise DatasetError(f"scheduler {scheduler!r}: cannot connect ({type(e).__name__}: {e})") from None
        else:
            cluster = local_cluster(int(workers or 1), processes=True)  # process workers pin themselves
            client = Client(cluster)
        batches = {f"jaxfish-samples-{sample_id(b[0])}-{sample_id(b[-1])}": b for b in _batches(frames, options.batch_frames)}
        warm = list(batches)[:WARM_BATCHES] if _warms_cache(cluster, options, len(batches)) else []
        warming = _warm_workers(client, source, options) if warm else []
        for key in warm:
            for sid, err in _counted_batch_task(source, out_dir, batches.pop(key), options):
                record(sid, err)
        runs = _worker_runs(client, list(batches))
        futures = [client.submit(_worker_batch_task, source, out_dir, batches[key], options, key=key, pure=False,
                                 priority=len(runs) - i, **_placement(worker))  # a worker runs its batches in order
                   for i, (key, worker) in enumerate(runs)]
        for fut in as_completed(futures):
            try:
                results = fut.result()
            except Exception as e:  # the worker itself died
                results = [(sample_id(f), f"worker failure: {type(e).__name__}: {e}") for f in batches[str(fut.key)]]
            for sid, err in results:
                record(sid, err)
    except KeyboardInterrupt:
        quiet = _quiet_dask_logs()  # the workers' ends are expected: no warnings, no tracebacks
        _stop_workers(client, cluster, futures + warming)
        raise
    finally:
        try:
            for closable in (client, cluster):
                if closable is not None:  # after an interrupt, an error closing would only hide it
                    with contextlib.suppress(*(() if quiet is None else (Exception,))):
                        closable.close()
        finally:
            with _CACHE_LOCK:  # thread workers behind a scheduler in this process kept the source here
                _KEPT.clear()
            if quiet is not None:
                quiet()


def _worker_addresses(client) -> list[str]:
    """The addresses of the cluster's workers now, in worker-name order (`local_cluster` names them
    0..N-1, as `share_cores` pins them); empty when the scheduler cannot tell."""
    try:
        info = client.scheduler_info()["workers"]
    except Exception:  # noqa: BLE001 - an unanswered query: no placement
        return []
    return sorted(info, key=lambda a: (str(info[a].get("name", a)), a))


def _worker_runs(client, keys: list[str]) -> list[tuple[str, str | None]]:
    """``(batch key, worker address or None)`` in submission order: with W >= 2 workers, the
    batches (in frame order) split into W contiguous runs of sizes differing by at most one, run i
    on worker i, submitted step by step across the runs. A worker therefore builds consecutive
    frames one after the other, as a serial build does, and each sample after the first of its run
    finds its t-1 images already resampled (`jaxfish.pipeline.sample_truth`); the placement is a
    preference (`_placement`), so an idle worker still takes another's pending batches, and a lost
    worker's batches go to the others."""
    addresses = _worker_addresses(client)
    if len(addresses) < 2:
        return [(key, None) for key in keys]
    runs = [[(key, w) for key in run] for w, run in zip(addresses, _contiguous_runs(keys, len(addresses)), strict=True)]
    return [run[step] for step in range(max(map(len, runs))) for run in runs if step < len(run)]


def _placement(worker: str | None) -> dict[str, Any]:
    """`client.submit` keywords that prefer ``worker`` (nothing for None)."""
    return {} if worker is None else {"workers": [worker], "allow_other_workers": True}


def _warm_worker(source, options: BuildOptions) -> None:
    """A worker's preparation before its first sample: the process settings and the source's rig
    constants (`rig_constants_of`, loading the LUT programs from the compile cache). A failure is
    left to the samples, which report it with their reason."""
    with contextlib.suppress(Exception):
        _prepare_process(options)
        rig_constants_of(_kept_source(source))


def _warm_workers(client, source, options: BuildOptions) -> list:
    """Start `_warm_worker` on every worker of ``client`` (one task each, placed on it), while the
    driver builds the `WARM_BATCHES`: a worker's start-up (imports, rig constants) then overlaps the
    driver's compilation instead of delaying the worker's first sample. The driver builds its own
    rig constants first, so that the workers load their programs from the cache. Returns the tasks'
    futures."""
    with contextlib.suppress(Exception):  # a failure is the driver's first sample's to report
        _prepare_process(options)
        rig_constants_of(source)
    return [client.submit(_warm_worker, source, options, key=f"jaxfish-warm-{i}", pure=False, priority=_WARM_PRIORITY,
                          **_placement(address))  # a preference: a restarted worker's warm-up runs elsewhere
            for i, address in enumerate(_worker_addresses(client))]


_WARM_PRIORITY = 2**62
"""Dask priority of the workers' warm-up tasks: above every sample's (`_worker_runs`' position)."""


WARM_BATCHES = 2
"""Batches the driver of a local process cluster builds itself, with a compile cache, before the
workers start theirs: two, because the later samples of a build use programs its first one does not
(about a quarter of them, measured on an 8-sample build)."""


def _warms_cache(cluster, options: BuildOptions, batches: int) -> bool:
    """Whether the driver builds the first `WARM_BATCHES` batches itself before the workers start:
    with a local (process) cluster and a compile cache, so that the programs are compiled once
    (here, into the cache) and the workers load them instead of all compiling them at the same time."""
    import jax

    return (cluster is not None and batches > WARM_BATCHES and options.compile_cache is not False
            and bool(jax.config.jax_compilation_cache_dir))


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


def _stop_workers(client, cluster, futures: list) -> None:
    """Stop the workers of an interrupted build: when this returns, no sample of it is written any
    more by a local cluster's workers (killed); an external cluster's pending tasks are cancelled."""
    if cluster is None:  # an external cluster: its workers are not ours to end
        if client is not None and futures:
            with contextlib.suppress(Exception):
                client.cancel(futures)
        return
    _end_local_workers(cluster)


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
    ``processes=False``): with processes, the cluster `build_dataset` starts for local process
    workers.

    Dask's nannies export ``MALLOC_TRIM_THRESHOLD_=65536`` to their workers, which turns off
    glibc's dynamic mmap threshold: every image-sized buffer then becomes a fresh, page-faulting
    mapping, which multiplies a sample's CPU time (docs/performance.md). These workers keep glibc's
    defaults, except that their threads share at most `MALLOC_ARENAS` heaps from the start
    (`jaxfish.dataset._runtime.allocator_env`). No dashboard; the scheduler's HTTP routes (health, metrics) take
    a free port, not dask's 8787 (another cluster on this machine would make dask warn on stderr).

    Process workers end with the process that calls this (its nannies run in it), however it ends,
    ``kill -9`` included, and ignore SIGINT and SIGTERM (`jaxfish.dataset._runtime.dask_setup`, a
    worker preload added to ``distributed.worker.preload``): stopping them is that process's job.
    On a GPU they allocate its memory as they need it (`jaxfish.dataset._runtime.accelerator_sharing_env`),
    so that several of them and that process can share it.
    With more than one, each process worker pins itself, as it starts and before JAX sizes its
    thread pools, to its own share of this process's cores (`jaxfish.dataset.core_shares`, worker
    ``i`` the ``i``-th share, as `jaxfish.dataset.share_cores` would pin them later)."""
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
        # Set in the worker only, over any inherited value; the workers share this process's GPU.
        kwargs["env"] = {BUILD_PID_ENV: str(os.getpid()), **accelerator_sharing_env(), **allocator_env()}
        cores = sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else []
        if cores and workers > 1:  # each worker pins itself to its share as it starts
            kwargs["env"][CORE_SHARES_ENV] = encode_shares(core_shares(workers, cores))
        preload = dask.config.get("distributed.worker.preload", None) or []
        kwargs["preload"] = ([preload] if isinstance(preload, str) else list(preload)) + ["jaxfish.dataset._runtime"]
    # The workers' statistical profiler samples every thread's stack periodically for the
    # dashboard, which these clusters do not start: it would only cost CPU time.
    with dask.config.set({"distributed.nanny.pre-spawn-environ": environ, "distributed.worker.profile.enabled": False}):
        return LocalCluster(n_workers=workers, threads_per_worker=1, processes=processes, dashboard_address=None,
                           scheduler_kwargs={"dashboard_address": "127.0.0.1:0"}, **kwargs)

