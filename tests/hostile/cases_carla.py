"""Hostile inputs of the CARLA glue (`jaxfish.carla`): buffers, versions, presets and frames that a
broken server, client or caller hands it; each raises `jaxfish.carla.CarlaCaptureError` naming the
sensor, file or field, and a rejected frame leaves nothing written."""

from __future__ import annotations

import math
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from tests.hostile.corpus import Case


def _frame(velocity=(1.0, 0.0, 0.0)):
    from jaxfish.carla import carla_street_frame
    from jaxfish.scene import Actor, EgoMotion

    ego = Actor(id=7, type_id="vehicle.lincoln.mkz_2017", category="ego", semantic_tag=10, object_index=-1,
                bbox_location=(0.0, 0.0, 0.8), bbox_extent=(2.4, 1.0, 0.8), location_prev=(0.0, 0.0, 0.0),
                rotation_prev=(0.0, 0.0, 0.0), location=(0.5, 0.0, 0.0), rotation=(0.0, 0.0, 0.0), velocity=velocity,
                angular_velocity=(0.0, 0.0, 0.0))
    return carla_street_frame(3, 1.0, [ego], EgoMotion(velocity=velocity, acceleration=(0.0, 0.0, 0.0),
                                                       angular_velocity=(0.0, 0.0, 0.0)))


def _records(velocity):
    from jaxfish.carla import carla_frame_records

    return carla_frame_records(_frame(velocity))


def _sensors(**bad):
    from jaxfish.carla import carla_frame_sensors
    from jaxfish.scene import RADAR_DTYPE, SEMANTIC_LIDAR_DTYPE

    good = {"lidar": np.zeros((2, 4), np.float32), "semantic_lidar": np.zeros(1, SEMANTIC_LIDAR_DTYPE),
            "radar": np.zeros(1, RADAR_DTYPE), "imu": {"compass": 0.5}, "gnss": {"latitude": 0.0}}
    return carla_frame_sensors(_frame(), **{**good, **bad})


def _write_bad_view(tmp: Path) -> None:
    import jaxfish as jf
    from jaxfish.carla import CarlaImages, write_carla_frame
    from jaxfish.io import DVS_EVENT_DTYPE, write_capture_header
    from jaxfish.scene import RADAR_DTYPE, SEMANTIC_LIDAR_DTYPE, CaptureConfig, sensor_mounts

    config = CaptureConfig(face_size=4, bev_size=4, front_width=4, front_height=4)
    rig = {"FV": jf.default_rig()["FV"].resize(16, 12)}
    write_capture_header(tmp / "cap", rig, config, sensor_mounts(rig, config), seed=0, source="carla")
    ok = CarlaImages(*(np.zeros((4, 4, 4), np.uint8),) * 3)
    write_carla_frame(tmp / "cap", _frame(), faces={"FV": {"front": (ok, ok, np.zeros(0, DVS_EVENT_DTYPE))}},
                      views={"bev": (ok, CarlaImages(ok.rgb, ok.depth, np.zeros((4, 4, 3), np.uint8)), np.zeros((4, 4)))},
                      lidar=np.zeros((0, 4)), semantic_lidar=np.zeros(0, SEMANTIC_LIDAR_DTYPE),
                      radar=np.zeros(0, RADAR_DTYPE), imu={}, gnss={})


def _source(frames):
    import jaxfish as jf
    from jaxfish.carla import CarlaSource
    from jaxfish.scene import CaptureConfig, sensor_mounts

    rig = {"FV": jf.default_rig()["FV"].resize(16, 12)}
    config = CaptureConfig(face_size=4, bev_size=4, front_width=4, front_height=4)
    return CarlaSource(rig, config=config, bev_camera_to_vehicle=sensor_mounts(rig, config).bev_camera_to_vehicle,
                       carla_version="0.9.15", frames=frames, next_frame=lambda k: None)


def _frame_with_bad_bev_height(tmp: Path):
    from jaxfish.carla import CarlaImages, carla_frame
    from jaxfish.io import DVS_EVENT_DTYPE

    ok = CarlaImages(*(np.zeros((4, 4, 4), np.uint8),) * 3)
    return carla_frame(_frame(), tag_table="0.9.10", faces={"FV": {"front": (ok, ok, np.zeros(0, DVS_EVENT_DTYPE))}},
                       bev=(ok, ok, np.zeros((4, 5))), lidar=np.zeros((0, 4)), semantic_lidar=np.zeros(0),
                       radar=np.zeros(0), imu={}, gnss={})


def _call(name: str, *args, **kwargs):
    def call(tmp: Path):
        import jaxfish.carla

        return getattr(jaxfish.carla, name)(*args, **kwargs)
    return call


def _bev_fov(altitude: float):
    def call(tmp: Path):
        from jaxfish.carla import bev_pinhole_fov_deg
        from jaxfish.scene import CaptureConfig

        return bev_pinhole_fov_deg(CaptureConfig(), altitude)
    return call


CASES = [
    Case("carla-dvs-buffer-not-whole-events", call=_call("dvs_to_events", b"\0" * 14, "FV/left/dvs"),
         says=("FV/left/dvs", "13-byte")),
    Case("carla-dvs-event-outside-the-image",
         call=_call("dvs_to_events", SimpleNamespace(raw_data=np.ones(1, [("x", "<u2"), ("y", "<u2"), ("t", "<i8"),
                                                                            ("pol", "?")]).tobytes(), width=1, height=1)),
         says=("outside the 1x1 image",)),
    Case("carla-image-buffer-too-short",
         call=_call("image_to_bgra", SimpleNamespace(raw_data=bytes(10), width=5, height=6), "FV/front/rgb"),
         says=("FV/front/rgb", "5x6")),
    Case("carla-image-without-a-buffer", call=_call("image_to_bgra", SimpleNamespace(raw_data=None, width=1, height=1)),
         says=("no raw buffer",)),
    Case("carla-lidar-buffer-not-whole-points", call=_call("lidar_to_points", b"\0" * 17), says=("lidar", "whole number")),
    Case("carla-version-garbage", call=_call("parse_carla_version", "latest"), says=("'latest'", "0.9.N")),
    Case("carla-version-too-old", call=_call("parse_carla_version", "0.9.9"), says=("not supported",)),
    Case("carla-version-ue5-branch", call=_call("parse_carla_version", "0.10.0"), says=("not supported",)),
    Case("carla-weather-unknown", call=_call("validate_weather", ["ClearNon"]), says=("did you mean 'ClearNoon'",)),
    Case("carla-weather-none", call=_call("validate_weather", []), says=("no weather",)),
    Case("carla-bev-altitude-zero", call=_bev_fov(0.0), says=("BEV altitude",)),
    Case("carla-bev-altitude-nan", call=_bev_fov(math.nan), says=("BEV altitude",)),
    Case("carla-bev-altitude-beyond-far-depth", call=_bev_fov(1000.0), says=("BEV altitude",)),
    Case("carla-tag-table-unknown", call=_call("actor_semantic_tag", "ego", "0.9.12"), says=("tag table '0.9.12'",)),
    Case("carla-frame-ego-velocity-nan", call=lambda tmp: _records((math.nan, 0.0, 0.0)),
         says=("frame 3 actors.json",)),
    Case("carla-frame-lidar-infinite", call=lambda tmp: _sensors(lidar=np.full((1, 4), np.inf, np.float32)),
         says=("frame 3: lidar", "not finite")),
    Case("carla-frame-lidar-three-columns", call=lambda tmp: _sensors(lidar=np.zeros((2, 3), np.float32)),
         says=("frame 3: lidar must be (N, 4)",)),
    Case("carla-frame-gnss-nan", call=lambda tmp: _sensors(gnss={"latitude": math.nan}), says=("frame 3 gnss.json",)),
    Case("carla-source-no-frames", call=lambda tmp: _source(0), says=("frames must be a positive integer",)),
    Case("carla-source-frame-count-not-a-number", call=lambda tmp: _source("many"), says=("'many'",)),
    Case("carla-frame-bev-height-of-another-size", call=_frame_with_bad_bev_height,
         says=("bev: height map (4, 5) does not match the image (4, 4)",)),
    Case("carla-writer-view-semantic-three-channels", call=_write_bad_view, says=("bev: semantic_curr", "BGRA"),
         absent=("{tmp}/cap/frames/000003",)),
]
