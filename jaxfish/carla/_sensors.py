"""The sensors of a capture and their blueprint attributes.

Fixed exposure on every camera (so that cube faces have no brightness seams), one lidar rotation per
tick, noise-free IMU and GNSS; attributes a release lacks are skipped.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping

from ..calibration import Calibration
from ..scene import CaptureConfig, SensorMounts
from ._mounts import CarlaMount, bev_pinhole_fov_deg, cube_face_mounts, sensor_carla_mounts, with_bev_altitude
from ._version import CarlaCaptureError, has_instance_camera

CAMERA_BLUEPRINTS: dict[str, str] = {
    "rgb": "sensor.camera.rgb",
    "depth": "sensor.camera.depth",
    "semantic": "sensor.camera.semantic_segmentation",
    "instance": "sensor.camera.instance_segmentation",
    "dvs": "sensor.camera.dvs",
}
"""Blueprint ids of CARLA's camera sensors by image kind (``instance`` exists from 0.9.14 on)."""
SENSOR_BLUEPRINTS: dict[str, str] = {
    "lidar": "sensor.lidar.ray_cast",
    "semantic_lidar": "sensor.lidar.ray_cast_semantic",
    "radar": "sensor.other.radar",
    "imu": "sensor.other.imu",
    "gnss": "sensor.other.gnss",
}
"""Blueprint ids of the other sensors."""


@dataclasses.dataclass(frozen=True)
class CarlaExposure:
    """Fixed (manual) exposure shared by every RGB and DVS camera: `shutter_speed` (1/s), `iso`,
    `fstop`, `exposure_compensation` (EV). Defaults are CARLA's own camera defaults."""

    shutter_speed: float = 200.0
    iso: float = 100.0
    fstop: float = 1.4
    exposure_compensation: float = 0.0

    def attributes(self) -> dict[str, str]:
        """Blueprint attributes that fix the exposure and switch off per-camera effects (motion blur,
        lens flare, bloom, chromatic aberration) so that cube faces meet without seams."""
        return {
            "exposure_mode": "manual",
            "shutter_speed": _num(self.shutter_speed),
            "iso": _num(self.iso),
            "fstop": _num(self.fstop),
            "exposure_compensation": _num(self.exposure_compensation),
            "motion_blur_intensity": "0.0",
            "lens_flare_intensity": "0.0",
            "bloom_intensity": "0.0",
            "chromatic_aberration_intensity": "0.0",
        }


def _num(x: float) -> str:
    return repr(float(x))


def camera_attributes(
    kind: str,
    width: int,
    height: int,
    *,
    fov_deg: float = 90.0,
    sensor_tick_s: float = 0.0,
    exposure: CarlaExposure | None = None,
    config: CaptureConfig | None = None,
) -> dict[str, str]:
    """Blueprint attributes of a camera of ``kind`` (``rgb``, ``depth``, ``semantic``, ``instance``,
    ``dvs``): image size, horizontal fov, ``sensor_tick`` (0: every simulation tick, which in
    synchronous mode is every ``fixed_delta_seconds``; a tick equal to the step can skip ticks through
    float rounding) and, for RGB and DVS, the fixed
    `CarlaExposure`; DVS adds `CaptureConfig`'s contrast thresholds (no noise, no refractory period)."""
    if kind not in CAMERA_BLUEPRINTS:
        raise CarlaCaptureError(f"camera kind {kind!r} is unknown; expected one of {tuple(CAMERA_BLUEPRINTS)}")
    if int(width) <= 0 or int(height) <= 0:
        raise CarlaCaptureError(f"{kind} camera: image size must be positive, got {width}x{height}")
    attrs = {"image_size_x": str(int(width)), "image_size_y": str(int(height)), "fov": _num(fov_deg),
             "sensor_tick": _num(sensor_tick_s)}
    if kind in ("rgb", "dvs"):
        attrs.update((exposure or CarlaExposure()).attributes())
    if kind == "dvs":
        config = config or CaptureConfig()
        attrs.update({
            "positive_threshold": _num(config.dvs_threshold), "negative_threshold": _num(config.dvs_threshold),
            "sigma_positive_threshold": "0.0", "sigma_negative_threshold": "0.0",
            "refractory_period_ns": "0", "use_log": "true", "log_eps": _num(config.dvs_log_eps),
        })
    return attrs


def lidar_attributes(config: CaptureConfig, *, dt_s: float = 0.1, semantic: bool = False) -> dict[str, str]:
    """Ray-cast (or semantic) lidar attributes: one full rotation per tick (``rotation_frequency =
    1 / dt_s``), ``points_per_second = channels · points_per_channel / dt_s``, `CaptureConfig`'s
    fov and range; the plain lidar has the capture's attenuation and no drop-off or noise."""
    attrs = {
        "channels": str(config.lidar_channels), "range": _num(config.lidar_range_m),
        "points_per_second": str(int(round(config.lidar_channels * config.lidar_points_per_channel / dt_s))),
        "rotation_frequency": _num(1.0 / dt_s), "upper_fov": _num(config.lidar_upper_fov_deg),
        "lower_fov": _num(config.lidar_lower_fov_deg), "horizontal_fov": "360.0", "sensor_tick": "0.0",
    }
    if not semantic:
        from ..scene import LIDAR_ATTENUATION_PER_M

        attrs.update({"atmosphere_attenuation_rate": _num(LIDAR_ATTENUATION_PER_M), "dropoff_general_rate": "0.0",
                      "dropoff_intensity_limit": "0.0", "dropoff_zero_intensity": "0.0", "noise_stddev": "0.0"})
    return attrs


def radar_attributes(config: CaptureConfig, *, dt_s: float = 0.1) -> dict[str, str]:
    """Radar attributes: `CaptureConfig`'s fov and range, ``radar_points`` detections per tick."""
    return {"horizontal_fov": _num(config.radar_horizontal_fov_deg), "vertical_fov": _num(config.radar_vertical_fov_deg),
            "range": _num(config.radar_range_m), "points_per_second": str(int(round(config.radar_points / dt_s))),
            "sensor_tick": "0.0"}


def imu_attributes() -> dict[str, str]:
    """IMU attributes: one reading per tick, no noise and no bias."""
    attrs = {"sensor_tick": "0.0"}
    for axis in "xyz":
        attrs[f"noise_accel_stddev_{axis}"] = "0.0"
        attrs[f"noise_gyro_stddev_{axis}"] = "0.0"
        attrs[f"noise_gyro_bias_{axis}"] = "0.0"
    return attrs


def gnss_attributes() -> dict[str, str]:
    """GNSS attributes: one fix per tick, no noise and no bias."""
    attrs = {"sensor_tick": "0.0"}
    for q in ("lat", "lon", "alt"):
        attrs[f"noise_{q}_stddev"] = "0.0"
        attrs[f"noise_{q}_bias"] = "0.0"
    return attrs


def set_blueprint_attributes(blueprint, attributes: Mapping[str, str]) -> tuple[str, ...]:
    """Set every attribute the blueprint has; return the names it does not have (older releases
    lack some, e.g. ``lens_flare_intensity`` or the lidar drop-off settings), in order."""
    missing = []
    for key, value in attributes.items():
        if blueprint.has_attribute(key):
            blueprint.set_attribute(key, str(value))
        else:
            missing.append(key)
    return tuple(missing)


@dataclasses.dataclass(frozen=True)
class SensorSpec:
    """One sensor to spawn: `key` (``("camera", CAM, face, kind)``, ``("view", name, kind)`` or
    ``(sensor,)``), CARLA `blueprint` id, blueprint `attributes` and `mount` on the ego actor."""

    key: tuple[str, ...]
    blueprint: str
    attributes: dict[str, str]
    mount: CarlaMount


def capture_sensor_specs(
    rig: Mapping[str, Calibration],
    config: CaptureConfig,
    mounts: SensorMounts,
    *,
    carla_version: str,
    bev_altitude_m: float = 500.0,
    dt_s: float = 0.1,
    exposure: CarlaExposure | None = None,
) -> list[SensorSpec]:
    """Every sensor of a capture: per fisheye camera and cube face an RGB, depth, semantic,
    (0.9.14+) instance and DVS camera; the BEV (pinhole from ``bev_altitude_m``, `bev_pinhole_fov_deg`)
    and front cameras (RGB, depth, semantic, instance); lidar, semantic lidar, radar, IMU, GNSS.
    ``mounts`` are `jaxfish.scene.sensor_mounts` (the BEV is raised here)."""
    kinds = ("rgb", "depth", "semantic") + (("instance",) if has_instance_camera(carla_version) else ())
    specs = []
    for cam, faces in cube_face_mounts(rig, config.faces).items():
        for face, mount in faces.items():
            for kind in kinds + ("dvs",):
                attrs = camera_attributes(kind, config.face_size, config.face_size, fov_deg=90.0,
                                          exposure=exposure, config=config)
                specs.append(SensorSpec(("camera", cam, face, kind), CAMERA_BLUEPRINTS[kind], attrs, mount))
    other = sensor_carla_mounts(with_bev_altitude(mounts, bev_altitude_m=bev_altitude_m))
    views = {"bev": (config.bev_size, config.bev_size, bev_pinhole_fov_deg(config, bev_altitude_m)),
             "front": (config.front_width, config.front_height, config.front_fov_deg)}
    for name, (w, h, fov) in views.items():
        for kind in kinds:
            attrs = camera_attributes(kind, w, h, fov_deg=fov, exposure=exposure, config=config)
            specs.append(SensorSpec(("view", name, kind), CAMERA_BLUEPRINTS[kind], attrs, other[name]))
    specs.append(SensorSpec(("lidar",), SENSOR_BLUEPRINTS["lidar"], lidar_attributes(config, dt_s=dt_s), other["lidar"]))
    specs.append(SensorSpec(("semantic_lidar",), SENSOR_BLUEPRINTS["semantic_lidar"],
                            lidar_attributes(config, dt_s=dt_s, semantic=True), other["semantic_lidar"]))
    specs.append(SensorSpec(("radar",), SENSOR_BLUEPRINTS["radar"], radar_attributes(config, dt_s=dt_s), other["radar"]))
    specs.append(SensorSpec(("imu",), SENSOR_BLUEPRINTS["imu"], imu_attributes(), other["imu"]))
    specs.append(SensorSpec(("gnss",), SENSOR_BLUEPRINTS["gnss"], gnss_attributes(), other["gnss"]))
    return specs

