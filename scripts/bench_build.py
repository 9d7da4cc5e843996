"""Benchmark: the dataset builder on a full-size two-frame capture (4 fisheyes 1280 x 966 from
768 px cube faces + BEV 1024 x 1024, all modalities, I/O included), on smooth and on textured content.

The embedded scene's smooth materials compress to about 1 bit per pixel as PNG, a CARLA render to
about 14: a benchmark on smooth content flatters every codec. ``--content both`` (the default)
measures a capture of each (``CaptureConfig.textured``: surface detail with a CARLA render's PNG
statistics), rendered in a child process when ``--capture`` / ``--textured-capture`` hold none.

Per content it prints the RGB cube faces' bits per pixel (Up filter + zlib level 1, as jaxfish
writes PNGs) next to the real SynWoodScape frame's (``../shared/samples/``; the textured faces must
be within ±30 %), and a **stage table** (`measure_stages`, in a fresh process after a compiling
round): CPU seconds per sample of decode, ground truth, BEV, encode and file system, their sum, the
whole `build_sample` from the capture and from the decoded frame in memory, the same for the next
sample of a sequence (frame 1 built right after frame 0: its t-1 is frame 0's t, decoded and
resampled once), the 2-core bound each implies (2 / CPU-s samples/s) and the process's peak
memory. Then, on the textured capture (the goals count on it), after compilation: the serial rate
(samples/s, the median of ``--repeat`` rebuilds into fresh directories), the peak resident memory
of the process (``resource.getrusage``), and the rate of dask ``LocalCluster`` builds with 1 and 2
single-threaded process workers, each pinned to its share of the cores as `build_dataset` pins them
(`jaxfish.dataset.share_cores`; each worker warms up on the sample first; then ``2 x workers``
builds of the sample run as separate tasks).

    uv run python scripts/bench_build.py                    # renders both captures first (minutes)
    uv run python scripts/bench_build.py --capture out/cap --textured-capture out/cap-tex  # kept, reused
    uv run python scripts/bench_build.py --scale 0.5 --tables-only  # half size, stage tables only

``--workers 1,2,4`` instead builds every frame of the capture (``--frames N`` when rendered) in
whole builds, each in a fresh process: serial and on that many local workers of each kind of
``--local`` (threads of the building process; a local dask cluster of pinned process workers, 4
on 2 cores: two per core), with no compile cache (``off``), an empty one (``cold``) and
the one the cold build filled (``warm``) (``--caches``); it prints each build's wall time
(compilation, cluster start included), the time to its first sample, its rate after the first,
and its rate over the second half of its samples (every worker past its start: the rate a long build
keeps), and for the serial build the CPU seconds per sample over that second half (every thread of
the process that builds: what a long serial build costs a sample, its files kept as a build keeps
them).

    uv run python scripts/bench_build.py --content textured --scale 0.25 --frames 8 --workers 1,2,4

``--sequence`` instead builds every frame of the capture in order into one kept folder, serially in
a fresh process with the builder's defaults, once from the capture and once from memory (each frame
decoded first, untimed), and prints each sample's CPU seconds (user and system, every thread), its
wall time, the programs it traced (a program variant met for the first time) and the system's free
memory after it; then the median over the samples past the first three that traced no program:
what each sample of a long build costs. ``--sequence capture`` or ``--sequence memory`` runs one of
the two. With ``--one-frame`` the frames are built every other one (0, 2, 4, ..., then 1, 3, 5,
...): no sample follows its predecessor, so each is a one-frame sample (its t-1 images decoded,
resampled and labelled), measured in a long build's steady state like the others.

    uv run python scripts/bench_build.py --content textured --sequence --textured-capture CAP  # e.g. 20 frames
    uv run python scripts/bench_build.py --content textured --sequence --one-frame --textured-capture CAP

Goals: <= 2.0 CPU-s per sample from the textured capture (>= 1 sample/s on two cores), <= 1.5 from
memory, peak < 4 GB. Current figures: docs/performance.md.
"""

from __future__ import annotations

import argparse
import os
import resource
import shutil
import statistics
import tempfile
import time
from pathlib import Path


def _peak_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _warm(capture: str, scratch: str) -> float:
    import os

    from jaxfish.dataset import build_sample

    start = time.perf_counter()
    build_sample(capture, os.path.join(scratch, f"warm-{os.getpid()}"), 0)
    return time.perf_counter() - start


def _task(capture: str, out: str) -> float:
    from jaxfish.dataset import build_sample

    start = time.perf_counter()
    build_sample(capture, out, 0)
    return time.perf_counter() - start


def _worker_peak_mb() -> float:
    """Peak RSS of a worker from /proc (VmHWM): ``ru_maxrss`` survives ``execve`` and would report
    the parent's peak for spawned workers."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return float(line.split()[1]) / 1024.0
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def bench_dask(capture: Path, scratch: Path, workers: int) -> tuple[float, float, list[float]]:
    from distributed import Client

    from jaxfish.dataset import local_cluster, share_cores

    with local_cluster(workers) as cluster, \
            Client(cluster) as client:
        share_cores(client)  # as build_dataset does for its local cluster
        warm = client.run(_warm, str(capture), str(scratch / f"dask{workers}"))
        n = 2 * workers
        start = time.perf_counter()
        futures = [client.submit(_task, str(capture), str(scratch / f"dask{workers}" / f"run{i}"), pure=False)
                   for i in range(n)]
        client.gather(futures)
        rate = n / (time.perf_counter() - start)
        peaks = list(client.run(_worker_peak_mb).values())
    return rate, max(warm.values()), peaks


def _cpu_s() -> float:
    t = os.times()
    return t.user + t.system


CONTENTS = ("smooth", "textured")
"""What a benchmark capture's RGB shows: the embedded scene's smooth materials, or its surface
detail (`CaptureConfig.textured`: a CARLA render's PNG statistics)."""
REAL_FRAME = Path(__file__).resolve().parents[1].parent / "shared" / "samples" / "synwoodscape_FV_rgb.png"
"""The CARLA-rendered SynWoodScape front frame the textured faces are compared with."""
MATCH = 0.30
"""The textured faces' bits per pixel must be within this fraction of the real frame's."""


def capture_settings(scale: float, textured: bool):
    """The benchmark capture's rig and `CaptureConfig` at ``scale`` (1: the default rig's 1280 x 966
    fisheyes from 768 px cube faces, BEV 1024 px, as `CaptureConfig()`); smaller scales shrink every
    image (the BEV keeps its ground coverage)."""
    import dataclasses

    import jax.numpy as jnp

    from jaxfish import default_rig
    from jaxfish.scene import CaptureConfig

    rig, config = default_rig(), CaptureConfig(textured=textured)
    if scale == 1.0:
        return rig, config
    rig = {k: v.resize(max(16, round(v.camera.width * scale)), max(12, round(v.camera.height * scale))).astype(jnp.float32)
           for k, v in rig.items()}
    bev = max(16, round(config.bev_size * scale))
    front = max(16, round(config.front_width * scale))
    return rig, dataclasses.replace(config, face_size=max(16, round(config.face_size * scale)), bev_size=bev,
                                    bev_metres_per_pixel=config.bev_metres_per_pixel * config.bev_size / bev,
                                    front_width=front, front_height=max(12, round(front * 3 / 4)))


def render_capture(path: str, scale: float, textured: bool, frames: int = 1) -> float:
    """Render frames 0 to ``frames - 1`` of seed 0 into ``path`` (run in a child process: its memory
    is not the builder's); returns the seconds it took."""
    from jaxfish.dataset import synthesize_capture

    rig, config = capture_settings(scale, textured)
    start = time.perf_counter()
    synthesize_capture(path, rig, frames=frames, seed=0, config=config)
    return time.perf_counter() - start


def in_child(fn, *args):
    """``fn(*args)`` in a fresh process (spawned: its own JAX, compilations and peak memory)."""
    import concurrent.futures
    import multiprocessing

    with concurrent.futures.ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn")) as pool:
        return pool.submit(fn, *args).result()


def up_bits_per_pixel(rgb) -> float:
    """Bits per pixel of an RGB image as jaxfish's PNGs store it: the "Up" row filter, then one zlib
    stream at level 1 (the real frame is measured the same way)."""
    import zlib

    import numpy as np

    a = np.ascontiguousarray(rgb, np.uint8)
    rows = a.reshape(a.shape[0], -1)
    up = rows.copy()
    up[1:] = rows[1:] - rows[:-1]
    raw = np.concatenate([np.full((rows.shape[0], 1), 2, np.uint8), up], axis=1).tobytes()
    return 8.0 * len(zlib.compress(raw, 1)) / (a.shape[0] * a.shape[1])


def face_bits_per_pixel(capture: Path) -> tuple[float, int]:
    """Bits per pixel of every RGB cube face at t of frame 0 (all faces' bytes over all their
    pixels), and how many faces."""
    from jaxfish.io import read_image

    bits = pixels = 0.0
    faces = sorted((capture / "frames" / "000000" / "cameras").glob("*/*/rgb_curr.png"))
    for path in faces:
        bgr = read_image(path)[..., 2::-1]  # CARLA BGRA -> RGB
        bits += up_bits_per_pixel(bgr) * bgr.shape[0] * bgr.shape[1]
        pixels += bgr.shape[0] * bgr.shape[1]
    return bits / max(pixels, 1.0), len(faces)


def report_bits_per_pixel(content: str, capture: Path) -> None:
    """Print the capture's RGB faces' bits per pixel next to the real frame's (Up + zlib level 1)."""
    from jaxfish.io import read_image

    faces, n = face_bits_per_pixel(capture)
    line = f"{content}: {n} RGB cube faces at t take {faces:.2f} bits/px (Up filter + zlib level 1)"
    if REAL_FRAME.is_file():
        real = up_bits_per_pixel(read_image(REAL_FRAME)[..., :3])
        ratio = faces / real
        verdict = "within" if abs(ratio - 1.0) <= MATCH else "OUTSIDE"
        line += (f"; the real SynWoodScape frame {real:.2f} bits/px: ratio {ratio:.2f}, {verdict} "
                 f"±{MATCH:.0%}" + ("" if content == "textured" else " (smooth content is not meant to match)"))
    else:
        line += f"; the real frame ({REAL_FRAME}) is missing"
    print(line, flush=True)


STAGES = ("decode", "ground truth", "BEV", "encode", "file system")
"""The stage table's rows, in pipeline order."""


class _Decoded:
    """A source that hands over one frame, or ``{index: frame}``, already decoded (an in-memory
    source: no capture decode; a capture's deferred face events read into memory first, `_held`);
    everything else is the wrapped source's."""

    def __init__(self, source, frame):
        self._source = source
        self._frame = {i: _held(f) for i, f in frame.items()} if isinstance(frame, dict) else _held(frame)

    def __getattr__(self, name):
        return getattr(self._source, name)

    def read(self, index: int, *, bev: bool = True):
        return self._frame[index] if isinstance(self._frame, dict) else self._frame


def _held(frame):
    """``frame`` with its face events as arrays in memory (a capture's are read when mapped:
    `jaxfish.io.DeferredEvents`)."""
    import equinox as eqx
    import numpy as np

    cams = tuple(eqx.tree_at(lambda cf: cf.events, cf, tuple(np.asarray(e) for e in cf.events))
                 for cf in frame.camera_frames)
    return eqx.tree_at(lambda f: f.camera_frames, frame, cams)


def _replay_writes(files: dict[Path, bytes]) -> None:
    from jaxfish.io import atomic_write_bytes

    for path, data in files.items():
        atomic_write_bytes(path, data)


def measure_stages(capture: str, scratch: str, repeat: int) -> dict:
    """CPU seconds per sample (``time.process_time``: this process, every thread) of each stage of a
    sample of ``capture``, run one after the other around the pipeline's own calls (median of
    ``repeat`` after a round that compiles):

    - decode: `CaptureSource.read` (every image decoded: ``reuse_decoded=False``; the face
      events' headers checked, their events read when the ground truth maps them);
    - ground truth: `sample_truth` of the fisheye cameras (``bev=False``), the face events read;
    - BEV: `bev_truth`;
    - encode: `LayoutSink.write` of every file of the sample, less the file system's share;
    - file system: the same files' bytes written again the way jaxfish writes a file
      (`atomic_write_bytes`: a temporary file, its bytes, chmod, rename; the builder calls no fsync).

    First (median of ``repeat`` after a compiling round) the whole `build_sample` (thread pool,
    SHA-256 of every file and the marker included) from the capture, and the process's peak RSS
    after them (compilation included; not the later runs', which hold a decoded frame or a
    sample's files in memory); then the same builds from the decoded frame handed over in memory.
    With two frames or more, then the next sample of a sequence: `build_sample` of frame 1 right
    after frame 0 (the builder's source, `CaptureSource` keeping its decodes: frame 1's images at
    t-1, byte copies of frame 0's at t, are neither decoded nor resampled again), from the capture
    and from the two decoded frames in memory. Run it in a fresh process (`in_child`)."""
    import jax

    from jaxfish.dataset import BuildOptions, CaptureSource, LayoutSink, build_sample, rig_constants_of
    from jaxfish.pipeline import SampleTruth, bev_truth, sample_truth

    source = CaptureSource(capture, reuse_decoded=False)
    options = BuildOptions().ground_truth()
    fisheye_options = type(options)(backward_flow=options.backward_flow, motion_threshold_m=options.motion_threshold_m,
                                    bev=False)
    constants = rig_constants_of(source)
    root = Path(scratch)
    runs: dict[str, list[float]] = {}

    def timed(name, fn, *args):
        c = time.process_time()
        result = jax.block_until_ready(fn(*args))
        runs.setdefault(name, []).append(time.process_time() - c)
        return result

    def whole_builds(name: str, src) -> None:
        for i in range(repeat + 1):  # the first round compiles
            c = time.process_time()
            build_sample(src, root / f"build{i}", 0)
            runs.setdefault(name, []).append(time.process_time() - c)
            shutil.rmtree(root / f"build{i}")

    whole_builds("total", source)  # first: the peak memory of builds from the capture, nothing else held
    peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    whole_builds("in memory", _Decoded(source, source.read(0)))  # the decoded frame held throughout
    if 1 in source.frames:
        def next_sample(name: str, src) -> None:
            for i in range(repeat + 1):  # the first round compiles
                build_sample(src, root / f"seq{i}", 0)
                c = time.process_time()
                build_sample(src, root / f"seq{i}", 1)
                runs.setdefault(name, []).append(time.process_time() - c)
                shutil.rmtree(root / f"seq{i}")

        in_order = CaptureSource(capture)  # reuse_decoded, as the builder reads a capture
        next_sample("sequence", in_order)
        next_sample("sequence in memory", _Decoded(in_order, {0: in_order.read(0), 1: in_order.read(1)}))
    names = [n for n in ("total", "in memory", "sequence", "sequence in memory") if n in runs]
    builds = {name: runs[name][1:] or runs[name] for name in names}  # without the compiling round
    runs.clear()
    for i in range(repeat + 1):  # the first round compiles the stages' own programs
        if i == 1:
            runs.clear()
        frame = timed("decode", source.read, 0)
        truth = timed("ground truth", sample_truth, frame, constants, fisheye_options)
        bev = timed("BEV", bev_truth, frame, constants, options) if frame.bev is not None else None
        full = SampleTruth(index=truth.index, cameras=truth.cameras, bev=bev, motion=truth.motion,
                           displacement_m=truth.displacement_m, corners_world=truth.corners_world,
                           corners_vehicle=truth.corners_vehicle, sensors=truth.sensors)
        out = root / f"stages{i}"
        paths = timed("sink", LayoutSink(out).write, "00000", full)
        files = {root / f"replay{i}" / p.relative_to(out): p.read_bytes() for p in paths}
        shutil.rmtree(out)
        timed("file system", _replay_writes, files)
        shutil.rmtree(root / f"replay{i}")
    med = {name: statistics.median(v) for name, v in {**runs, **builds}.items()}
    med["encode"] = max(med.pop("sink") - med["file system"], 0.0)
    med["peak_mb"] = peak_mb
    med["files"] = len(paths)
    med["mb"] = sum(len(b) for b in files.values()) / 2**20
    return med


def print_stage_table(content: str, stages: dict, repeat: int) -> None:
    """The stage table of one content: CPU seconds per sample and the 2-core bound they imply."""
    def bound(cpu: float) -> str:
        return f"{2.0 / cpu:5.2f}" if cpu > 0 else "  inf"

    print(f"stage table, {content} capture ({stages['files']} files, {stages['mb']:.0f} MB per sample; "
          f"CPU seconds per sample, median of {repeat}; 2-core bound = 2 / CPU-s samples/s):")
    print(f"  {'stage':46s} {'CPU-s':>6s}")
    for name in STAGES:
        print(f"  {name:46s} {stages[name]:6.2f}")
    total = sum(stages[name] for name in STAGES)
    print(f"  {'sum of the stages':46s} {total:6.2f}   2-core bound {bound(total)} samples/s")
    print(f"  {'build_sample from the capture (total)':46s} {stages['total']:6.2f}   2-core bound "
          f"{bound(stages['total'])} samples/s (goal <= 2.00 CPU-s)")
    print(f"  {'build_sample from memory (no decode)':46s} {stages['in memory']:6.2f}   2-core bound "
          f"{bound(stages['in memory'])} samples/s (goal <= 1.50 CPU-s)")
    if "sequence" in stages:
        print(f"  {'next sample of a sequence, from the capture':46s} {stages['sequence']:6.2f}   2-core bound "
              f"{bound(stages['sequence'])} samples/s (frame 1 after frame 0)")
        print(f"  {'next sample of a sequence, from memory':46s} {stages['sequence in memory']:6.2f}   2-core bound "
              f"{bound(stages['sequence in memory'])} samples/s")
    print(f"  peak memory of the builds from the capture (compilation included): {stages['peak_mb']:.0f} MB (goal < 4096)", flush=True)


def prepare_captures(args, scratch: Path) -> dict[str, Path]:
    """``{content: capture}`` for ``--content``: ``--capture`` (smooth) and ``--textured-capture``
    when they hold a capture, else rendered there (or in ``scratch``) in a child process."""
    wanted = CONTENTS if args.content == "both" else (args.content,)
    given = {"smooth": args.capture, "textured": args.textured_capture}
    captures = {}
    for content in wanted:
        path = given[content]
        if path is None or not (path / "capture.json").is_file():
            path = path or scratch / f"capture-{content}"
            seconds = in_child(render_capture, str(path), args.scale, content == "textured", args.frames)
            print(f"rendered the {content} capture (scale {args.scale:g}) in {seconds:.1f} s: {path}", flush=True)
        captures[content] = path
    return captures


def report_contents(captures: dict[str, Path], scratch: Path, repeat: int) -> None:
    """Per content: the RGB faces' bits per pixel against the real frame's, then the stage table."""
    print(f"load average before the stage tables: {', '.join(f'{x:.2f}' for x in os.getloadavg())}")
    for content, capture in captures.items():
        report_bits_per_pixel(content, capture)
        work = scratch / f"stages-{content}"
        work.mkdir(parents=True, exist_ok=True)
        print_stage_table(content, in_child(measure_stages, str(capture), str(work), repeat), repeat)


# ------------------------------------------------------------------ whole builds on 1, 2, 4 workers
def _whole_build(capture: str, out: str, workers: int, cache: str, processes: bool | None = None) -> dict:
    """One whole build in this (fresh) process: ``workers`` 0 = serial, else that many local
    workers (``processes``: `build_dataset`'s); ``cache`` a folder or "" (no compile cache). Returns the build's wall time (compilation, cluster start included) and
    its rate after the first sample (compilation excluded), and for a build in this process its
    CPU time per sample over the second half and its peak resident memory."""
    from jaxfish.dataset import BuildOptions, build_dataset, local_processes

    stamps: list[float] = []
    cpu: list[float] = []  # this process's CPU time at each completion: a serial or thread build's own work

    def progress(_sample, _error) -> None:
        stamps.append(time.perf_counter())
        cpu.append(time.process_time())

    start = time.perf_counter()
    report = build_dataset(capture, out, options=BuildOptions(compile_cache=cache or False),
                           workers=workers or None, processes=processes, progress=progress)
    wall = time.perf_counter() - start
    assert report.ok, report.summary()
    half = len(stamps) // 2 - 1
    own = workers == 0 or not local_processes(workers, processes)  # every sample built in this process
    peak_gb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20 if own else None  # kB -> GiB
    return {"peak_gb": peak_gb, "wall_s": wall, "first_s": stamps[0] - start, "after_rate": _rate(stamps),
            "samples": len(report.built),
            "half_rate": _rate(stamps[half:] if len(stamps) >= 4 else []),
            "half_cpu_s": ((cpu[-1] - cpu[half]) / (len(cpu) - 1 - half)
                           if own and len(cpu) >= 4 else None)}


def _rate(stamps: list[float]) -> float:
    """Samples per second between the first and the last of ``stamps`` (completion times)."""
    return (len(stamps) - 1) / (stamps[-1] - stamps[0]) if len(stamps) > 1 and stamps[-1] > stamps[0] else 0.0


def _whole_build_in_a_process(capture: Path, out: Path, workers: int, cache: str, processes: bool | None) -> dict:
    import json
    import subprocess
    import sys

    start = time.perf_counter()
    done = subprocess.run([sys.executable, __file__, "--whole-build", json.dumps([str(capture), str(out), workers, cache, processes])],
                          capture_output=True, text=True, check=True)
    result = json.loads(done.stdout.strip().splitlines()[-1])
    result["process_s"] = time.perf_counter() - start  # Python and JAX start-up included
    return result


def bench_workers(capture: Path, scratch: Path, workers: list[int], caches: list[str],
                  kinds: tuple[str, ...] = ("threads", "processes")) -> None:
    """Whole builds of every frame of ``capture``, each in a fresh process, serial (``0``) and on
    ``workers`` local workers of each of ``kinds`` (threads of the building process; pinned process
    workers of a local dask cluster), with no compile cache (``off``), an empty one (``cold``) and
    the one the cold build filled (``warm``: a cold build runs, and is reported, before it when
    ``caches`` lists none)."""
    caches = list(caches)
    if "warm" in caches and "cold" not in caches[:caches.index("warm")]:
        caches.insert(caches.index("warm"), "cold")  # the warm cache is the one a cold build fills
    print(f"whole builds of {len(_frames(capture))} samples, each in a fresh process (load {os.getloadavg()[0]:.1f}):")
    print(f"  {'build':22s} {'cache':5s} {'wall s':>7s} {'first s':>8s} {'samples/s after 1st':>20s} "
          f"{'second half':>12s} {'CPU-s per sample, second half (this process)':>45s} {'peak GiB (this process)':>24s}")
    for n, kind in [(0, "serial"), *[(n, k) for n in workers for k in kinds]]:
        name = "serial" if n == 0 else f"--workers {n} --{kind}"
        folder = scratch / f"xla-{n}-{kind}"
        shutil.rmtree(folder, ignore_errors=True)
        for cache in caches:
            out = scratch / f"whole-{n}-{kind}-{cache}"
            r = _whole_build_in_a_process(capture, out, n, "" if cache == "off" else str(folder),
                                          None if n == 0 else kind == "processes")
            shutil.rmtree(out, ignore_errors=True)
            cpu = "" if r["half_cpu_s"] is None else f"{r['half_cpu_s']:.2f}"
            peak = "" if r["peak_gb"] is None else f"{r['peak_gb']:.2f}"
            print(f"  {name:22s} {cache:5s} {r['wall_s']:7.1f} {r['first_s']:8.1f} {r['after_rate']:20.2f} "
                  f"{r['half_rate']:12.2f} {cpu:>45s} {peak:>24s}", flush=True)


# ------------------------------------------------------------------ a long serial build, sample by sample
def _free_mb() -> float | None:
    """The system's free memory (``MemFree`` of ``/proc/meminfo``, MB), None where there is none."""
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemFree:"):
                return float(line.split()[1]) / 1024.0
    except OSError:
        pass
    return None


def measure_sequence(capture: str, out: str, in_memory: bool, one_frame: bool = False) -> list[dict]:
    """`build_sample` of every frame of ``capture`` in order into the one folder ``out`` (kept, as a
    build keeps its samples), in this (fresh) process with the builder's defaults (compile cache,
    tuned allocator): the builder's `CaptureSource`, so that each frame's t-1 images are its
    predecessor's t images, decoded and resampled once. ``one_frame``: every other frame instead
    (`one_frame_order`), so that no frame's predecessor was built just before it. ``in_memory``:
    each frame is decoded first, untimed, and handed over decoded (`_Decoded`). Per sample: CPU
    seconds (user, system: every thread), wall seconds, the programs it traced (a program variant
    this process meets for the first time: traced, then compiled or loaded from the cache) and the
    system's free memory after it."""
    import collections

    from jax import monitoring

    from jaxfish.dataset import BuildOptions, CaptureSource, build_sample, tune_allocator, use_compile_cache

    options = BuildOptions()
    use_compile_cache(options.compile_cache)
    tune_allocator()
    traced = collections.Counter()
    monitoring.register_event_duration_secs_listener(
        lambda event, _duration, **_kw: traced.update([event]) if event == "/jax/core/compile/jaxpr_trace_duration" else None)
    source = CaptureSource(capture)
    rows = []
    for frame in one_frame_order(source.frames) if one_frame else source.frames:
        src = _Decoded(source, source.read(frame)) if in_memory else source
        before, t0, w0 = traced.total(), os.times(), time.perf_counter()
        build_sample(src, out, frame, options=options)
        t1 = os.times()
        rows.append({"frame": frame, "user_s": t1.user - t0.user, "system_s": t1.system - t0.system,
                     "wall_s": time.perf_counter() - w0, "traced": traced.total() - before, "free_mb": _free_mb()})
    return rows


def one_frame_order(frames: list[int]) -> list[int]:
    """``frames`` every other one, then the others (0, 2, 4, ..., 1, 3, 5, ...): a build in this
    order builds no frame right after its predecessor."""
    return list(frames[0::2]) + list(frames[1::2])


SEQUENCE_WARM = 3
"""Samples of a long build the sample-by-sample figures leave out: compilation, then the first
sample (a one-frame sample: its t-1 is decoded and resampled) and the process's heap growing."""


def bench_sequence(capture: Path, scratch: Path, kinds: str = "both", one_frame: bool = False) -> None:
    """`measure_sequence` of ``capture`` from the capture, then from memory (``kinds``: ``both``,
    ``capture`` or ``memory``), each in a fresh process; per sample its CPU seconds, and the median
    over the samples after `SEQUENCE_WARM` that traced no program. ``one_frame``: every sample a
    one-frame sample (`one_frame_order`)."""
    n = len(_frames(capture))
    order = "every other frame: one-frame samples" if one_frame else "in order"
    print(f"a long serial build of {capture} ({n} frames, {order}), sample by sample, each kind in a fresh process "
          f"(load {os.getloadavg()[0]:.1f}):")
    goals = {"from the capture": 2.0, "from memory (each frame decoded first)": 1.5}
    for (kind, goal), in_memory in zip(goals.items(), (False, True), strict=True):
        if kinds != "both" and kinds != ("memory" if in_memory else "capture"):
            continue
        out = scratch / ("sequence-memory" if in_memory else "sequence")
        rows = in_child(measure_sequence, str(capture), str(out), in_memory, one_frame)
        shutil.rmtree(out, ignore_errors=True)
        print(f"  {kind}:")
        print(f"    {'frame':>5s} {'CPU-s':>6s} {'user':>6s} {'system':>7s} {'wall s':>7s} {'traced':>7s} {'free MB':>8s}")
        for r in rows:
            cpu = r["user_s"] + r["system_s"]
            free = "" if r["free_mb"] is None else f"{r['free_mb']:.0f}"
            print(f"    {r['frame']:5d} {cpu:6.2f} {r['user_s']:6.2f} {r['system_s']:7.2f} {r['wall_s']:7.2f} "
                  f"{r['traced']:7d} {free:>8s}")
        steady = [r for r in rows[SEQUENCE_WARM:] if r["traced"] == 0]
        if steady:
            cpu = [r["user_s"] + r["system_s"] for r in steady]
            med = statistics.median(cpu)
            print(f"    median over the {len(steady)} samples after the first {SEQUENCE_WARM} that traced no program: "
                  f"{med:.2f} CPU-s (range {min(cpu):.2f}-{max(cpu):.2f}; goal <= {goal:.1f}; 2-core bound "
                  f"{2 / med:.2f} samples/s); user {statistics.median(r['user_s'] for r in steady):.2f}, "
                  f"system {statistics.median(r['system_s'] for r in steady):.2f} "
                  f"(range {min(r['system_s'] for r in steady):.2f}-{max(r['system_s'] for r in steady):.2f})", flush=True)


def _frames(capture: Path) -> list:
    import json

    return json.loads((capture / "capture.json").read_text())["frames"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--capture", type=Path, default=None,
                        help="smooth capture with frame 0 (rendered there if absent; default: a temporary one)")
    parser.add_argument("--textured-capture", type=Path, default=None,
                        help="textured capture with frame 0 (rendered there if absent; default: a temporary one)")
    parser.add_argument("--content", choices=("smooth", "textured", "both"), default="both",
                        help="which captures to measure (default both)")
    parser.add_argument("--scale", type=float, default=1.0,
                        help="size of rendered captures (1: full size, fisheyes 1280 x 966 from 768 px faces)")
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--no-dask", action="store_true")
    parser.add_argument("--tables-only", action="store_true",
                        help="only the bits per pixel and the stage tables (no serial build_dataset or dask rates)")
    parser.add_argument("--workers", default=None,
                        help="instead: whole builds of every frame on these worker counts, e.g. 1,2,4 (with a serial "
                             "one), on the textured capture (the smooth one with --content smooth)")
    parser.add_argument("--caches", default="off,cold,warm", help="compile caches of the whole builds")
    parser.add_argument("--local", default="threads,processes",
                        help="kinds of local workers of the whole builds (threads, processes)")
    parser.add_argument("--sequence", nargs="?", const="both", choices=("both", "capture", "memory"), default=None,
                        help="instead: a long serial build of every frame, sample by sample, from the capture and "
                             "from memory (or only one of them), on the textured capture (the smooth one with "
                             "--content smooth)")
    parser.add_argument("--one-frame", action="store_true",
                        help="with --sequence: build every other frame, so that every sample is a one-frame sample")
    parser.add_argument("--frames", type=int, default=2,
                        help="frames of the rendered captures (two or more: the stage tables add the next sample of a sequence)")
    parser.add_argument("--whole-build", default=None, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.one_frame and not args.sequence:
        parser.error("--one-frame orders the frames of --sequence: give --sequence too")
    if args.whole_build:
        import json

        print(json.dumps(_whole_build(*json.loads(args.whole_build))))
        return
    scratch = Path(tempfile.mkdtemp(prefix="jaxfish_bench_build_"))
    try:
        captures = prepare_captures(args, scratch)
        if args.sequence:
            bench_sequence(captures.get("textured", captures.get("smooth")), scratch, args.sequence, args.one_frame)
            return
        if args.workers:
            capture = captures.get("textured", captures.get("smooth"))
            bench_workers(capture, scratch, [int(n) for n in args.workers.split(",")], args.caches.split(","),
                          tuple(args.local.split(",")))
            return
        report_contents(captures, scratch, args.repeat)
        if args.tables_only:
            return
        capture = captures.get("textured", captures.get("smooth"))  # the goals count on textured content
        print(f"serial and dask builds of {capture}:")
        from jaxfish.dataset import build_dataset

        t = time.perf_counter()
        first = build_dataset(capture, scratch / "first", frames=[0])
        assert first.ok, first.summary()
        compile_s = time.perf_counter() - t
        times, cpus = [], []
        for i in range(args.repeat):
            t, c0 = time.perf_counter(), os.times()
            rep = build_dataset(capture, scratch / f"run{i}", frames=[0])
            times.append(time.perf_counter() - t)
            c1 = os.times()
            cpus.append(c1.user + c1.system - c0.user - c0.system)
            assert rep.ok, rep.summary()
            shutil.rmtree(scratch / f"run{i}")
        med = statistics.median(times)
        files = sum(1 for p in (scratch / "first").rglob("*") if p.is_file())
        size_mb = sum(p.stat().st_size for p in (scratch / "first").rglob("*") if p.is_file()) / 2**20
        print(f"serial: first sample (compile included) {compile_s:.1f} s; after compile {med:.2f} s per sample "
              f"= {1 / med:.2f} samples/s (runs: {', '.join(f'{x:.2f}' for x in times)} s); "
              f"{files} files, {size_mb:.0f} MB per sample")
        print(f"CPU time per sample (all threads): {statistics.median(cpus):.2f} s = "
              f"{statistics.median(cpus) / med:.2f} cores busy on average; a {os.cpu_count()}-core bound of "
              f"{os.cpu_count() / statistics.median(cpus):.2f} samples/s at this work per sample")
        print(f"peak memory (this process): {_peak_mb():.0f} MB")
        if not args.no_dask:
            for n in (1, 2):
                rate, warm_s, peaks = bench_dask(capture, scratch, n)
                print(f"dask LocalCluster, {n} process worker(s): {rate:.2f} samples/s after warm-up "
                      f"(warm-up {warm_s:.1f} s); worker peak memory {', '.join(f'{p:.0f}' for p in peaks)} MB")
    finally:
        shutil.rmtree(scratch, ignore_errors=True)


if __name__ == "__main__":
    main()
