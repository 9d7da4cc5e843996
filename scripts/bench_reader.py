"""Benchmark: `jaxfish.dataset.open` reading samples, single process.

Times ``ds[i]`` over every sample of a dataset (``--repeat`` passes, after one warm-up read that
builds the camera models) for three selections: every field of every camera, RGB + semantics of
the four fisheyes, RGB + semantics of every camera (BEV included). Prints samples/s (the median
pass), the process's CPU time per sample (its inverse is the rate of one free core,
all threads), MB of camera arrays per sample and the 1-minute load average.

    uv run jaxfish synth --out CAP --frames 2 --texture    # a full-size capture
    uv run jaxfish build CAP DATASET                        # its dataset (or any dataset)
    uv run python scripts/bench_reader.py DATASET

Goal: reading is never the bottleneck of a 2-core trainer, i.e. ten or more samples a second for
RGB + semantics of the four fisheyes in one process. Current figures: docs/performance.md.
"""

from __future__ import annotations

import argparse
import os
import statistics
import time


def _rate(ds, repeat: int) -> tuple[float, float, float]:
    """(samples/s wall, CPU seconds of this process per sample, MB of camera arrays per sample);
    medians over ``repeat`` passes."""
    ds[0]  # warm-up: camera models, file cache
    rates, cpu = [], []
    nbytes = 0
    for _ in range(repeat):
        start, start_cpu = time.perf_counter(), time.process_time()
        nbytes = 0
        for i in range(len(ds)):
            s = ds[i]
            nbytes += sum(v.nbytes for c in s.cameras.values() for v in vars(c).values() if hasattr(v, "nbytes"))
        rates.append(len(ds) / (time.perf_counter() - start))
        cpu.append((time.process_time() - start_cpu) / len(ds))
    return statistics.median(rates), statistics.median(cpu), nbytes / len(ds) / 1e6


def main(argv=None) -> None:
    from jaxfish.dataset import FISHEYE_CAMERAS, open

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("dataset")
    p.add_argument("--repeat", type=int, default=5)
    args = p.parse_args(argv)
    probe = open(args.dataset, fields=set())
    print(f"{args.dataset}: {len(probe)} samples, cameras {', '.join(probe.cameras)}, layout {probe.layout}")
    rows = [("all fields, all cameras", open(args.dataset)),
            ("RGB + semantics, 4 fisheyes", open(args.dataset, fields={"rgb", "semantics"},
                                                  cameras=[c for c in FISHEYE_CAMERAS if c in probe.cameras])),
            ("RGB + semantics, all cameras", open(args.dataset, fields={"rgb", "semantics"}))]
    print("| selection | samples/s | CPU s per sample (1 / it: the rate on a free core) | MB of camera arrays per sample |")
    print("|---|---|---|---|")
    for name, ds in rows:
        rate, cpu, mb = _rate(ds, args.repeat)
        print(f"| {name} | {rate:.1f} | {cpu:.3f} ({1 / cpu:.1f} samples/s) | {mb:.1f} |")
    print(f"load average (1 min): {os.getloadavg()[0]:.2f}, {os.cpu_count()} cores")


if __name__ == "__main__":
    main()
