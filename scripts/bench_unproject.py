"""Benchmark: full-frame pixel -> ray table vs the WoodScape reference (np.roots per pixel).

Run: ``uv run python scripts/bench_unproject.py [--calibration FV.json] [--sample 2000]``

In one process: times the reference method on a random sample of pixels and extrapolates to the
full frame, then times jaxfish's jitted ``WoodScapeFisheye.unproject`` of the whole frame (float32
and float64; compile time reported separately) and prints the ratio, the largest angle from the
reference rays on the sampled pixels, and the full frame's round trip (``project`` of the rays,
pixels). Goals: >= 5000x in float32 and >= 1000x in float64 after compile on a 2-core CPU, the
float64 round trip within 1e-9 px. The load average is printed before and after: on a shared
machine, compare ratios measured in the same process.
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import jax
import numpy as np


def reference_unproject_pixel(u: float, v: float, k: np.ndarray, cx: float, cy: float, aspect: float) -> np.ndarray:
    """WoodScape projection.py's method for one pixel: np.roots, smallest real root."""
    x, y = u - cx, (v - cy) / aspect
    rho = np.hypot(x, y)
    roots = np.roots([k[3], k[2], k[1], k[0], -rho])
    real = roots[np.abs(roots.imag) < 1e-9].real
    real = real[(real >= 0) & (real < np.pi)]
    theta = float(real.min()) if real.size else 0.0
    if rho == 0:
        return np.array([0.0, 0.0, 1.0])
    return np.array([np.sin(theta) * x / rho, np.sin(theta) * y / rho, np.cos(theta)])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    default = Path(__file__).resolve().parents[1].parent / "shared/calibration/synwoodscape/FV.json"
    parser.add_argument("--calibration", type=Path, default=default if default.exists() else None)
    parser.add_argument("--sample", type=int, default=2000, help="pixels timed with the reference method")
    parser.add_argument("--repeats", type=int, default=30)
    args = parser.parse_args()
    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp

    import jaxfish as jf

    calib = jf.load_calibration(args.calibration) if args.calibration else jf.default_rig()["FV"]
    cam = calib.camera
    w, h = cam.width, cam.height
    k = np.asarray(cam.k, dtype=np.float64)
    cx, cy = (float(c) for c in np.asarray(cam.principal_point))
    aspect = float(cam.aspect_ratio)
    print(f"calibration: {args.calibration or 'jaxfish default rig FV'} ({w}x{h}); devices: {jax.devices()}")
    print(f"load average: {' '.join(f'{x:.2f}' for x in os.getloadavg())}")

    rng = np.random.default_rng(0)
    sample = np.stack([rng.uniform(0, w - 1, args.sample), rng.uniform(0, h - 1, args.sample)], -1)
    t0 = time.perf_counter()
    ref = np.stack([reference_unproject_pixel(u, v, k, cx, cy, aspect) for u, v in sample])
    t_ref_px = (time.perf_counter() - t0) / args.sample
    t_ref_frame = t_ref_px * w * h
    print(f"reference np.roots: {t_ref_px * 1e6:.1f} us/pixel -> {t_ref_frame:.1f} s per frame (extrapolated)")

    fn = jax.jit(lambda c, g: c.unproject(g))
    rows = []
    for dtype in (jnp.float32, jnp.float64):
        c = cam.astype(dtype)
        grid = c.pixel_grid(dtype)
        t0 = time.perf_counter()
        jax.block_until_ready(fn(c, grid))
        compile_s = time.perf_counter() - t0
        times = []
        for _ in range(args.repeats):
            t0 = time.perf_counter()
            jax.block_until_ready(fn(c, grid))
            times.append(time.perf_counter() - t0)
        rays, valid = fn(c, grid)
        got = np.asarray(jax.jit(lambda c, q: c.unproject(q))(c, jnp.asarray(sample, dtype))[0], dtype=np.float64)
        err = np.arctan2(np.linalg.norm(np.cross(got, ref), axis=-1), np.sum(got * ref, -1)).max()
        back, _ = jax.jit(lambda c, r: c.project(r))(c, rays)
        trip = float(jnp.max(jnp.where(valid[..., None], jnp.abs(back - grid), 0.0)))
        best, med = min(times), float(np.median(times))
        rows.append((jnp.dtype(dtype).name, compile_s, best, med, t_ref_frame / med, t_ref_frame / best, err, trip,
                     float(np.mean(valid))))
    print(f"\n{'dtype':8} {'compile s':>10} {'best ms':>9} {'median ms':>10} {'speed-up':>10} {'best':>8} "
          f"{'max angle err rad':>18} {'round trip px':>14} {'valid':>6}")
    for name, comp, best, med, ratio, ratio_best, err, trip, frac in rows:
        print(f"{name:8} {comp:10.2f} {best * 1e3:9.2f} {med * 1e3:10.2f} {ratio:9.0f}x {ratio_best:7.0f}x "
              f"{err:18.2e} {trip:14.2e} {frac:6.3f}")
    print("\nspeed-up = reference full frame (extrapolated) / jaxfish median full frame, same process; best: the same over")
    print(f"the fastest repeat. load average: {' '.join(f'{x:.2f}' for x in os.getloadavg())}")


if __name__ == "__main__":
    main()
