"""What a source hands the pipeline: one capture instant pair (t-1, t) of the whole vehicle.

A `Frame` holds decoded sensor data exactly as a CARLA-style capture stores it after decoding (CARLA
quantisation applied: 24-bit planar depth in metres, uint8 tags, DVS events in CARLA's dtype), so
every source (capture directory, embedded scene in memory, CARLA online) gives the pipeline the same
arrays for the same scene. Everything is immutable (`equinox.Module`); arrays are NumPy on the host.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import equinox as eqx
import numpy as np
from jaxtyping import Float, UInt8

from ..groundtruth import Boxes3D, boxes_from_actors, vehicle_to_world_from_carla
from ..transforms import Pose

BOX_SLOT_QUANTUM = 32
"""Box slots are allocated in multiples of this many (inactive padding), so that frames whose actor
counts differ (CARLA spawns and removes actors) share compiled programs instead of compiling per count."""

TAG_TABLES = ("0.9.10", "0.9.14")
"""CARLA semantic tag tables a frame may use: CARLA 0.9.10-0.9.13 or 0.9.14+."""


def box_slots(num_actors: int) -> int:
    """The number of box slots for ``num_actors`` actors: the next multiple of `BOX_SLOT_QUANTUM`
    (at least one quantum). Padding changes no output: inactive boxes own no pixel and no file row."""
    q = BOX_SLOT_QUANTUM
    return max(q, -(-int(num_actors) // q) * q)


class CubeFaces(eqx.Module):
    """One fisheye camera's cube faces at one instant, in the `RigConstants.faces` order.

    - `rgb` ``(F, S, S, 3)`` uint8;
    - `depth_m` ``(F, S, S)`` float32: CARLA planar depth in metres after CARLA's 24-bit
      quantisation (1000 = far / sky);
    - `semantic` ``(F, S, S)`` uint8: CARLA semantic tags (`Frame.carla_tags` table).
    """

    rgb: UInt8[np.ndarray, "F S S 3"]
    depth_m: Float[np.ndarray, "F S S"]
    semantic: UInt8[np.ndarray, "F S S"]


class CameraFrame(eqx.Module):
    """One fisheye camera's input: its cube faces at t-1 (`faces_prev`) and t (`faces`) and the DVS
    events of each face between them (`events`: one array per face, CARLA's DVS dtype
    ``x, y`` uint16, ``t`` int64 nanoseconds, ``pol`` bool; or an object whose ``np.asarray`` is
    that array, such as a capture's `jaxfish.io.DeferredEvents`: the pipeline converts each one
    when it maps that face's events and keeps no reference to the array)."""

    faces_prev: CubeFaces
    faces: CubeFaces
    events: tuple[np.ndarray, ...]


class ViewImages(eqx.Module):
    """A camera captured directly (no cube faces) at one instant: `rgb` ``(H, W, 3)`` uint8,
    `depth_m` ``(H, W)`` float32 planar depth (the orthographic BEV: distance from its image
    plane; CARLA 24-bit quantisation applied), `semantic` ``(H, W)`` uint8 CARLA tags."""

    rgb: UInt8[np.ndarray, "H W 3"]
    depth_m: Float[np.ndarray, "H W"]
    semantic: UInt8[np.ndarray, "H W"]


class ViewFrame(eqx.Module):
    """The BEV top view's input: `images_prev` (t-1), `images` (t) and its height map at t
    (`height_m` ``(H, W)`` float32 metres above the ground, or None: then derived from its depth)."""

    images_prev: ViewImages
    images: ViewImages
    height_m: Float[np.ndarray, "H W"] | None


class Motion(eqx.Module):
    """The frame's actors and ego motion, parsed once by the source.

    - `actors`: the actor records (``actors.json``'s ``actors`` list; `docs/capture_layout.md`);
    - `boxes_prev`, `boxes`: their `Boxes3D` at t-1 and t, padded to `box_slots` slots;
    - `vehicle_to_world_prev`, `vehicle_to_world`: ego vehicle (ISO 8855) -> CARLA world poses
      at t-1 and t (float32).
    """

    actors: tuple[dict[str, Any], ...] = eqx.field(static=True)
    boxes_prev: Boxes3D
    boxes: Boxes3D
    vehicle_to_world_prev: Pose
    vehicle_to_world: Pose

    def padded(self, slots: int) -> Motion:
        """This motion with its boxes padded to ``slots`` (>= the actors) box slots."""
        if slots == self.boxes.num_boxes:
            return self
        return Motion(self.actors, boxes_from_actors(self.actors, "t-1", pad_to=slots),
                      boxes_from_actors(self.actors, "t", pad_to=slots), self.vehicle_to_world_prev,
                      self.vehicle_to_world)


def motion_from_records(actors: Sequence[Mapping[str, Any]], ego: Mapping[str, Any]) -> Motion:
    """`Motion` of a frame from its actor records and ego record (``ego.json``: ``transform_prev``
    and ``transform`` ``{location, rotation}`` in CARLA units). Raises ``KeyError``, ``TypeError``
    or ``ValueError`` on a malformed record (sources name their file)."""
    records = tuple(dict(a) for a in actors)
    pad = box_slots(len(records))
    v2w_p = vehicle_to_world_from_carla(np.asarray(ego["transform_prev"]["location"], np.float32),
                                        np.asarray(ego["transform_prev"]["rotation"], np.float32))
    v2w = vehicle_to_world_from_carla(np.asarray(ego["transform"]["location"], np.float32),
                                      np.asarray(ego["transform"]["rotation"], np.float32))
    return Motion(records, boxes_from_actors(records, "t-1", pad_to=pad), boxes_from_actors(records, "t", pad_to=pad),
                  v2w_p, v2w)


class SensorRecords(eqx.Module):
    """The frame's other sensors, passed through to the sink unchanged.

    - `ego`: the ego record (``ego.json``: timestamps, transforms at t-1 and t, velocity,
      acceleration, angular velocity; CARLA world units);
    - `lidar` ``(N, 4)`` float32 ``x, y, z, intensity`` (sensor frame, Unreal axes);
    - `semantic_lidar`, `radar`: CARLA's raw record dtypes; `imu`, `gnss`: readings at t;
    - `lidar_to_vehicle`, `radar_to_vehicle` ``(4, 4)`` float64: the lidar's (also the semantic
      lidar's) and the radar's local Unreal frame -> ISO 8855 vehicle frame
      (`jaxfish.pipeline.sensor_to_vehicle_matrix` of the sensor's CARLA mount), or None when the
      source does not know the mount (then `jaxfish.pipeline.sensor_truth` refuses its points).
    """

    ego: dict[str, Any] = eqx.field(static=True)
    lidar: Float[np.ndarray, "N 4"]
    semantic_lidar: np.ndarray
    radar: np.ndarray
    imu: dict[str, Any] = eqx.field(static=True)
    gnss: dict[str, Any] = eqx.field(static=True)
    lidar_to_vehicle: Float[np.ndarray, "4 4"] | None = None
    radar_to_vehicle: Float[np.ndarray, "4 4"] | None = None


class Frame(eqx.Module):
    """One capture instant pair of the whole vehicle: what `sample_truth` turns into a sample.

    - `index`: the capture frame number (sample ``{index:05d}``);
    - `carla_tags`: the semantic tag table of its images (`TAG_TABLES`);
    - `cameras`: fisheye camera names, in the order of `camera_frames` and of the
      `RigConstants` cameras;
    - `camera_frames`: one `CameraFrame` per fisheye camera;
    - `motion`: actors and ego poses (`Motion`);
    - `bev`: the BEV top view (`ViewFrame`) or None when the source has none;
    - `sensors`: the other sensors (`SensorRecords`), or None when the source was asked for
      the cameras only.
    """

    index: int = eqx.field(static=True)
    carla_tags: str = eqx.field(static=True)
    cameras: tuple[str, ...] = eqx.field(static=True)
    camera_frames: tuple[CameraFrame, ...]
    motion: Motion
    bev: ViewFrame | None
    sensors: SensorRecords | None

    def __check_init__(self) -> None:
        if len(self.cameras) != len(self.camera_frames):
            raise ValueError(f"Frame {self.index}: {len(self.cameras)} camera names for {len(self.camera_frames)} "
                             "camera frames")
        if self.carla_tags not in TAG_TABLES:
            raise ValueError(f"Frame {self.index}: carla_tags must be one of {TAG_TABLES}, got {self.carla_tags!r}")


