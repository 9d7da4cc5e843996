"""Benchmark: the dataset builder on a full-size one-sample capture (4 fisheyes 1280 x 966 from
768 px cube faces + BEV 1024 x 1024, all modalities, I/O included).

Measures, after compilation: the serial rate (samples/s, the median of ``--repeat`` rebuilds into
fresh directories), the peak resident memory of the process (``resource.getrusage``), and the rate
of dask ``LocalCluster`` builds with 1 and 2 single-threaded process workers, each pinned to its
share of the cores as `build_dataset` pins them (`jaxfish.dataset.share_cores`; each worker warms up
on the sample first; then ``2 x workers`` builds of the sample run as separate tasks).

    uv run python scripts/bench_build.py                    # renders the capture first (minutes)
    uv run python scripts/bench_build.py --capture out/cap  # reuse a full-size capture
    uv run python scripts/bench_build.py --capture out/cap --no-dask --stages  # + each stage's wall / CPU time
    uv run python scripts/bench_build.py --capture out/cap8 --scale 0.25 --frames 8 --workers 1,2,4

``--workers 1,2,4`` instead builds every frame of the capture in whole builds, each in a fresh
process: serial and on local clusters of that many pinned process workers (4 on 2 cores: two per
core), with no compile cache (``off``), an empty one (``cold``) and the one the cold build filled
(``warm``) (``--caches``); it prints each build's wall time (compilation, cluster start included),
the time to its first sample, and its rate after the first sample. ``--scale S --frames N``
render a capture of N frames at S times the demo's sizes when ``--capture`` names none yet.

Goal: >= 1 sample/s after compile, peak < 4 GB. Current figures: docs/performance.md.
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


def _run_jobs(jobs) -> list:
    return [p for job in jobs for p in job()]


def bench_stages(capture: Path, scratch: Path, repeat: int) -> None:
    """Wall and CPU seconds (all threads) of each stage of a sample through the pipeline, run one
    after the other: read the frame (decode), fisheye ground truth, fisheye files, BEV ground truth,
    BEV files (`build_sample` writes in a pool of threads, so it takes less wall time than their sum,
    but the same CPU time). The CPU seconds are the work per sample: a 2-core machine builds at most
    2 / CPU samples per second, so 1 sample/s needs <= 2 CPU-s."""
    import jax

    from jaxfish.dataset import CaptureSource, LayoutSink, rig_constants_of
    from jaxfish.pipeline import GroundTruthOptions, SampleTruth, bev_truth, sample_truth

    source = CaptureSource(capture, reuse_decoded=False)
    constants = rig_constants_of(source)  # the per-calibration constants a build keeps per process
    options = GroundTruthOptions(bev=False)
    stages: dict[str, list[tuple[float, float]]] = {}

    def timed(name, fn, *args):
        w, c = time.perf_counter(), _cpu_s()
        result = jax.block_until_ready(fn(*args))
        stages.setdefault(name, []).append((time.perf_counter() - w, _cpu_s() - c))
        return result

    for i in range(repeat + 1):  # the first round compiles
        if i == 1:
            stages.clear()
        out = scratch / f"stages{i}"
        sink = LayoutSink(out)
        frame = timed("read the frame (decode faces, BEV, sensors)", source.read, 0)
        truth = timed("fisheye ground truth + events + renderings", sample_truth, frame, constants, options)
        timed("write the fisheye and per-sample files (inline)", sink.write, "00000", truth)
        if frame.bev is not None:
            bev = timed("BEV ground truth", bev_truth, frame, constants, GroundTruthOptions())
            bev_only = SampleTruth(index=truth.index, cameras=(), bev=bev, motion=truth.motion,
                                   displacement_m=truth.displacement_m, corners_world=truth.corners_world,
                                   corners_vehicle=truth.corners_vehicle, sensors=truth.sensors)
            timed("write the BEV files (inline)", _run_jobs, sink.jobs("00000", bev_only)[:-2])  # the BEV's only
        shutil.rmtree(out)
    print(f"stages of one sample, run one after the other (median of {repeat}; wall / CPU seconds):")
    for name, runs in stages.items():
        wall, cpu = statistics.median(r[0] for r in runs), statistics.median(r[1] for r in runs)
        print(f"  {name:52s} {wall:5.2f} / {cpu:5.2f}")
    total = sum(statistics.median(r[1] for r in runs) for runs in stages.values())
    print(f"  CPU per sample: {total:.2f} s = a 2-core bound of {2 / total:.2f} samples/s; "
          f"1 sample/s needs <= 2.00 CPU-s")


# ------------------------------------------------------------------ whole builds on 1, 2, 4 workers
def _whole_build(capture: str, out: str, workers: int, cache: str) -> dict:
    """One whole build in this (fresh) process: ``workers`` 0 = serial; ``cache`` a folder or ""
    (no compile cache). Returns the build's wall time (compilation, cluster start included) and
    its rate after the first sample (compilation excluded)."""
    from jaxfish.dataset import BuildOptions, build_dataset

    stamps: list[float] = []
    start = time.perf_counter()
    report = build_dataset(capture, out, options=BuildOptions(compile_cache=cache or False),
                           workers=workers or None, progress=lambda _s, _e: stamps.append(time.perf_counter()))
    wall = time.perf_counter() - start
    assert report.ok, report.summary()
    after = (len(stamps) - 1) / (stamps[-1] - stamps[0]) if len(stamps) > 1 and stamps[-1] > stamps[0] else 0.0
    return {"wall_s": wall, "first_s": stamps[0] - start, "after_rate": after, "samples": len(report.built)}


def _whole_build_in_a_process(capture: Path, out: Path, workers: int, cache: str) -> dict:
    import json
    import subprocess
    import sys

    start = time.perf_counter()
    done = subprocess.run([sys.executable, __file__, "--whole-build", json.dumps([str(capture), str(out), workers, cache])],
                          capture_output=True, text=True, check=True)
    result = json.loads(done.stdout.strip().splitlines()[-1])
    result["process_s"] = time.perf_counter() - start  # Python and JAX start-up included
    return result


def bench_workers(capture: Path, scratch: Path, workers: list[int], caches: list[str]) -> None:
    """Whole builds of every frame of ``capture``, each in a fresh process, serial (``0``) and on
    local clusters of ``workers`` pinned process workers, with no compile cache (``off``), an
    empty one (``cold``) and the one the cold build filled (``warm``)."""
    print(f"whole builds of {len(_frames(capture))} samples, each in a fresh process (load {os.getloadavg()[0]:.1f}):")
    print(f"  {'build':22s} {'cache':5s} {'wall s':>7s} {'first s':>8s} {'samples/s after 1st':>20s}")
    for n in [0, *workers]:
        name = "serial (--no-dask)" if n == 0 else f"--workers {n}"
        folder = scratch / f"xla-{n}"
        shutil.rmtree(folder, ignore_errors=True)
        for cache in caches:
            out = scratch / f"whole-{n}-{cache}"
            r = _whole_build_in_a_process(capture, out, n, "" if cache == "off" else str(folder))
            shutil.rmtree(out, ignore_errors=True)
            print(f"  {name:22s} {cache:5s} {r['wall_s']:7.1f} {r['first_s']:8.1f} {r['after_rate']:20.2f}", flush=True)


def _frames(capture: Path) -> list:
    import json

    return json.loads((capture / "capture.json").read_text())["frames"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--capture", type=Path, default=None, help="full-size capture with frame 0 (rendered if absent)")
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--no-dask", action="store_true")
    parser.add_argument("--stages", action="store_true", help="also time each stage of a sample (wall and CPU)")
    parser.add_argument("--workers", default=None,
                        help="whole builds of every frame on these worker counts, e.g. 1,2,4 (with a serial one)")
    parser.add_argument("--caches", default="off,cold,warm", help="compile caches of the whole builds")
    parser.add_argument("--scale", type=float, default=None,
                        help="render the capture at this scale of the demo's sizes (with --frames)")
    parser.add_argument("--frames", type=int, default=1, help="frames of the rendered capture")
    parser.add_argument("--whole-build", default=None, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.whole_build:
        import json

        print(json.dumps(_whole_build(*json.loads(args.whole_build))))
        return
    scratch = Path(tempfile.mkdtemp(prefix="jaxfish_bench_build_"))
    try:
        capture = args.capture
        if capture is None or not (capture / "capture.json").is_file():
            from jaxfish import default_rig
            from jaxfish.dataset import synthesize_capture

            capture = capture or scratch / "capture"
            t = time.perf_counter()
            if args.scale is not None:
                from jaxfish.cli._demo import demo_config, demo_rig

                synthesize_capture(capture, demo_rig(args.scale), frames=args.frames, seed=0,
                                   config=demo_config(args.scale))
            else:
                synthesize_capture(capture, default_rig(), frames=args.frames, seed=0)
            print(f"rendered the full-size capture in {time.perf_counter() - t:.1f} s")
        if args.workers:
            bench_workers(capture, scratch, [int(n) for n in args.workers.split(",")], args.caches.split(","))
            return
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
        if args.stages:
            bench_stages(capture, scratch, args.repeat)
        if not args.no_dask:
            for n in (1, 2):
                rate, warm_s, peaks = bench_dask(capture, scratch, n)
                print(f"dask LocalCluster, {n} process worker(s): {rate:.2f} samples/s after warm-up "
                      f"(warm-up {warm_s:.1f} s); worker peak memory {', '.join(f'{p:.0f}' for p in peaks)} MB")
    finally:
        shutil.rmtree(scratch, ignore_errors=True)


if __name__ == "__main__":
    main()
