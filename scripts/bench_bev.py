"""Benchmark: BEV fusion of the four fisheye cameras (1280 x 966) into the 1024 x 1024 top view
(0.04 m/px), and the IPM baseline on the same grid, after compile.

Input: jaxfish's default rig looking at a flat ground with a field of 1.5 m high blocks (range
from the closed-form ray/plane intersection, far = 1000 for rays above the horizon) and a class
per pixel. The rays are the per-rig constant `jaxfish.bev.rig_rays` (computed once); the
fusion with the unprojection included is timed too.

    uv run python scripts/bench_bev.py [--repeats 5] [--size 1024]

Goal (issue 6): fusion under 100 ms after compile on the 2-core CPU.
"""

from __future__ import annotations

import argparse
import json
import time

import jax
import jax.numpy as jnp
import numpy as np

import jaxfish as jf
from jaxfish import bev

F32 = jnp.float32


def synthetic_inputs(rig, rays):
    """Range and class of every pixel: ground plane z = 0 with blocks 1.5 m high on a 4 m lattice."""
    ray, ok = (np.asarray(a) for a in rays)
    ranges, classes = [], []
    for i, calib in enumerate(rig.values()):
        r = np.asarray(calib.camera_to_vehicle.rotation_matrix, np.float64)
        t = np.asarray(calib.camera_to_vehicle.translation, np.float64)
        d = ray[i] @ r.T
        down = d[..., 2] < -1e-6
        s_ground = np.where(down, -t[2] / np.where(down, d[..., 2], -1.0), 1000.0)
        s_top = np.where(down, (1.5 - t[2]) / np.where(down, d[..., 2], -1.0), -1.0)
        top = t + s_top[..., None] * d
        on_block = (s_top > 0) & (np.mod(top[..., 0], 4.0) < 1.5) & (np.mod(top[..., 1], 4.0) < 1.5)
        rng = np.where(on_block, s_top, np.minimum(s_ground, 1000.0))
        ranges.append(np.where(ok[i], rng, 0.0))
        classes.append(np.where(on_block, 10, np.where(down, 7, 13)))
    return np.stack(ranges).astype(np.float32), np.stack(classes).astype(np.int32)


def timed(fn, repeats):
    out = fn()
    jax.block_until_ready(out)
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn())
        ts.append(time.perf_counter() - t0)
    return 1e3 * float(np.median(ts)), 1e3 * float(np.min(ts))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--size", type=int, default=1024, help="BEV size in pixels (0.04 m/px)")
    args = ap.parse_args()
    rig = {k: c.astype(F32) for k, c in jf.default_rig(dtype=F32).items()}
    cams = bev.stack_cameras([c.camera for c in rig.values()])
    poses = bev.stack_poses([c.camera_to_vehicle for c in rig.values()])
    bev_cam = jf.Orthographic(0.04, width=args.size, height=args.size, dtype=F32)
    bev_pose = jf.Pose(np.array([[0.0, -1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, -1.0]]), np.array([1.3, 0.0, 50.0]), dtype=F32)
    t0 = time.perf_counter()
    rays = jax.block_until_ready(jax.jit(bev.rig_rays)(cams))
    t_rays = time.perf_counter() - t0
    rng, sem = synthetic_inputs(rig, rays)
    rng, sem = jnp.asarray(rng), jnp.asarray(sem)
    fuse = jax.jit(lambda c, p, r, s, b, bp, ry: bev.fuse_cameras(c, p, r, s, b, bp, rays=ry))
    fuse_unproject = jax.jit(lambda c, p, r, s, b, bp: bev.fuse_cameras(c, p, r, s, b, bp))
    ipm = jax.jit(lambda c, p, s, b, bp: bev.ipm_semantics(c, p, s, b, bp))
    t0 = time.perf_counter()
    jax.block_until_ready(fuse(cams, poses, rng, sem, bev_cam, bev_pose, rays))
    compile_s = time.perf_counter() - t0
    med, best = timed(lambda: fuse(cams, poses, rng, sem, bev_cam, bev_pose, rays), args.repeats)
    med_u, best_u = timed(lambda: fuse_unproject(cams, poses, rng, sem, bev_cam, bev_pose), max(1, args.repeats // 2))
    med_i, best_i = timed(lambda: ipm(cams, poses, sem, bev_cam, bev_pose), args.repeats)
    res = fuse(cams, poses, rng, sem, bev_cam, bev_pose, rays)
    report = {
        "cameras": f"4 x {cams.width}x{cams.height}", "bev": f"{args.size}x{args.size} @ 0.04 m/px",
        "rig_rays_s_incl_compile": round(t_rays, 2), "fusion_compile_s": round(compile_s, 2),
        "fusion_ms_median": round(med, 1), "fusion_ms_min": round(best, 1),
        "fusion_with_unprojection_ms_median": round(med_u, 1), "fusion_with_unprojection_ms_min": round(best_u, 1),
        "ipm_ms_median": round(med_i, 1), "ipm_ms_min": round(best_i, 1),
        "observed_cells": float(np.mean(np.asarray(res.observed))), "goal_fusion_ms": 100,
    }
    print(json.dumps(report, indent=2))


if __name__ == "__main__":
    main()
