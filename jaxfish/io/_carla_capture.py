"""The pure parts of the CARLA capture program (``scripts/carla_capture.py``).

Everything here runs without a CARLA server and without the ``carla`` package: functions that touch
CARLA take the ``carla`` module or CARLA objects as arguments (anything with the same attributes
works, which is how the tests drive them). The program's contract is the capture layout
(``docs/capture_layout.md``); how to run it is ``docs/carla_capture.md``.

- **Mounts.** Every sensor is attached to the ego actor with a `CarlaMount` (CARLA ``Transform``
  relative to the ego actor: location in metres, Unreal axes, and ``(pitch, yaw, roll)`` degrees).
  The cube faces of a fisheye camera are the embedded scene's faces exactly:
  ``calibration.camera_to_vehicle @ CubeRig.face_pose(face)`` turned into a CARLA transform.
- **Blueprint attributes** for each sensor (fixed exposure on every camera so that cube faces have
  no brightness seams; one lidar rotation per tick; noise-free IMU and GNSS).
- **Conversions** of CARLA sensor outputs to the capture's arrays and of actors to its records.
- **Frame assembly**: `write_carla_frame` writes one frame through the capture writers.
"""

from __future__ import annotations

import dataclasses
import difflib
import json
import math
import os
import re
import shutil
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from .._errors import JaxfishError
from ..calibration import Calibration
from ..cameras import Pinhole
from ..reprojection import FIVE_FACES, CubeRig
from ..scene import (
    RADAR_DTYPE,
    SEMANTIC_LIDAR_DTYPE,
    Actor,
    CaptureConfig,
    EgoMotion,
    SensorMounts,
    StreetFrame,
)
from ..transforms import CARLA_TO_ISO, UNREAL_CAMERA_TO_OPENCV, Pose, carla_rotation_matrix
from ._atomic import atomic_path, atomic_write_text
from ._capture import frame_dir, write_frame, write_npy
from ._carla import CARLA_MAX_DEPTH_M, DVS_EVENT_DTYPE, decode_semantic, encode_instance
from ._images import write_image
from ._json import to_json_text, write_json

SUPPORTED_CARLA_VERSIONS = ("0.9.10", "0.9.11", "0.9.12", "0.9.13", "0.9.14", "0.9.15", "0.9.16")
"""CARLA releases the capture program supports (the ``carla`` client package must match the server)."""
CARLA_WEATHER_PRESETS: tuple[str, ...] = (
    "Default", "ClearNoon", "CloudyNoon", "WetNoon", "WetCloudyNoon", "MidRainyNoon", "HardRainNoon",
    "SoftRainNoon", "ClearSunset", "CloudySunset", "WetSunset", "WetCloudySunset", "MidRainSunset",
    "HardRainSunset", "SoftRainSunset",
)
"""The 15 weather presets of ``carla.WeatherParameters`` in every supported release (0.9.10+)."""
CARLA_LATER_WEATHER_PRESETS: tuple[str, ...] = (
    "ClearNight", "CloudyNight", "WetNight", "WetCloudyNight", "SoftRainNight", "MidRainyNight",
    "HardRainNight", "DustStorm",
)
"""Presets that later releases add (night presets, dust storm): accepted by name, and then only when
the connected ``carla`` client has them (`validate_weather` with ``carla=``)."""
SYNWOODSCAPE_WEATHER_PRESETS: tuple[str, ...] = (
    "ClearNoon", "ClearSunset", "CloudyNoon", "CloudySunset", "Default", "WetCloudyNoon", "WetCloudySunset",
    "WetNoon", "WetSunset",
)
"""The nine presets SynWoodScape was captured with (the paper's list, Town10HD, CARLA 0.9.10.1)."""
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
TWO_WHEELER_BLUEPRINTS = frozenset({
    "vehicle.bh.crossbike", "vehicle.diamondback.century", "vehicle.gazelle.omafiets",
    "vehicle.harley-davidson.low_rider", "vehicle.kawasaki.ninja", "vehicle.yamaha.yzf", "vehicle.vespa.zx125",
})
"""Vehicle blueprints with two wheels (used when a blueprint has no ``number_of_wheels`` attribute)."""
ACTOR_TAGS: dict[str, dict[str, int]] = {
    "0.9.10": {"ego": 10, "four_wheeler": 10, "two_wheeler": 10, "pedestrian": 4},
    "0.9.14": {"ego": 14, "four_wheeler": 14, "two_wheeler": 18, "pedestrian": 12},
}
"""Actor semantic tag of each category in each CARLA tag table (``"0.9.10"``: 0.9.10-0.9.13,
``"0.9.14"``: 0.9.14+ Cityscapes order)."""
_LIDAR_POINT = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("intensity", "<f4")])


class CarlaCaptureError(JaxfishError):
    """A CARLA capture input is unusable: an unknown weather preset or version, a sensor buffer of
    the wrong size, a missing sensor reading. The message names the sensor, file or field."""


# ---------------------------------------------------------------------------- versions and weather
def parse_carla_version(version: str) -> tuple[int, int, int]:
    """``"0.9.14"`` (also ``"0.9.14-12-gabc"``, ``"0.9.15.2"``) -> ``(0, 9, 14)``; rejects releases
    outside 0.9.10 - 0.9.16."""
    m = re.match(r"^\s*(\d+)\.(\d+)\.(\d+)", str(version))
    if not m:
        raise CarlaCaptureError(f"CARLA version {version!r} is not of the form 0.9.N")
    v = (int(m.group(1)), int(m.group(2)), int(m.group(3)))
    if not (0, 9, 10) <= v <= (0, 9, 16):
        raise CarlaCaptureError(f"CARLA version {version!r} is not supported (0.9.10 - 0.9.16)")
    return v


def carla_semantic_tags(version: str) -> str:
    """The tag table a CARLA release's semantic camera and lidar use, as ``capture.json``'s
    ``carla_semantic_tags``: ``"0.9.10"`` for 0.9.10-0.9.13 (23 tags), ``"0.9.14"`` for 0.9.14+
    (Cityscapes order)."""
    return "0.9.10" if parse_carla_version(version) < (0, 9, 14) else "0.9.14"


def has_instance_camera(version: str) -> bool:
    """Whether a CARLA release has ``sensor.camera.instance_segmentation`` (0.9.14+)."""
    return parse_carla_version(version) >= (0, 9, 14)


def validate_weather(names: Iterable[str], *, carla=None) -> tuple[str, ...]:
    """Check weather preset names (exact, case-sensitive ``carla.WeatherParameters`` attribute
    names) and return them in order without duplicates. With the ``carla`` module, a name must also
    exist in that client (night presets and ``DustStorm`` are not in every release)."""
    out: list[str] = []
    known = CARLA_WEATHER_PRESETS + CARLA_LATER_WEATHER_PRESETS
    for name in names:
        if name not in known:
            close = difflib.get_close_matches(str(name), known, n=1)
            hint = f" (did you mean {close[0]!r}?)" if close else ""
            raise CarlaCaptureError(f"weather preset {name!r} is unknown{hint}; presets: {', '.join(known)}")
        if carla is not None and getattr(carla.WeatherParameters, name, None) is None:
            raise CarlaCaptureError(f"weather preset {name!r} does not exist in this carla client")
        if name not in out:
            out.append(name)
    if not out:
        raise CarlaCaptureError("no weather preset given")
    return tuple(out)


def import_carla():
    """Import and return the ``carla`` client module, with an installation hint when it is missing."""
    try:
        import carla  # noqa: PLC0415 - the edge imports CARLA only when a capture runs
    except ImportError as e:
        raise CarlaCaptureError(
            "the CARLA client package is not installed: pip install 'jaxfish[carla]' (its version must match the "
            "server's, e.g. pip install carla==0.9.15)"
        ) from e
    return carla


# ---------------------------------------------------------------------------- mounts
def carla_angles_from_matrix(rotation: np.ndarray) -> tuple[float, float, float]:
    """``(pitch, yaw, roll)`` degrees whose CARLA rotation (``Transform.get_matrix()``) is
    ``rotation`` (Unreal, left-handed). At pitch ±90° only yaw ∓ roll is defined: roll is set to 0."""
    r = np.asarray(rotation, np.float64)
    sp = float(np.clip(r[2, 0], -1.0, 1.0))
    pitch = math.asin(sp)
    if math.cos(pitch) > 1e-9 and math.hypot(r[0, 0], r[1, 0]) > 1e-9:
        yaw = math.atan2(r[1, 0], r[0, 0])
        roll = math.atan2(-r[2, 1], r[2, 2])
    else:  # gimbal lock: with roll = 0, r11 = cos(yaw), r12 = -sin(pitch) sin(yaw)
        pitch = math.copysign(math.pi / 2, sp)
        yaw = math.atan2(-math.copysign(1.0, sp) * r[1, 2], r[1, 1])
        roll = 0.0
    return math.degrees(pitch), math.degrees(yaw), math.degrees(roll)


@dataclasses.dataclass(frozen=True)
class CarlaMount:
    """A sensor's CARLA transform relative to the ego actor: `location` in metres (Unreal: x
    forward, y right, z up) and `rotation` ``(pitch, yaw, roll)`` in degrees."""

    location: tuple[float, float, float]
    rotation: tuple[float, float, float]

    def pose(self) -> Pose:
        """The same transform as a float64 `Pose` (sensor local -> ego actor, Unreal): CARLA's
        ``Transform.get_matrix()``."""
        return Pose(np.asarray(carla_rotation_matrix(*self.rotation), np.float64), np.asarray(self.location, np.float64))

    def to_carla(self, carla):
        """``carla.Transform(carla.Location(...), carla.Rotation(pitch=..., yaw=..., roll=...))``."""
        x, y, z = self.location
        p, yw, r = self.rotation
        return carla.Transform(carla.Location(x=x, y=y, z=z), carla.Rotation(pitch=p, yaw=yw, roll=r))

    def as_dict(self) -> dict[str, list[float]]:
        """``{"location": [x, y, z], "rotation": [pitch, yaw, roll]}`` (the capture's JSON form)."""
        return {"location": list(self.location), "rotation": list(self.rotation)}


def camera_mount(camera_to_vehicle: Pose) -> CarlaMount:
    """The CARLA mount of a camera given as OpenCV camera -> ISO 8855 ego vehicle (a calibration's
    ``camera_to_vehicle``; the vehicle origin is the ego actor's origin)."""
    s, m = CARLA_TO_ISO, UNREAL_CAMERA_TO_OPENCV
    r = s @ np.asarray(camera_to_vehicle.rotation_matrix, np.float64) @ m
    t = s @ np.asarray(camera_to_vehicle.translation, np.float64)
    return CarlaMount(_clean(t), _clean(carla_angles_from_matrix(r)))


def _clean(values) -> tuple[float, float, float]:
    return tuple(float(v) + 0.0 for v in values)  # type: ignore[return-value]  # + 0.0: no "-0.0" in JSON


def face_camera_to_vehicle(calibration: Calibration, face: str) -> Pose:
    """OpenCV face camera -> ISO vehicle pose of one cube face, as the embedded scene renders it
    (``camera_to_vehicle @ CubeRig.face_pose(face)``), in float64."""
    import jax.numpy as jnp

    rig = CubeRig(2, faces=(face,), dtype=jnp.float64)
    mount = Pose(np.asarray(calibration.camera_to_vehicle.rotation_matrix, np.float64),
                 np.asarray(calibration.camera_to_vehicle.translation, np.float64))
    pose = mount @ rig.face_pose(face)
    return Pose(np.asarray(pose.rotation_matrix, np.float64), np.asarray(pose.translation, np.float64))


def cube_face_mounts(rig: Mapping[str, Calibration], faces: Sequence[str] = FIVE_FACES) -> dict[str, dict[str, CarlaMount]]:
    """``{camera: {face: CarlaMount}}``: every cube face of every fisheye camera as a CARLA
    transform on the ego actor (fov-90 square pinholes; see `CubeRig`)."""
    return {name: {f: camera_mount(face_camera_to_vehicle(calib, f)) for f in faces} for name, calib in rig.items()}


def rear_axle_origin(wheel_positions_cm: Sequence, ego_transform: tuple[Sequence[float], Sequence[float]]) -> tuple[float, float, float]:
    """Where a WoodScape-flavour calibration's vehicle origin (on the ground below the rear-axle
    centre) is in the ego actor's CARLA frame: ``(x_rear, y_rear, 0)`` metres from the wheel
    positions of ``vehicle.get_physics_control().wheels`` (world, **centimetres**, as CARLA reports
    them) and the ego's ``(location, rotation)`` at that moment; the rear axle is the mean of the
    half of the wheels with the smallest actor x."""
    p = np.asarray([[float(w.x), float(w.y), float(w.z)] for w in wheel_positions_cm], np.float64) / 100.0
    if p.shape[0] < 2:
        raise CarlaCaptureError(f"rear_axle_origin: need at least 2 wheels, got {p.shape[0]}")
    loc, rot = ego_transform
    r = np.asarray(carla_rotation_matrix(*[float(a) for a in rot]), np.float64)
    local = (p - np.asarray(loc, np.float64)) @ r  # world -> actor: R^T (p - t)
    rear = local[np.argsort(local[:, 0], kind="stable")[: max(1, p.shape[0] // 2)]]
    return _clean((rear[:, 0].mean(), rear[:, 1].mean(), 0.0))


def rig_on_actor(rig: Mapping[str, Calibration], origin_carla: Sequence[float]) -> dict[str, Calibration]:
    """The rig with its vehicle origin moved to the ego actor's origin: ``origin_carla`` is where the
    calibrations' vehicle origin is in the ego actor frame (CARLA, metres; e.g. `rear_axle_origin`).
    Every ``camera_to_vehicle`` translation gains ``origin_carla`` (y flipped to ISO); a capture
    stores this rig, so that its vehicle frame is the ego actor's frame with y flipped."""
    import equinox as eqx
    import jax.numpy as jnp

    shift = CARLA_TO_ISO @ np.asarray(origin_carla, np.float64)
    out = {}
    for name, calib in rig.items():
        t = calib.camera_to_vehicle.translation
        out[name] = eqx.tree_at(lambda c: c.camera_to_vehicle.translation, calib,
                                jnp.asarray(np.asarray(t) + shift, dtype=t.dtype))
    return out


def bev_pinhole_fov_deg(config: CaptureConfig, altitude_m: float) -> float:
    """Horizontal fov (degrees) of the CARLA pinhole that stands in for the orthographic BEV camera
    from ``altitude_m`` above the ground: its footprint on the ground is the BEV's
    ``bev_size · bev_metres_per_pixel`` square, so ground pixels land exactly where the orthographic
    camera puts them (points ``h`` above the ground at ``r`` from the centre move ``r h / (A - h)``)."""
    if not 0.0 < altitude_m < CARLA_MAX_DEPTH_M:
        raise CarlaCaptureError(f"BEV altitude must be in (0, {CARLA_MAX_DEPTH_M}) m, got {altitude_m}")
    half = 0.5 * config.bev_size * config.bev_metres_per_pixel
    return math.degrees(2.0 * math.atan(half / altitude_m))


def bev_pinhole(config: CaptureConfig, altitude_m: float) -> Pinhole:
    """The CARLA pinhole camera of the BEV (see `bev_pinhole_fov_deg`), float64."""
    import jax.numpy as jnp

    return Pinhole.from_fov(config.bev_size, config.bev_size, bev_pinhole_fov_deg(config, altitude_m), dtype=jnp.float64)


def with_bev_altitude(mounts: SensorMounts, *, bev_altitude_m: float | None = None) -> SensorMounts:
    """``mounts`` with the BEV camera raised to ``bev_altitude_m`` above the ground (CARLA has no
    orthographic camera: the capture uses a narrow pinhole from high up, `bev_pinhole_fov_deg`)."""
    if bev_altitude_m is None:
        return mounts
    bev = mounts.bev_camera_to_vehicle
    t = np.asarray(bev.translation, np.float64).copy()
    t[2] = float(bev_altitude_m)
    return dataclasses.replace(mounts, bev_camera_to_vehicle=Pose(np.asarray(bev.rotation_matrix, np.float64), t))


def sensor_carla_mounts(mounts: SensorMounts) -> dict[str, CarlaMount]:
    """CARLA mounts of the BEV and front cameras, lidar (also the semantic lidar), radar, IMU and
    GNSS (from `jaxfish.scene.sensor_mounts`); lidar and radar have ``Rotation(0, 0, 0)``."""
    out = {"bev": camera_mount(mounts.bev_camera_to_vehicle), "front": camera_mount(mounts.front_camera_to_vehicle)}
    for name, loc in (("lidar", mounts.lidar_location), ("radar", mounts.radar_location)):
        out[name] = CarlaMount(_clean((loc[0], -float(loc[1]), loc[2])), (0.0, 0.0, 0.0))
    out["semantic_lidar"] = out["lidar"]
    out["imu"] = out["gnss"] = CarlaMount((0.0, 0.0, 0.0), (0.0, 0.0, 0.0))
    return out


# ---------------------------------------------------------------------------- blueprint attributes
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


# ---------------------------------------------------------------------------- sensor data
def _raw_bytes(data, what: str) -> bytes:
    raw = getattr(data, "raw_data", data)
    try:
        return bytes(raw)
    except TypeError as e:
        raise CarlaCaptureError(f"{what}: no raw buffer ({type(data).__name__})") from e


def image_to_bgra(image, what: str = "camera") -> np.ndarray:
    """A ``carla.Image`` (``raw_data``, ``width``, ``height``) -> BGRA uint8 ``(H, W, 4)`` (a copy)."""
    raw = _raw_bytes(image, what)
    w, h = int(image.width), int(image.height)
    if len(raw) != w * h * 4:
        raise CarlaCaptureError(f"{what}: image buffer of {len(raw)} bytes does not hold {w}x{h} BGRA pixels "
                                f"({w * h * 4} bytes)")
    return np.frombuffer(raw, np.uint8).reshape(h, w, 4).copy()


def dvs_to_events(events, what: str = "dvs") -> np.ndarray:
    """A ``carla.DVSEventArray`` (or its raw bytes) -> `DVS_EVENT_DTYPE` events (``t`` absolute
    simulation time in ns), stably sorted by ``t`` (CARLA's order is kept among equal times and when
    already sorted)."""
    raw = _raw_bytes(events, what)
    if len(raw) % DVS_EVENT_DTYPE.itemsize:
        raise CarlaCaptureError(f"{what}: DVS buffer of {len(raw)} bytes is not a whole number of "
                                f"{DVS_EVENT_DTYPE.itemsize}-byte events")
    ev = np.frombuffer(raw, DVS_EVENT_DTYPE).copy()
    w, h = getattr(events, "width", None), getattr(events, "height", None)
    if ev.size and w is not None and (int(ev["x"].max()) >= int(w) or int(ev["y"].max()) >= int(h)):
        raise CarlaCaptureError(f"{what}: DVS event outside the {w}x{h} image")
    return ev[np.argsort(ev["t"], kind="stable")]


def _records(data, dtype: np.dtype, what: str) -> np.ndarray:
    raw = _raw_bytes(data, what)
    if len(raw) % dtype.itemsize:
        raise CarlaCaptureError(f"{what}: buffer of {len(raw)} bytes is not a whole number of {dtype.itemsize}-byte records")
    return np.frombuffer(raw, dtype).copy()


def lidar_to_points(measurement, what: str = "lidar") -> np.ndarray:
    """A ``carla.LidarMeasurement`` -> float32 ``(N, 4)`` ``x, y, z, intensity`` (sensor frame,
    Unreal axes, metres; CARLA 0.9.10+ layout)."""
    rec = _records(measurement, _LIDAR_POINT, what)
    return rec.view(np.float32).reshape(-1, 4).copy()


def semantic_lidar_to_records(measurement, what: str = "semantic_lidar") -> np.ndarray:
    """A ``carla.SemanticLidarMeasurement`` -> `jaxfish.scene.SEMANTIC_LIDAR_DTYPE` records
    (``x, y, z, CosAngle, ObjIdx, ObjTag``; 24 bytes each)."""
    return _records(measurement, SEMANTIC_LIDAR_DTYPE, what)


def radar_to_records(measurement, what: str = "radar") -> np.ndarray:
    """A ``carla.RadarMeasurement`` -> `jaxfish.scene.RADAR_DTYPE` records (``velocity, azimuth,
    altitude, depth``: m/s (d range / dt), rad, rad, m; 16 bytes each)."""
    return _records(measurement, RADAR_DTYPE, what)


def _vec(v) -> tuple[float, float, float]:
    return float(v.x), float(v.y), float(v.z)


def imu_to_dict(measurement) -> dict[str, Any]:
    """A ``carla.IMUMeasurement`` -> ``imu.json`` (m/s² with gravity, rad/s, compass rad, time s)."""
    return {"accelerometer": list(_vec(measurement.accelerometer)), "gyroscope": list(_vec(measurement.gyroscope)),
            "compass": float(measurement.compass), "timestamp_s": float(measurement.timestamp)}


def gnss_to_dict(measurement) -> dict[str, Any]:
    """A ``carla.GnssMeasurement`` -> ``gnss.json`` (degrees, metres, time s)."""
    return {"latitude": float(measurement.latitude), "longitude": float(measurement.longitude),
            "altitude": float(measurement.altitude), "timestamp_s": float(measurement.timestamp)}


def carla_geo_reference(carla_map, carla) -> dict[str, float]:
    """The map's geo-reference (the geolocation of the world origin) for ``sensors.json``."""
    g = carla_map.transform_to_geolocation(carla.Location(x=0.0, y=0.0, z=0.0))
    return {"latitude": float(g.latitude), "longitude": float(g.longitude), "altitude": float(g.altitude)}


# ---------------------------------------------------------------------------- actors
def carla_transform_tuple(transform) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
    """A ``carla.Transform`` -> ``((x, y, z), (pitch, yaw, roll))`` floats."""
    r = transform.rotation
    return _vec(transform.location), (float(r.pitch), float(r.yaw), float(r.roll))


def actor_category(type_id: str, attributes: Mapping[str, str] | None = None, *, is_ego: bool = False) -> str | None:
    """``"ego"``, ``"four_wheeler"``, ``"two_wheeler"``, ``"pedestrian"`` from a blueprint id and
    its attributes (``number_of_wheels``, or ``base_type`` in 0.9.14+); None for other actors."""
    attributes = attributes or {}
    if is_ego:
        return "ego"
    if type_id.startswith("walker.pedestrian"):
        return "pedestrian"
    if not type_id.startswith("vehicle."):
        return None
    base = str(attributes.get("base_type", "")).lower()
    wheels = attributes.get("number_of_wheels")
    if base in ("motorcycle", "bicycle") or type_id in TWO_WHEELER_BLUEPRINTS or (wheels is not None and int(wheels) == 2):
        return "two_wheeler"
    return "four_wheeler"


def actor_semantic_tag(category: str, tag_table: str, semantic_tags: Sequence[int] | None = None) -> int:
    """An actor's semantic tag in the capture's tag table: CARLA's own (``actor.semantic_tags[0]``)
    when given, else the table's tag of its category (`ACTOR_TAGS`)."""
    if tag_table not in ACTOR_TAGS:
        raise CarlaCaptureError(f"tag table {tag_table!r} is unknown; expected one of {tuple(ACTOR_TAGS)}")
    if semantic_tags:
        return int(semantic_tags[0])
    return ACTOR_TAGS[tag_table][category]


def carla_actor_record(actor, snapshot_prev, snapshot, *, tag_table: str = "0.9.10", is_ego: bool = False) -> Actor | None:
    """A CARLA actor (``id``, ``type_id``, ``attributes``, ``bounding_box``, optional
    ``semantic_tags``) and its ``carla.ActorSnapshot`` at t-1 and t -> a `jaxfish.scene.Actor`
    (``object_index`` -1: not part of an embedded scene). None for actors that are neither vehicles
    nor pedestrians."""
    category = actor_category(str(actor.type_id), dict(getattr(actor, "attributes", {}) or {}), is_ego=is_ego)
    if category is None:
        return None
    loc_p, rot_p = carla_transform_tuple(snapshot_prev.get_transform())
    loc, rot = carla_transform_tuple(snapshot.get_transform())
    box = actor.bounding_box
    return Actor(
        id=int(actor.id), type_id=str(actor.type_id), category=category,
        semantic_tag=actor_semantic_tag(category, tag_table, getattr(actor, "semantic_tags", None)),
        object_index=-1, bbox_location=_vec(box.location), bbox_extent=_vec(box.extent),
        location_prev=loc_p, rotation_prev=rot_p, location=loc, rotation=rot,
        velocity=_vec(snapshot.get_velocity()), angular_velocity=_vec(snapshot.get_angular_velocity()),
    )


def carla_ego_motion(snapshot) -> EgoMotion:
    """The ego's `EgoMotion` at t from its ``carla.ActorSnapshot`` (world: m/s, m/s² without
    gravity, deg/s)."""
    return EgoMotion(velocity=_vec(snapshot.get_velocity()), acceleration=_vec(snapshot.get_acceleration()),
                     angular_velocity=_vec(snapshot.get_angular_velocity()))


def carla_street_frame(frame: int, timestamp_s: float, actors: Sequence[Actor], motion: EgoMotion, *, dt_s: float = 0.1,
                 seed: int = 0) -> StreetFrame:
    """The `StreetFrame` record `write_frame` needs for a CARLA frame (``actors[0]`` is the ego; no
    embedded `Scene`: ``scene`` is None)."""
    if not actors or actors[0].category != "ego":
        raise CarlaCaptureError(f"frame {frame}: the first actor must be the ego vehicle")
    return StreetFrame(scene=None, actors=tuple(actors), ego_motion=motion, frame=int(frame), seed=int(seed),  # type: ignore[arg-type]
                       timestamp_s=float(timestamp_s), dt_s=float(dt_s))


def carla_actor_records(world_actors: Iterable, snapshot_prev, snapshot, *, ego_id: int, tag_table: str) -> list[Actor]:
    """Records of the ego (first) and every vehicle and pedestrian present at both t-1 and t, by id.
    ``snapshot_prev`` / ``snapshot`` are ``carla.WorldSnapshot``s (``find(id)`` -> ActorSnapshot)."""
    ego, others = None, []
    for actor in world_actors:
        a_prev, a_curr = snapshot_prev.find(actor.id), snapshot.find(actor.id)
        if a_prev is None or a_curr is None:
            continue
        rec = carla_actor_record(actor, a_prev, a_curr, tag_table=tag_table, is_ego=int(actor.id) == int(ego_id))
        if rec is None:
            continue
        if rec.category == "ego":
            ego = rec
        else:
            others.append(rec)
    if ego is None:
        raise CarlaCaptureError(f"the ego vehicle (actor {ego_id}) is missing from the world snapshots")
    return [ego] + sorted(others, key=lambda a: a.id)


# ---------------------------------------------------------------------------- height maps
def height_from_depth(depth_m: np.ndarray, camera: Pinhole, camera_to_vehicle: Pose) -> np.ndarray:
    """Height map ``(H, W)`` float32 of a pinhole view (the BEV or front camera) at t: the height of
    the surface each pixel sees above the ego's ground plane, i.e. its z in the ISO 8855 vehicle
    frame (metres; the vehicle origin is on the ground), from its planar depth (metres) and its
    ``camera_to_vehicle`` (OpenCV -> ISO); 0 where the depth is CARLA's far value (sky). The same
    convention as `jaxfish.bev.height_map` and the fusion; it differs from world z minus the ego's z
    when the ego pitches or rolls."""
    d = np.asarray(depth_m, np.float64)
    h, w = d.shape
    if (w, h) != (camera.width, camera.height):
        raise CarlaCaptureError(f"height_from_depth: depth {w}x{h} does not match the camera's {camera.width}x{camera.height}")
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    fx, fy, cx, cy = (float(np.asarray(getattr(camera, k))) for k in ("fx", "fy", "cx", "cy"))
    p_cam = np.stack([(u - cx) / fx * d, (v - cy) / fy * d, d], axis=-1)
    r_cv = np.asarray(camera_to_vehicle.rotation_matrix, np.float64)
    t_cv = np.asarray(camera_to_vehicle.translation, np.float64)
    z = p_cam @ r_cv[2] + t_cv[2]  # vehicle-frame z of p_vehicle = R p_cam + t
    return np.where(d >= CARLA_MAX_DEPTH_M * (1.0 - 1e-6), 0.0, z).astype(np.float32)


# ---------------------------------------------------------------------------- frame assembly
@dataclasses.dataclass(frozen=True)
class CarlaImages:
    """One camera's raw CARLA images at one instant, BGRA uint8 ``(H, W, 4)``: `rgb`, `depth`
    (24-bit encoded), `semantic` (tag in R) and `instance` (0.9.14+; None before)."""

    rgb: np.ndarray
    depth: np.ndarray
    semantic: np.ndarray
    instance: np.ndarray | None = None


def _write_raw_images(directory: Path, images: CarlaImages, instant: str, what: str, reuse: Path | None = None) -> None:
    shape = None
    for kind in ("rgb", "depth", "semantic", "instance"):
        a = getattr(images, kind)
        if a is None:  # no instance camera before 0.9.14: the tag, and actor id 0 (unknown)
            a = encode_instance(decode_semantic(images.semantic), np.zeros(images.semantic.shape[:2], np.int64))
        a = np.asarray(a)
        if a.dtype != np.uint8 or a.ndim != 3 or a.shape[-1] != 4:
            raise CarlaCaptureError(f"{what}: {kind}_{instant} must be BGRA uint8 (H, W, 4), got {a.dtype} {a.shape}")
        if shape is not None and a.shape != shape:
            raise CarlaCaptureError(f"{what}: {kind}_{instant} is {a.shape}, the rgb image {shape}")
        shape = a.shape
        source = reuse / f"{kind}_curr.png" if reuse is not None else None
        if source is not None and source.is_file():  # the same tick, already encoded: copy its bytes
            with atomic_path(directory / f"{kind}_{instant}.png") as tmp:
                shutil.copyfile(source, tmp)
        else:
            write_image(directory / f"{kind}_{instant}.png", a)


def write_carla_frame(
    root: str | os.PathLike,
    frame: StreetFrame,
    *,
    faces: Mapping[str, Mapping[str, tuple[CarlaImages, CarlaImages, np.ndarray]]],
    views: Mapping[str, tuple[CarlaImages, CarlaImages, np.ndarray]],
    lidar: np.ndarray,
    semantic_lidar: np.ndarray,
    radar: np.ndarray,
    imu: Mapping[str, Any],
    gnss: Mapping[str, Any],
    prev_from_frame: int | None = None,
    dvs_missing: Sequence[str] = (),
) -> Path:
    """Write one CARLA frame in the capture layout: ``faces[camera][face] = (prev, curr, dvs events)``
    and ``views[name] = (prev, curr, height map at t)`` with raw BGRA images (written unchanged);
    lidar, radar, IMU, GNSS, ego and actors through `jaxfish.io.write_frame`, which lists the frame
    in ``capture.json`` last (a frame is listed only once complete).

    ``prev_from_frame``: a frame already written whose t is this frame's t-1 (consecutive ticks): its
    ``*_curr.png`` files are copied as this frame's ``*_prev.png`` instead of encoding the same
    pixels again (half the PNG encoding of a sequence); the caller guarantees they are the same tick.

    ``dvs_missing``: the faces (``"camera/face"``) whose DVS sent no reading for t within the wait,
    written sorted to the frame's ``carla_frame.json`` as ``{"dvs_missing": [...]}`` (their
    ``dvs.npy`` is empty: no pixel changed, or the reading came too late)."""
    d = frame_dir(root, frame.frame)
    known = {f"{cam}/{face}" for cam, per_face in faces.items() for face in per_face}
    unknown = sorted(set(dvs_missing) - known)
    if unknown:
        raise CarlaCaptureError(f"frame {frame.frame}: dvs_missing names faces {unknown} that are not written "
                                f"(faces are 'camera/face': {sorted(known)})")
    before = frame_dir(root, prev_from_frame) if prev_from_frame is not None else None
    for cam, per_face in faces.items():
        for face, (prev, curr, events) in per_face.items():
            fd = d / "cameras" / cam / face
            _write_raw_images(fd, prev, "prev", f"{cam}/{face}",
                              before / "cameras" / cam / face if before is not None else None)
            _write_raw_images(fd, curr, "curr", f"{cam}/{face}")
            ev = np.asarray(events)
            if ev.dtype != DVS_EVENT_DTYPE:
                raise CarlaCaptureError(f"{cam}/{face}: DVS events must have DVS_EVENT_DTYPE, got {ev.dtype}")
            write_npy(fd / "dvs.npy", ev)
    for name, (prev, curr, height) in views.items():
        _write_raw_images(d / name, prev, "prev", name, before / name if before is not None else None)
        _write_raw_images(d / name, curr, "curr", name)
        hm = np.asarray(height, np.float32)
        if hm.shape != curr.rgb.shape[:2]:
            raise CarlaCaptureError(f"{name}: height map {hm.shape} does not match the image {curr.rgb.shape[:2]}")
        write_image(d / name / "height_curr.exr", hm)
    write_json(d / "carla_frame.json", {"dvs_missing": sorted(set(dvs_missing))}, indent=1, error=CarlaCaptureError)
    return write_frame(root, frame, cameras={}, views={}, lidar=lidar, semantic_lidar=semantic_lidar, radar=radar,
                       imu=imu, gnss=gnss)


def finish_carla_header(
    root: str | os.PathLike,
    *,
    carla_version: str,
    mounts: Mapping[str, CarlaMount],
    bev_altitude_m: float,
    config: CaptureConfig,
    geo: Mapping[str, float] | None = None,
    extra: Mapping[str, Any] | None = None,
) -> None:
    """Complete the files `jaxfish.io.write_capture_header` wrote for a CARLA capture:
    ``capture.json`` gets ``carla_semantic_tags`` of the release, ``carla_version``,
    ``instance_ids`` (False before 0.9.14: instance PNGs then carry actor id 0) and ``extra``;
    ``sensors.json`` gets the exact CARLA mounts, the BEV's stand-in pinhole and the geo-reference."""
    root = Path(root)
    header = json.loads((root / "capture.json").read_text())
    header.update({"carla_semantic_tags": carla_semantic_tags(carla_version), "carla_version": str(carla_version),
                   "instance_ids": has_instance_camera(carla_version)})
    header.update(dict(extra or {}))
    sensors = json.loads((root / "sensors.json").read_text())
    for name, mount in mounts.items():
        if name in sensors:
            sensors[name]["carla_transform"] = mount.as_dict()
    sensors["bev"]["carla_camera"] = {"model": "pinhole", "fov_deg": bev_pinhole_fov_deg(config, bev_altitude_m),
                                      "altitude_m": float(bev_altitude_m)}
    if geo is not None:
        sensors["gnss"]["geo_reference"] = {k: float(geo[k]) for k in ("latitude", "longitude", "altitude")}
    texts = {name: to_json_text(root / name, doc, indent=2, error=CarlaCaptureError)  # both valid before either is written
             for name, doc in (("sensors.json", sensors), ("capture.json", header))}
    for name, text in texts.items():
        atomic_write_text(root / name, text)
