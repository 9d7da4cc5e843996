"""A small capture holding only what the BEV needs (header, calibrations, sensors, the BEV view at
t-1 and t with its height map, ego and actors): shared by the io and CLI BEV tests."""

from __future__ import annotations

from pathlib import Path

import jax.numpy as jnp
import numpy as np

import jaxfish as jf
from jaxfish.io import write_capture_header, write_frame
from jaxfish.scene import (
    RADAR_DTYPE,
    SEMANTIC_LIDAR_DTYPE,
    CaptureConfig,
    bev_camera,
    generate_street,
    sensor_mounts,
    simulate_gnss,
    simulate_imu,
    simulate_view,
)

BEV_SIZE = 64
BEV_MPP = 0.5
SEED = 3


def write_bev_capture(root: Path, *, frames: int = 1) -> Path:
    """Write the capture under ``root`` (the fisheye rig's calibrations, no cube faces)."""
    rig = {k: v.resize(64, 48).astype(jnp.float32) for k, v in jf.default_rig().items()}
    config = CaptureConfig(face_size=16, bev_size=BEV_SIZE, bev_metres_per_pixel=BEV_MPP)
    mounts = sensor_mounts(rig, config)
    write_capture_header(root, rig, config, mounts, seed=SEED)
    cam = bev_camera(config)
    for k in range(frames):
        frame = generate_street(SEED, frame=k, rig=rig)
        view = simulate_view(frame, cam, mounts.bev_camera_to_vehicle, config)
        write_frame(root, frame, cameras={}, views={"bev": view}, lidar=np.zeros((0, 4), np.float32),
                    semantic_lidar=np.zeros(0, SEMANTIC_LIDAR_DTYPE), radar=np.zeros(0, RADAR_DTYPE),
                    imu=simulate_imu(frame), gnss=simulate_gnss(frame))
    return root
