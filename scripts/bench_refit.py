"""Benchmark: refit on 2,000 board correspondences and WoodScape -> KB conversion (2-core CPU).

Goal (issue 7): a refit on 2,000 correspondences converges in under 1 s after compile.
Run: ``uv run python scripts/bench_refit.py``. Prints compile time, run time (best of 5
repeats: the machine is shared), Levenberg-Marquardt iterations and the fit's RMS.
"""

from __future__ import annotations

import time

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import jaxfish as jf  # noqa: E402
from jaxfish.refit import Correspondences, convert_camera, refit, rotation_from_vector  # noqa: E402


def board_scene(noise_px: float = 0.3, n_views: int = 5, board: int = 20):
    cam = jf.WoodScapeFisheye([336.0, -30.5, 47.0, -7.0], width=1280, height=966, cx_offset=3.5, cy_offset=-2.75,
                              aspect_ratio=1.0015)
    g = np.stack(np.meshgrid(np.arange(board), np.arange(board)), -1).reshape(-1, 2) * 0.06
    g = np.c_[g - g.mean(0), np.zeros(len(g))]
    rng = np.random.default_rng(0)
    omegas = rng.normal(size=(n_views, 3)) * 0.4
    ts = np.c_[rng.uniform(-0.5, 0.5, (n_views, 2)), rng.uniform(0.35, 0.6, n_views)]
    rot = np.asarray(rotation_from_vector(jnp.asarray(omegas)))
    pts = np.tile(g, (n_views, 1))
    view = np.repeat(np.arange(n_views), len(g))
    pc = np.einsum("nij,nj->ni", rot[view], pts) + ts[view]
    uv, valid = cam.project(jnp.asarray(pc))
    valid = np.asarray(valid & cam.contains(uv))
    pixels = np.asarray(uv) + rng.normal(size=(len(pts), 2)) * noise_px
    return Correspondences(pts, pixels, view, valid.astype(np.float64)), cam


def timed(fn, repeats: int = 7):
    t0 = time.perf_counter()
    out = jax.block_until_ready(fn())
    first = time.perf_counter() - t0
    runs = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = jax.block_until_ready(fn())
        runs.append(time.perf_counter() - t0)
    return out, first, float(np.min(runs))


def main() -> None:
    corr, truth = board_scene()
    start = jf.WoodScapeFisheye([336.0 * 1.05, 0.0, 0.0, 0.0], width=1280, height=966)
    n = int(np.sum(np.asarray(corr.weight) > 0))
    res, first, run = timed(lambda: refit(start, corr))
    print(f"refit radial_poly + 5 poses, {n} correspondences (of {corr.size}): first call {first:.2f} s "
          f"(compile + run), then {run * 1e3:.0f} ms per refit; {int(res.num_steps)} LM steps, "
          f"converged={bool(res.converged)}, rms {float(res.rms_px):.3f} px")
    res, first, run = timed(lambda: refit(res.camera, corr, poses=res.poses, fit_pose=False))
    print(f"refit intrinsics only (poses held): first {first:.2f} s, then {run * 1e3:.0f} ms; "
          f"{int(res.num_steps)} LM steps")
    conv, first, run = timed(lambda: convert_camera(truth, "kb"), repeats=3)
    print(f"convert radial_poly -> kannala_brandt ({int(conv.num_samples)} rays): first {first:.2f} s, then "
          f"{run * 1e3:.0f} ms; {int(conv.num_steps)} LM steps; max {float(conv.max_px):.3f} px, "
          f"rms {float(conv.rms_px):.3f} px")


if __name__ == "__main__":
    main()
