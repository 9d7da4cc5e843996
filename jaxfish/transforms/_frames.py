"""Frame conventions: CARLA/Unreal (left-handed), ISO 8855 vehicle, OpenCV camera.

- **CARLA / Unreal** world and actor frames: x forward, y right, z up (left-handed), metres.
- **ISO 8855** vehicle frame: x forward, y left, z up (right-handed), metres. WoodScape puts its
  origin on the ground below the rear-axle centre; for SynWoodScape/CARLA captures it is the CARLA
  ego actor's origin.
- **OpenCV** camera frame: x right, y down, z forward (optical axis).

CARLA <-> ISO flips y (a reflection ``S = diag(1, -1, 1)``; a pose ``T`` becomes ``S T S``). A CARLA
camera's local point ``(x, y, z)`` is ``(y, -z, x)`` in the OpenCV camera frame.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from ._pose import Pose

CARLA_TO_ISO = np.diag([1.0, -1.0, 1.0])
"""Reflection between CARLA/Unreal coordinates and ISO 8855 coordinates (its own inverse)."""
UNREAL_CAMERA_TO_OPENCV = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])
"""A CARLA camera's local Unreal coordinates -> OpenCV camera coordinates: (x, y, z) -> (y, -z, x)."""


def carla_to_iso(points: Float[ArrayLike, "*batch 3"]) -> Float[Array, "*batch 3"]:
    """CARLA/Unreal coordinates -> ISO 8855 coordinates (y flipped). Also for vectors."""
    p = jnp.asarray(points)
    return jnp.stack([p[..., 0], -p[..., 1], p[..., 2]], axis=-1)


def iso_to_carla(points: Float[ArrayLike, "*batch 3"]) -> Float[Array, "*batch 3"]:
    """ISO 8855 coordinates -> CARLA/Unreal coordinates (y flipped)."""
    return carla_to_iso(points)


def unreal_camera_to_opencv(points: Float[ArrayLike, "*batch 3"]) -> Float[Array, "*batch 3"]:
    """A CARLA camera's local Unreal coordinates ``(x fwd, y right, z up)`` -> OpenCV ``(y, -z, x)``."""
    p = jnp.asarray(points)
    return jnp.stack([p[..., 1], -p[..., 2], p[..., 0]], axis=-1)


def opencv_to_unreal_camera(points: Float[ArrayLike, "*batch 3"]) -> Float[Array, "*batch 3"]:
    """OpenCV camera coordinates -> the CARLA camera's local Unreal coordinates ``(z, x, -y)``."""
    p = jnp.asarray(points)
    return jnp.stack([p[..., 2], p[..., 0], -p[..., 1]], axis=-1)


def _as(m: np.ndarray, like: Array) -> Array:
    return jnp.asarray(m, dtype=like.dtype)


def carla_pose_to_iso(pose: Pose) -> Pose:
    """A pose between two CARLA/Unreal frames -> the same pose between their ISO 8855 versions."""
    s = _as(CARLA_TO_ISO, pose.rotation_matrix)
    return Pose(s @ pose.rotation_matrix @ s, carla_to_iso(pose.translation))


def iso_pose_to_carla(pose: Pose) -> Pose:
    """Inverse of `carla_pose_to_iso` (the same operation)."""
    return carla_pose_to_iso(pose)


def carla_camera_pose_to_opencv(camera_to_parent_unreal: Pose) -> Pose:
    """A CARLA camera's transform (camera local -> parent, Unreal) -> OpenCV camera -> ISO parent."""
    s = _as(CARLA_TO_ISO, camera_to_parent_unreal.rotation_matrix)
    m = _as(UNREAL_CAMERA_TO_OPENCV, camera_to_parent_unreal.rotation_matrix)
    r = s @ camera_to_parent_unreal.rotation_matrix @ m.T
    return Pose(r, carla_to_iso(camera_to_parent_unreal.translation))


def opencv_camera_pose_to_carla(camera_to_parent_iso: Pose) -> Pose:
    """OpenCV camera -> ISO parent pose (e.g. a WoodScape calibration) -> the CARLA camera
    transform (camera local -> parent, Unreal) that mounts it; see `Pose.as_carla` for angles."""
    s = _as(CARLA_TO_ISO, camera_to_parent_iso.rotation_matrix)
    m = _as(UNREAL_CAMERA_TO_OPENCV, camera_to_parent_iso.rotation_matrix)
    r = s @ camera_to_parent_iso.rotation_matrix @ m
    return Pose(r, iso_to_carla(camera_to_parent_iso.translation))
