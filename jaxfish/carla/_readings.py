"""CARLA sensor readings -> the capture's arrays and records (copies of the raw buffers), and the
height maps of the BEV and front views."""

from __future__ import annotations

from typing import Any

import numpy as np

from ..cameras import Pinhole
from ..io import CARLA_MAX_DEPTH_M, DVS_EVENT_DTYPE
from ..scene import RADAR_DTYPE, SEMANTIC_LIDAR_DTYPE
from ..transforms import Pose
from ._version import CarlaCaptureError

_LIDAR_POINT = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("intensity", "<f4")])


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


def checked_events(events: np.ndarray, what: str = "dvs") -> np.ndarray:
    """``events`` as a 1-D `DVS_EVENT_DTYPE` array (what `dvs_to_events` returns); another dtype or
    shape raises `CarlaCaptureError` naming ``what`` (the face, e.g. ``"FV/left"``)."""
    ev = np.asarray(events)
    if ev.dtype != DVS_EVENT_DTYPE or ev.ndim != 1:
        raise CarlaCaptureError(f"{what}: DVS events must have DVS_EVENT_DTYPE and one axis, got {ev.dtype} {ev.shape}")
    return ev


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

