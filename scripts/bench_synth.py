"""Benchmark: one full capture frame of the embedded scene (not a test).

4 cameras x 5 faces at t-1 and t (default 768-px faces), the BEV top view (1024 px) at t-1 and t,
and one lidar sweep; reports wall time and rays per second. Goal (issue 4): under 60 s on the
2-core CPU. Optional: the DVS sub-frames and the front camera, timed separately.

    uv run python scripts/bench_synth.py [--face-size 768] [--dvs] [--front]
"""

from __future__ import annotations

import argparse
import time

import jax.numpy as jnp
import numpy as np

import jaxfish as jf
from jaxfish.scene import (
    CaptureConfig,
    bev_camera,
    front_camera,
    generate_street,
    render_camera,
    render_cube_faces,
    sensor_mounts,
    simulate_camera,
    simulate_lidar,
)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--face-size", type=int, default=768)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--dvs", action="store_true", help="also time the DVS sub-frames of one camera")
    ap.add_argument("--front", action="store_true", help="also time the front perspective camera")
    args = ap.parse_args()
    rig = {k: v.astype(jnp.float32) for k, v in jf.default_rig().items()}
    config = CaptureConfig(face_size=args.face_size)
    frame = generate_street(args.seed, rig=rig)
    mounts = sensor_mounts(rig, config)
    n_prims = int(np.sum(np.asarray(frame.scene.box_active))) + int(np.sum(np.asarray(frame.scene.capsule_active)))
    print(f"scene: {n_prims} primitives ({frame.scene.box_center.shape[0]} box + "
          f"{frame.scene.capsule_center.shape[0]} capsule slots), {len(frame.actors)} actors")

    t0 = time.perf_counter()  # warm-up: compiles the caster (shared by every image size)
    render_cube_faces(frame, rig["FV"], args.face_size, faces=("front",))["front"].rgb.block_until_ready()
    print(f"warm-up (compile): {time.perf_counter() - t0:.1f} s")

    rays = 0
    t0 = time.perf_counter()
    for calib in rig.values():
        for tm in (0.0, 1.0):
            for b in render_cube_faces(frame, calib, args.face_size, time=tm, faces=config.faces).values():
                b.rgb.block_until_ready()
                rays += b.rgb.shape[0] * b.rgb.shape[1]
    t_faces = time.perf_counter() - t0
    t1 = time.perf_counter()
    bev = bev_camera(config)
    for tm in (0.0, 1.0):
        render_camera(frame, bev, mounts.bev_camera_to_vehicle, time=tm).rgb.block_until_ready()
        rays += bev.width * bev.height
    t_bev = time.perf_counter() - t1
    t1 = time.perf_counter()
    lidar, _ = simulate_lidar(frame, mounts.lidar_location, config)
    rays += config.lidar_channels * config.lidar_points_per_channel
    t_lidar = time.perf_counter() - t1
    total = time.perf_counter() - t0
    print(f"faces (4 cams x 5 faces x 2 instants, {args.face_size} px): {t_faces:.1f} s")
    print(f"BEV ({bev.width} px, 2 instants): {t_bev:.1f} s; lidar ({lidar.shape[0]} points): {t_lidar:.2f} s")
    print(f"full capture frame: {total:.1f} s for {rays / 1e6:.1f} M rays -> {rays / total / 1e6:.2f} M rays/s "
          f"(goal: < 60 s)")
    if args.front:
        cam = front_camera(config)
        t1 = time.perf_counter()
        render_camera(frame, cam, mounts.front_camera_to_vehicle).rgb.block_until_ready()
        print(f"front camera {cam.width}x{cam.height}: {time.perf_counter() - t1:.1f} s")
    if args.dvs:
        t1 = time.perf_counter()
        simulate_camera(frame, rig["RV"], config)  # compiles the colour-only render of the sub-frames
        t_first = time.perf_counter() - t1
        t1 = time.perf_counter()
        cap = simulate_camera(frame, rig["FV"], config)
        n = sum(e.size for e in cap.dvs.values())
        print(f"one camera with DVS ({config.dvs_substeps} sub-steps, {n} events): {time.perf_counter() - t1:.1f} s "
              f"(the first camera, compilation included: {t_first:.1f} s)")


if __name__ == "__main__":
    main()
