"""CARLA camera sensors: blueprint attributes and the mount transform, as JSON::

    {"sensors": [{"name": "FV", "blueprint": "sensor.camera.rgb",
                  "attributes": {"image_size_x": "1280", "image_size_y": "966", "fov": "90"},
                  "transform": {"location": [x, y, z], "rotation": [pitch, yaw, roll]}}]}

(a single sensor object at the root is read too). Attribute values are strings, as
``blueprint.get_attribute(...)`` gives them, or numbers. ``transform`` is the sensor's
``carla.Transform`` relative to the ego vehicle (Unreal: x forward, y right, z up, metres;
degrees), converted to jaxfish's OpenCV camera -> ISO 8855 vehicle pose as
`jaxfish.transforms.carla_camera_pose_to_opencv` does (the vehicle origin is the ego actor's).

A plain ``sensor.camera.*`` is CARLA's pinhole (`jaxfish.Pinhole.from_fov`: focal length
``W / (2 tan(fov/2))`` from the horizontal ``fov``, optical axis at the image centre); a sensor
with the WideAngle lens attributes (``camera_model``, ``k0``..``k3``) or a ``*_wide_angle_lens``
blueprint (CARLA 0.9.16) is ``carla_wide_angle`` (``camera_model`` default ``kannala-brandt``,
``fov`` and ``k0``..``k3`` CARLA's defaults where absent), written as
``sensor.camera.rgb_wide_angle_lens``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from ...refit._parameters import MODEL_CLASSES, PARAMETER_NAMES
from ._common import CameraRecord, fail, mapping, number, short, whole

WIDE_ANGLE_ATTRIBUTES = ("camera_model", "k0", "k1", "k2", "k3")
"""Blueprint attributes that make a camera CARLA's WideAngle lens (``carla_wide_angle``)."""
_PINHOLE_TOLERANCE = 1e-9


def carla_rotation(pitch: float, yaw: float, roll: float) -> np.ndarray:
    """The rotation block of CARLA's ``Transform.get_matrix()`` (Unreal, left-handed, degrees), in
    float64 NumPy (as `jaxfish.transforms.carla_rotation_matrix`)."""
    p, y, r = (math.radians(a) for a in (pitch, yaw, roll))
    cp, sp, cy, sy, cr, sr = math.cos(p), math.sin(p), math.cos(y), math.sin(y), math.cos(r), math.sin(r)
    return np.array([[cp * cy, cy * sp * sr - sy * cr, -cy * sp * cr - sy * sr],
                     [cp * sy, sy * sp * sr + cy * cr, -sy * sp * cr + cy * sr],
                     [sp, -cp * sr, cp * cr]])


def carla_angles(rot: np.ndarray) -> tuple[float, float, float]:
    """``(pitch, yaw, roll)`` degrees of a CARLA rotation matrix (inverse of `carla_rotation`; at
    pitch ±90° roll is 0)."""
    r = np.asarray(rot, np.float64)
    sp = float(np.clip(r[2, 0], -1.0, 1.0))
    pitch = math.asin(sp)
    if math.cos(pitch) > 1e-9 and math.hypot(r[0, 0], r[1, 0]) > 1e-9:
        yaw, roll = math.atan2(r[1, 0], r[0, 0]), math.atan2(-r[2, 1], r[2, 2])
    else:
        pitch = math.copysign(math.pi / 2, sp)
        yaw, roll = math.atan2(-math.copysign(1.0, sp) * r[1, 2], r[1, 1]), 0.0
    return math.degrees(pitch), math.degrees(yaw), math.degrees(roll)


def _transform(value: Any, source: str, field: str) -> np.ndarray:
    """A sensor's CARLA transform -> the 4x4 OpenCV camera -> ISO vehicle matrix, as
    `jaxfish.transforms.carla_camera_pose_to_opencv` (``S R M^T``, ``S t``)."""
    from ...transforms import CARLA_TO_ISO, UNREAL_CAMERA_TO_OPENCV

    t = mapping(value, source, field)
    loc, rot = t.get("location"), t.get("rotation")
    if loc is None:
        raise fail(source, f"{field}.location", "missing")
    if rot is None:
        raise fail(source, f"{field}.rotation", "missing")
    if isinstance(loc, dict):
        loc = [loc.get(k) for k in ("x", "y", "z")]
    if isinstance(rot, dict):
        rot = [rot.get(k) for k in ("pitch", "yaw", "roll")]
    if not isinstance(loc, list) or len(loc) != 3:
        raise fail(source, f"{field}.location", f"expected [x, y, z] metres, got {short(loc)}")
    if not isinstance(rot, list) or len(rot) != 3:
        raise fail(source, f"{field}.rotation", f"expected [pitch, yaw, roll] degrees, got {short(rot)}")
    xyz = [number(v, source, f"{field}.location[{i}]") for i, v in enumerate(loc)]
    pyr = [number(v, source, f"{field}.rotation[{i}]") for i, v in enumerate(rot)]
    out = np.eye(4)
    out[:3, :3] = CARLA_TO_ISO @ carla_rotation(*pyr) @ UNREAL_CAMERA_TO_OPENCV.T
    out[:3, 3] = CARLA_TO_ISO @ np.asarray(xyz)
    return out


def _sensor(s: Any, source: str, where: str, index: int) -> CameraRecord:
    s = mapping(s, source, where)
    bp = s.get("blueprint", "sensor.camera.rgb")
    if not isinstance(bp, str) or not bp.startswith("sensor.camera."):
        raise fail(source, f"{where}.blueprint", f"expected a camera blueprint (sensor.camera.*), got {short(bp)}")
    attrs = mapping(s.get("attributes", {}), source, f"{where}.attributes")
    for key in ("image_size_x", "image_size_y"):
        if key not in attrs:
            raise fail(source, f"{where}.attributes.{key}", "missing")
    w = whole(attrs["image_size_x"], source, f"{where}.attributes.image_size_x")
    h = whole(attrs["image_size_y"], source, f"{where}.attributes.image_size_y")
    fov = number(attrs.get("fov", 90.0), source, f"{where}.attributes.fov")
    name = s.get("name", f"camera{index}")
    if not isinstance(name, str) or not name:
        raise fail(source, f"{where}.name", f"expected a non-empty string, got {short(name)}")
    pose = _transform(s["transform"], source, f"{where}.transform") if "transform" in s else np.eye(4)
    lens = [k for k in WIDE_ANGLE_ATTRIBUTES if k in attrs]
    if lens or "wide_angle" in bp.lower():
        field = f"{where}.attributes.{lens[0]}" if lens else f"{where}.blueprint"
        if "carla_wide_angle" not in MODEL_CLASSES:
            raise fail(source, field, "CARLA's WideAngle lens is jaxfish's lens model 'carla_wide_angle', which this "
                       "version of jaxfish does not have")
        params, strings = _wide_angle(attrs, source, f"{where}.attributes")
        return CameraRecord(name, "carla_wide_angle", params, w, h, pose, where=where, strings=strings)
    if not 0.0 < fov < 180.0:
        raise fail(source, f"{where}.attributes.fov", f"a pinhole's horizontal fov must be in (0, 180) degrees, got {short(fov)}")
    f = w / (2.0 * math.tan(math.radians(fov) / 2.0))
    return CameraRecord(name, "pinhole", {"fx": f, "fy": f, "cx": (w - 1) / 2.0, "cy": (h - 1) / 2.0}, w, h, pose,
                        where=where)


def _wide_angle(attrs, source, where) -> tuple[dict[str, float], dict[str, str]]:
    """The carla_wide_angle parameters (``fov``, ``k0`` .. ``k3``: the blueprint attributes of the
    same names, CARLA's defaults where absent) and its ``camera_model`` (default
    ``kannala-brandt``, as the sensor's)."""
    from ...cameras import _carla_wide_angle as cwa

    model = attrs.get("camera_model", "kannala-brandt")
    if not isinstance(model, str) or model.strip().lower().replace("_", "-") not in cwa.CARLA_CAMERA_MODELS:
        raise fail(source, f"{where}.camera_model", f"expected one of {', '.join(cwa.CARLA_CAMERA_MODELS)}, "
                   f"got {short(model)}")
    defaults = {"fov": cwa.CARLA_DEFAULT_FOV_DEG, **dict(zip(("k0", "k1", "k2", "k3"), cwa.CARLA_DEFAULT_KB, strict=True))}
    params = {n: number(attrs[n], source, f"{where}.{n}") if n in attrs else float(defaults[n])
              for n in PARAMETER_NAMES["carla_wide_angle"]}
    return params, {"camera_model": model.strip().lower().replace("_", "-")}


def read(data: Any, source: str) -> list[CameraRecord]:
    """The cameras of a parsed CARLA sensors JSON."""
    data = mapping(data, source, "<root>")
    if "sensors" in data:
        sensors = data["sensors"]
        if not isinstance(sensors, list) or not sensors:
            raise fail(source, "sensors", "expected a non-empty list of sensors")
        return [_sensor(s, source, f"sensors[{i}]", i) for i, s in enumerate(sensors)]
    return [_sensor(data, source, "<root>", 0)]


def pinhole_fov(record: CameraRecord) -> float | None:
    """The horizontal fov (degrees) of a pinhole CARLA renders exactly (square pixels, axis at the
    image centre), or None."""
    p = record.params
    if record.model != "pinhole":
        return None
    if p["fx"] != p["fy"] or abs(p["cx"] - (record.width - 1) / 2) > _PINHOLE_TOLERANCE \
            or abs(p["cy"] - (record.height - 1) / 2) > _PINHOLE_TOLERANCE:
        return None
    return math.degrees(2.0 * math.atan(record.width / (2.0 * p["fx"])))


def writable(record: CameraRecord) -> bool:
    """Whether CARLA renders this camera exactly."""
    return pinhole_fov(record) is not None or record.model == "carla_wide_angle"


def write(records: Sequence[CameraRecord]) -> dict[str, Any]:
    """The CARLA sensors object of cameras CARLA renders exactly (`writable`)."""
    from ...transforms import CARLA_TO_ISO, UNREAL_CAMERA_TO_OPENCV

    sensors = []
    for r in records:
        attrs: dict[str, str] = {"image_size_x": str(r.width), "image_size_y": str(r.height)}
        fov = pinhole_fov(r)
        if fov is not None:
            attrs["fov"] = repr(fov)
        else:
            attrs.update(r.strings)
            attrs.update({k: repr(float(v)) for k, v in r.params.items()})
        m = r.camera_to_vehicle
        loc = [float(x) + 0.0 for x in CARLA_TO_ISO @ m[:3, 3]]  # + 0.0: no "-0.0" in the file
        rot = [float(x) + 0.0 for x in carla_angles(CARLA_TO_ISO @ m[:3, :3] @ UNREAL_CAMERA_TO_OPENCV)]
        blueprint = "sensor.camera.rgb" if fov is not None else "sensor.camera.rgb_wide_angle_lens"
        sensors.append({"name": r.name, "blueprint": blueprint, "attributes": attrs,
                        "transform": {"location": loc, "rotation": rot}})
    return {"sensors": sensors}
