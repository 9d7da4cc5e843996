"""The frame's other sensors in the ISO 8855 vehicle frame: ego state, lidar, semantic lidar, radar, IMU, GNSS.

A capture stores them as CARLA does: lidar, semantic lidar and radar in the sensor's local Unreal
frame (x forward, y right, z up: left-handed), the ego's velocity, acceleration and angular velocity in
the CARLA world, the IMU in the ego frame with Unreal axes. `sensor_truth` converts every one to the
right-handed ISO 8855 vehicle frame at t (x forward, y left, z up; origin = the ego actor origin), the
frame of the dataset's boxes, BEV and calibrations. Pure NumPy (float64), nothing read or written.

Handedness: the reflection ``S = diag(1, -1, 1)`` maps Unreal coordinates to ISO ones. Points and
ordinary vectors (positions, velocities, accelerations) map as ``S v``. Angular velocities are axial
vectors: a rotation rate ``w`` of the left-handed frame (``dR/dt = [w]x R`` written in its
coordinates; CARLA's gyroscope and ``get_angular_velocity``: z positive = yaw increasing = turning
right) is ``-S w = (-wx, wy, -wz)`` in ISO coordinates (z positive = turning left).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

import equinox as eqx
import numpy as np
from jaxtyping import Float

CARLA_TO_ISO_4X4 = np.diag([1.0, -1.0, 1.0, 1.0])
"""The reflection between Unreal and ISO 8855 coordinates as a homogeneous 4 x 4 (its own inverse)."""

SEMANTIC_LIDAR_VEHICLE_DTYPE = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("cos_inc_angle", "<f4"),
                                         ("object_idx", "<u4"), ("object_tag", "<u4")])
"""Semantic lidar points in the ISO vehicle frame: ``x, y, z`` (metres), CARLA's ``CosAngle``,
``ObjIdx`` (actor id, 0 = static) and ``ObjTag`` (the capture's tag) under snake-case names."""

RADAR_VEHICLE_DTYPE = np.dtype([("velocity", "<f4"), ("azimuth", "<f4"), ("altitude", "<f4"), ("depth", "<f4"),
                                ("x", "<f4"), ("y", "<f4"), ("z", "<f4")])
"""Radar detections: CARLA's fields (``velocity`` m/s, ``azimuth`` and ``altitude`` rad in the
sensor frame, ``depth`` m) plus ``x, y, z``: the detection in the ISO vehicle frame (metres)."""


def carla_rotation_np(rotation_deg: Sequence[float]) -> np.ndarray:
    """CARLA's rotation matrix of ``(pitch, yaw, roll)`` degrees (``Transform.get_matrix()``'s
    rotation block, Unreal axes), float64."""
    p, y, r = (math.radians(float(v)) for v in rotation_deg)
    cp, sp, cy, sy, cr, sr = math.cos(p), math.sin(p), math.cos(y), math.sin(y), math.cos(r), math.sin(r)
    return np.array([[cp * cy, cy * sp * sr - sy * cr, -cy * sp * cr - sy * sr],
                     [cp * sy, sy * sp * sr + cy * cr, -sy * sp * cr + cy * sr],
                     [sp, -cp * sr, cp * cr]], np.float64)


def carla_transform_matrix(location: Sequence[float], rotation_deg: Sequence[float]) -> np.ndarray:
    """4 x 4 of CARLA's ``Transform(location, Rotation(pitch, yaw, roll))``: local -> parent, Unreal."""
    m = np.eye(4)
    m[:3, :3] = carla_rotation_np(rotation_deg)
    m[:3, 3] = np.asarray(location, np.float64)
    return m


def sensor_to_vehicle_matrix(location: Sequence[float], rotation_deg: Sequence[float]) -> Float[np.ndarray, "4 4"]:
    """The 4 x 4 mapping a sensor's local Unreal coordinates to ISO 8855 vehicle coordinates, from
    its CARLA mount on the ego (``sensors.json`` ``carla_transform``: location in metres and
    ``(pitch, yaw, roll)`` degrees relative to the ego actor, Unreal): ``S @ T`` (determinant -1)."""
    return CARLA_TO_ISO_4X4 @ carla_transform_matrix(location, rotation_deg)


def vehicle_to_world_matrix(location: Sequence[float], rotation_deg: Sequence[float]) -> Float[np.ndarray, "4 4"]:
    """The 4 x 4 mapping ISO 8855 vehicle coordinates to CARLA world coordinates (column vectors) of
    an ego actor whose CARLA transform is ``(location, rotation)``: ``T @ S`` (determinant -1: the
    vehicle frame is right-handed, the world left-handed)."""
    return carla_transform_matrix(location, rotation_deg) @ CARLA_TO_ISO_4X4


def to_vehicle(points: Float[np.ndarray, "N 3"], sensor_to_vehicle: Float[np.ndarray, "4 4"]) -> Float[np.ndarray, "N 3"]:
    """Points ``(N, 3)`` of a sensor's local frame -> the vehicle frame by a 4 x 4 (float64)."""
    p = np.asarray(points, np.float64).reshape(-1, 3)
    m = np.asarray(sensor_to_vehicle, np.float64)
    r = m[:3, :3]  # p @ r.T as products and sums in a fixed order (not a CPU-dependent BLAS kernel)
    return p[:, 0:1] * r[:, 0] + p[:, 1:2] * r[:, 1] + p[:, 2:3] * r[:, 2] + m[:3, 3]


def radar_points_local(radar: np.ndarray) -> Float[np.ndarray, "N 3"]:
    """CARLA radar detections -> points of the radar's local Unreal frame (float64):
    ``depth (cos(alt) cos(az), cos(alt) sin(az), sin(alt))`` (azimuth positive to the right = +y)."""
    az = np.asarray(radar["azimuth"], np.float64)
    alt = np.asarray(radar["altitude"], np.float64)
    d = np.asarray(radar["depth"], np.float64)
    return np.stack([d * np.cos(alt) * np.cos(az), d * np.cos(alt) * np.sin(az), d * np.sin(alt)], axis=-1)


def unreal_vector_to_iso(v: Sequence[float]) -> np.ndarray:
    """An ordinary vector (position, velocity, acceleration) in Unreal axes -> ISO axes: ``S v``."""
    a = np.asarray(v, np.float64)
    return a * np.array([1.0, -1.0, 1.0])


def unreal_angular_velocity_to_iso(w: Sequence[float]) -> np.ndarray:
    """An angular velocity (axial vector) in Unreal axes -> ISO axes: ``-S w = (-wx, wy, -wz)``."""
    a = np.asarray(w, np.float64)
    return a * np.array([-1.0, 1.0, -1.0])


class EgoState(eqx.Module):
    """The ego vehicle at t in the ISO 8855 vehicle frame at t.

    - `timestamp_s`, `previous_timestamp_s`: simulation time of t and t-1 (seconds);
    - `vehicle_to_world` ``(4, 4)`` float64: ISO vehicle at t -> CARLA world (column vectors,
      determinant -1, `vehicle_to_world_matrix`);
    - `velocity_mps`, `acceleration_mps2` ``(3,)``: the world velocity and acceleration
      (without gravity) rotated into the vehicle frame;
    - `angular_velocity_radps` ``(3,)``: rad/s about the ISO vehicle axes (z positive = turning left).
    """

    timestamp_s: float = eqx.field(static=True)
    previous_timestamp_s: float = eqx.field(static=True)
    vehicle_to_world: Float[np.ndarray, "4 4"]
    velocity_mps: Float[np.ndarray, " 3"]
    acceleration_mps2: Float[np.ndarray, " 3"]
    angular_velocity_radps: Float[np.ndarray, " 3"]


class ImuReading(eqx.Module):
    """The IMU at t in the ISO vehicle frame: `accelerometer_mps2` (gravity included: +9.81 on z
    at rest), `gyroscope_radps` (z positive = turning left), `compass_rad` (CARLA's: radians from
    north, clockwise; frame-independent)."""

    accelerometer_mps2: Float[np.ndarray, " 3"]
    gyroscope_radps: Float[np.ndarray, " 3"]
    compass_rad: float = eqx.field(static=True)


class GnssFix(eqx.Module):
    """The GNSS fix at t: `latitude_deg`, `longitude_deg` (degrees), `altitude_m` (metres)."""

    latitude_deg: float = eqx.field(static=True)
    longitude_deg: float = eqx.field(static=True)
    altitude_m: float = eqx.field(static=True)


class SensorTruth(eqx.Module):
    """Every non-camera sensor of a sample in the ISO 8855 vehicle frame at t (`sensor_truth`).

    - `ego`: `EgoState`; `imu`: `ImuReading` or None (no IMU record); `gnss`: `GnssFix` or None;
    - `lidar_vehicle` ``(N, 4)`` float32: x, y, z (ISO vehicle, metres), intensity;
    - `semantic_lidar_vehicle` ``(N,)`` `SEMANTIC_LIDAR_VEHICLE_DTYPE`;
    - `radar_vehicle` ``(N,)`` `RADAR_VEHICLE_DTYPE`.
    """

    ego: EgoState
    imu: ImuReading | None
    gnss: GnssFix | None
    lidar_vehicle: Float[np.ndarray, "N 4"]
    semantic_lidar_vehicle: np.ndarray
    radar_vehicle: np.ndarray


def ego_state(ego: Mapping[str, Any]) -> EgoState:
    """`EgoState` of an ego record (``ego.json``: ``timestamp_s``, ``timestamp_prev_s``,
    ``transform`` ``{location, rotation}``, ``velocity`` m/s and ``acceleration`` m/s² in the CARLA
    world, ``angular_velocity`` deg/s in the CARLA world). Raises ``KeyError`` / ``TypeError`` /
    ``ValueError`` on a malformed record."""
    tr = ego["transform"]
    v2w = vehicle_to_world_matrix(tr["location"], tr["rotation"])
    r_actor = carla_rotation_np(tr["rotation"])  # ego actor (Unreal) -> world (Unreal)

    def world_vector(key: str) -> np.ndarray:
        v = np.asarray(ego[key], np.float64)
        if v.shape != (3,):
            raise ValueError(f"{key} must be 3 numbers, got shape {v.shape}")
        # In the ego actor's Unreal axes: R^T v as products and sums in a fixed order (a BLAS
        # product's rounding depends on the CPU's kernel; these bytes must not).
        return r_actor[0] * v[0] + r_actor[1] * v[1] + r_actor[2] * v[2]

    w = np.deg2rad(world_vector("angular_velocity"))
    return EgoState(timestamp_s=float(ego["timestamp_s"]), previous_timestamp_s=float(ego["timestamp_prev_s"]),
                    vehicle_to_world=v2w, velocity_mps=unreal_vector_to_iso(world_vector("velocity")),
                    acceleration_mps2=unreal_vector_to_iso(world_vector("acceleration")),
                    angular_velocity_radps=unreal_angular_velocity_to_iso(w))


def imu_reading(imu: Mapping[str, Any] | None) -> ImuReading | None:
    """`ImuReading` of an IMU record (``imu.json``: ``accelerometer`` m/s² and ``gyroscope`` rad/s
    in the ego frame with Unreal axes, ``compass`` rad); None for an empty or missing record."""
    if not imu:
        return None
    acc = np.asarray(imu["accelerometer"], np.float64)
    gyro = np.asarray(imu["gyroscope"], np.float64)
    if acc.shape != (3,) or gyro.shape != (3,):
        raise ValueError(f"imu accelerometer / gyroscope must be 3 numbers, got {acc.shape} / {gyro.shape}")
    return ImuReading(accelerometer_mps2=unreal_vector_to_iso(acc), gyroscope_radps=unreal_angular_velocity_to_iso(gyro),
                      compass_rad=float(imu["compass"]))


def gnss_fix(gnss: Mapping[str, Any] | None) -> GnssFix | None:
    """`GnssFix` of a GNSS record (``gnss.json``: ``latitude``, ``longitude``, ``altitude``); None
    for an empty or missing record."""
    if not gnss:
        return None
    return GnssFix(latitude_deg=float(gnss["latitude"]), longitude_deg=float(gnss["longitude"]),
                   altitude_m=float(gnss["altitude"]))


def sensor_truth(records) -> SensorTruth:
    """Every non-camera sensor of a frame (`SensorRecords`) in the ISO 8855 vehicle frame at t:
    the ego state, IMU and GNSS, the lidar and semantic lidar points (mapped by
    ``records.lidar_to_vehicle``) and the radar detections with their vehicle-frame points
    (``records.radar_to_vehicle``). Raises ``ValueError`` when points are present and their mount
    is missing, and ``KeyError`` / ``TypeError`` / ``ValueError`` on a malformed record."""
    lidar = np.asarray(records.lidar, np.float32).reshape(-1, 4)
    sem = np.asarray(records.semantic_lidar)
    radar = np.asarray(records.radar)

    def mount(name: str, n: int) -> np.ndarray:
        m = getattr(records, f"{name}_to_vehicle")
        if m is None:
            if n:
                raise ValueError(f"{n} {name} point(s) but no {name} mount (SensorRecords.{name}_to_vehicle)")
            return np.eye(4)
        return np.asarray(m, np.float64)

    m_lidar = mount("lidar", max(len(lidar), len(sem)))
    out_lidar = np.empty((len(lidar), 4), np.float32)
    out_lidar[:, :3] = to_vehicle(lidar[:, :3], m_lidar)
    out_lidar[:, 3] = lidar[:, 3]
    out_sem = np.zeros(len(sem), SEMANTIC_LIDAR_VEHICLE_DTYPE)
    if len(sem):
        xyz = np.stack([np.asarray(sem[k], np.float64) for k in ("x", "y", "z")], axis=-1)
        v = to_vehicle(xyz, m_lidar)
        out_sem["x"], out_sem["y"], out_sem["z"] = v[:, 0], v[:, 1], v[:, 2]
        out_sem["cos_inc_angle"], out_sem["object_idx"], out_sem["object_tag"] = sem["CosAngle"], sem["ObjIdx"], sem["ObjTag"]
    out_radar = np.zeros(len(radar), RADAR_VEHICLE_DTYPE)
    if len(radar):
        v = to_vehicle(radar_points_local(radar), mount("radar", len(radar)))
        for k in ("velocity", "azimuth", "altitude", "depth"):
            out_radar[k] = radar[k]
        out_radar["x"], out_radar["y"], out_radar["z"] = v[:, 0], v[:, 1], v[:, 2]
    return SensorTruth(ego=ego_state(records.ego), imu=imu_reading(records.imu), gnss=gnss_fix(records.gnss),
                       lidar_vehicle=out_lidar, semantic_lidar_vehicle=out_sem, radar_vehicle=out_radar)
