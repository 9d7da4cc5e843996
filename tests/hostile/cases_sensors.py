"""Sensor mounts and records that cannot be put in the vehicle frame."""

from __future__ import annotations

from pathlib import Path

from .corpus import Case, edit_json


def _mount(location):
    def call(tmp: Path):
        from jaxfish.dataset._sources import sensor_mount_matrices

        return sensor_mount_matrices({"lidar": {"carla_transform": {"location": location, "rotation": [0, 0, 0]}}},
                                     str(tmp / "capture" / "sensors.json"))
    return call


def _no_lidar_mount(tmp: Path) -> None:
    edit_json(tmp / "capture" / "sensors.json", lambda s: s["lidar"].pop("carla_transform"))


def _sensor_truth_without_mount(tmp: Path):
    import numpy as np

    from jaxfish.pipeline import SensorRecords, sensor_truth

    ego = {"timestamp_s": 1.0, "timestamp_prev_s": 0.9, "transform": {"location": [0, 0, 0], "rotation": [0, 0, 0]},
           "velocity": [0, 0, 0], "acceleration": [0, 0, 0], "angular_velocity": [0, 0, 0]}
    return sensor_truth(SensorRecords(ego=ego, lidar=np.ones((2, 4), np.float32), semantic_lidar=np.zeros(0),
                                      radar=np.zeros(0), imu={}, gnss={}))


CASES = [
    Case("sensors-mount-location-not-numbers", call=_mount([1.0, "left", 2.0]),
         says=("sensors.json", "lidar.carla_transform")),
    Case("sensors-mount-location-nan", call=_mount([1.0, float("nan"), 2.0]),
         says=("sensors.json", "lidar.carla_transform", "finite")),
    Case("sensors-mount-location-two-numbers", call=_mount([1.0, 2.0]), says=("lidar.carla_transform",)),
    Case("sensors-points-without-mount", call=_sensor_truth_without_mount, raises=ValueError, says=("lidar mount",)),
    Case("sensors-build-without-lidar-mount", "build {capture} {tmp}/out --frames 0", setup=_no_lidar_mount, exit=1,
         says=("lidar mount",)),
]
