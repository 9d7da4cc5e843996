"""Where every sensor sits on the ego actor, as CARLA transforms.

Every sensor is attached to the ego actor with a `CarlaMount` (CARLA ``Transform`` relative to the
ego actor: location in metres, Unreal axes, and ``(pitch, yaw, roll)`` degrees). The cube faces of
a fisheye camera are the embedded scene's faces exactly: ``calibration.camera_to_vehicle @
CubeRig.face_pose(face)`` turned into a CARLA transform.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping, Sequence

import numpy as np

from ..calibration import Calibration
from ..cameras import Pinhole
from ..io import CARLA_MAX_DEPTH_M
from ..reprojection import FIVE_FACES, CubeRig
from ..scene import CaptureConfig, SensorMounts
from ..transforms import CARLA_TO_ISO, UNREAL_CAMERA_TO_OPENCV, Pose, carla_rotation_matrix
from ._version import CarlaCaptureError


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

