"""The embedded street scene as data: a pytree of primitives and object poses, plus actor metadata.

Frames and units (CARLA 0.9.10, CONVENTIONS §3):

- **world**: CARLA/Unreal, left-handed, x forward, y right, z up, metres; the ground is z = 0.
- **object / actor frame**: an object's local Unreal frame; its pose is a CARLA transform
  ``(location, (pitch, yaw, roll))`` with pitch = roll = 0 (every embedded object stays upright).
- Two instants per scene: index 0 is **t-1**, index 1 is **t** (``dt_s`` apart, 0.1 s by
  default). A render at fraction ``time`` in [0, 1] interpolates every pose linearly (location and
  yaw) between them, which is exact for the constant-velocity straight motion of the generator.
"""

from __future__ import annotations

import dataclasses
import math

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int, UInt32

from ..transforms import CARLA_TO_ISO, Pose

STATIC_OBJECT = 0
"""Object index of the static world (buildings, poles, vegetation, ...; actor id 0)."""
EGO_OBJECT = 1
"""Object index of the ego vehicle."""
TEXTURE_PLAIN, TEXTURE_CHECKER, TEXTURE_NOISE, TEXTURE_WINDOWS, TEXTURE_STRIPES = 0, 1, 2, 3, 4
"""Texture kinds of a primitive (object-local procedural patterns; see `docs/scene.md`)."""


class Scene(eqx.Module):
    """Everything the ray caster needs, as arrays (a pytree: pass it to jitted functions as an
    argument). Built by `generate_street`; primitive arrays are padded with inactive entries so that
    scenes of different seeds and frames share compiled functions.

    Objects (``O``): ``object_location (2, O, 3)`` metres and ``object_yaw_deg (2, O)`` at t-1 and t
    (world frame), ``object_actor_id (O,)`` (0 for the static world). Object 0 is the static world,
    object 1 the ego vehicle.

    Oriented boxes (``B``): centre ``box_center (B, 3)`` in the object frame, half sizes
    ``box_half_extent (B, 3)``, extra yaw in the object frame ``box_yaw_deg (B,)``.
    Upright capsules (``K``): segment midpoint ``capsule_center (K, 3)`` in the object frame, half
    length of the vertical segment ``capsule_half_length (K,)``, ``capsule_radius (K,)`` (a sphere
    when the half length is 0). Each primitive has an owning ``*_object`` index, a CARLA 0.9.10
    semantic ``*_tag``, a linear RGB ``*_albedo`` in [0, 1], a ``*_texture`` kind and
    ``*_texture_scale`` (metres), and ``*_active``.

    The ground (z = 0) is a straight road along world x: road ``|y| < road_half_width``, a centre
    line at y = 0 and dashed lane lines every ``lane_width``, sidewalks up to
    ``road_half_width + sidewalk_width``, terrain beyond. ``sun_direction`` (unit, world, pointing
    to the sun) shades every surface.

    ``textured`` (static) adds surface detail to every material (`jaxfish.scene.surface_detail`:
    grain, blotches and colour variation, a pure function of the surface point, ``texture_seed``
    and the material), for renders with the pixel statistics of a CARLA render; off, renders are
    the smooth procedural materials alone.
    """

    object_location: Float[Array, "2 O 3"]
    object_yaw_deg: Float[Array, "2 O"]
    object_actor_id: Int[Array, " O"]
    box_object: Int[Array, " B"]
    box_center: Float[Array, "B 3"]
    box_half_extent: Float[Array, "B 3"]
    box_yaw_deg: Float[Array, " B"]
    box_tag: Int[Array, " B"]
    box_albedo: Float[Array, "B 3"]
    box_texture: Int[Array, " B"]
    box_texture_scale: Float[Array, " B"]
    box_active: Bool[Array, " B"]
    capsule_object: Int[Array, " K"]
    capsule_center: Float[Array, "K 3"]
    capsule_half_length: Float[Array, " K"]
    capsule_radius: Float[Array, " K"]
    capsule_tag: Int[Array, " K"]
    capsule_albedo: Float[Array, "K 3"]
    capsule_texture: Int[Array, " K"]
    capsule_texture_scale: Float[Array, " K"]
    capsule_active: Bool[Array, " K"]
    road_half_width: Float[Array, ""]
    lane_width: Float[Array, ""]
    sidewalk_width: Float[Array, ""]
    sun_direction: Float[Array, " 3"]
    dt_s: float = eqx.field(static=True, default=0.1)
    textured: bool = eqx.field(static=True, default=False)
    texture_seed: UInt32[Array, ""] = eqx.field(default_factory=lambda: jnp.zeros((), jnp.uint32))

    def __check_init__(self):
        groups = {
            "object": ("object_location", "object_yaw_deg", "object_actor_id"),
            "box": ("box_object", "box_center", "box_half_extent", "box_yaw_deg", "box_tag", "box_albedo",
                    "box_texture", "box_texture_scale", "box_active"),
            "capsule": ("capsule_object", "capsule_center", "capsule_half_length", "capsule_radius", "capsule_tag",
                        "capsule_albedo", "capsule_texture", "capsule_texture_scale", "capsule_active"),
        }
        for group, names in groups.items():
            counts = {}
            for name in names:
                x = getattr(self, name)
                if not hasattr(x, "shape"):
                    return  # a partitioned / transformed pytree, not a constructed scene
                axis = 1 if name in ("object_location", "object_yaw_deg") else 0
                counts[name] = x.shape[axis] if x.ndim > axis else None
            if len(set(counts.values())) != 1:
                raise ValueError(f"Scene: the {group} fields disagree on their count: {counts}")
        if self.object_location.shape[:1] != (2,) or self.object_yaw_deg.shape[:1] != (2,):
            raise ValueError("Scene: object_location and object_yaw_deg need a leading axis of 2 (t-1, t)")
        if self.dt_s <= 0:
            raise ValueError(f"Scene: dt_s must be positive, got {self.dt_s}")

    @property
    def num_objects(self) -> int:
        """Number of objects ``O`` (static world, ego, actors)."""
        return int(self.object_yaw_deg.shape[-1])

    def object_poses(self, time) -> tuple[Float[Array, "O 3"], Float[Array, " O"]]:
        """``(location (O, 3), yaw (O,) radians)`` of every object at fraction ``time`` of the
        interval (0 = t-1, 1 = t), interpolated linearly (yaw along the shorter arc). The ends are
        exact: ``time`` 0 and 1 give the stored poses bit for bit, so that a scene whose t-1 poses
        are another scene's t poses renders its t-1 exactly as the other renders t."""
        dtype = self.object_location.dtype
        a = jnp.asarray(time, dtype)
        loc = (1 - a) * self.object_location[0] + a * self.object_location[1]  # exact at a = 0 and a = 1
        y0 = jnp.deg2rad(self.object_yaw_deg[0])
        y1 = jnp.deg2rad(self.object_yaw_deg[1])
        dy = jnp.mod(y1 - y0 + jnp.pi, 2 * jnp.pi) - jnp.pi
        return loc, jnp.where(a == 1, y1, y0 + a * dy)

    def object_to_world(self, time) -> Pose:
        """CARLA transforms (object frame -> world, Unreal) of every object at ``time``, batched ``(O,)``."""
        loc, yaw = self.object_poses(time)
        return Pose(_yaw_matrix(yaw), loc)

    def ego_to_world(self, time) -> Pose:
        """The ego vehicle's CARLA transform (actor frame -> world, Unreal) at ``time``."""
        loc, yaw = self.object_poses(time)
        return Pose(_yaw_matrix(yaw[EGO_OBJECT]), loc[EGO_OBJECT])

    def vehicle_to_world(self, time) -> Pose:
        """ISO 8855 ego vehicle frame (x forward, y left, z up; the actor frame with y flipped)
        -> CARLA world. Its rotation has determinant -1 (it changes handedness)."""
        ego = self.ego_to_world(time)
        s = jnp.asarray(CARLA_TO_ISO, ego.rotation_matrix.dtype)
        return Pose(ego.rotation_matrix @ s, ego.translation)

    def camera_to_world(self, camera_to_vehicle: Pose, time) -> Pose:
        """OpenCV camera frame of a camera mounted on the ego vehicle (``camera_to_vehicle`` in ISO
        8855, as `Calibration.camera_to_vehicle`) -> CARLA world, at ``time``."""
        dtype = self.object_location.dtype
        mount = Pose(camera_to_vehicle.rotation_matrix, camera_to_vehicle.translation, dtype=dtype)
        return self.vehicle_to_world(time) @ mount

    def move_points(self, object_index: Int[Array, "*batch"], points: Float[Array, "*batch 3"], time_from, time_to) -> Float[Array, "*batch 3"]:
        """Where world points rigidly attached to objects at ``time_from`` are at ``time_to``.

        ``object_index < 0`` (ground, sky) and the static world (0) do not move.
        """
        loc_a, yaw_a = self.object_poses(time_from)
        loc_b, yaw_b = self.object_poses(time_to)
        idx = jnp.clip(object_index, 0, self.num_objects - 1)
        rel = points - loc_a[idx]
        dyaw = yaw_b[idx] - yaw_a[idx]
        c, s = jnp.cos(dyaw), jnp.sin(dyaw)
        x = c * rel[..., 0] - s * rel[..., 1]
        y = s * rel[..., 0] + c * rel[..., 1]
        moved = jnp.stack([x, y, rel[..., 2]], axis=-1) + loc_b[idx]
        return jnp.where((object_index > STATIC_OBJECT)[..., None], moved, points)


def _yaw_matrix(yaw: Float[Array, "*batch"]) -> Float[Array, "*batch 3 3"]:
    c, s = jnp.cos(yaw), jnp.sin(yaw)
    z, o = jnp.zeros_like(c), jnp.ones_like(c)
    rows = [[c, -s, z], [s, c, z], [z, z, o]]
    return jnp.stack([jnp.stack(r, axis=-1) for r in rows], axis=-2)


@dataclasses.dataclass(frozen=True)
class Actor:
    """A dynamic actor (or the ego vehicle) as a CARLA client would read it.

    - `id`: CARLA-style actor id (unique over a recording); `type_id`: blueprint-like name;
    - `category`: ``"ego"``, ``"four_wheeler"``, ``"two_wheeler"`` or ``"pedestrian"``;
    - `semantic_tag`: CARLA 0.9.10 tag of its pixels (10 vehicle, 4 pedestrian);
    - `object_index`: its index in the `Scene` object arrays;
    - `bbox_location`, `bbox_extent`: box centre in the **actor** frame and **half** sizes (metres),
      as ``actor.bounding_box``; the box encloses every primitive of the actor exactly;
    - `location_prev`, `rotation_prev`, `location`, `rotation`: CARLA transforms at t-1 and t
      (world, metres; ``(pitch, yaw, roll)`` degrees);
    - `velocity` (m/s, world) and `angular_velocity` (deg/s, world) at t, as ``get_velocity()`` /
      ``get_angular_velocity()``.
    """

    id: int
    type_id: str
    category: str
    semantic_tag: int
    object_index: int
    bbox_location: tuple[float, float, float]
    bbox_extent: tuple[float, float, float]
    location_prev: tuple[float, float, float]
    rotation_prev: tuple[float, float, float]
    location: tuple[float, float, float]
    rotation: tuple[float, float, float]
    velocity: tuple[float, float, float]
    angular_velocity: tuple[float, float, float]

    @property
    def displacement_m(self) -> float:
        """Distance the actor origin moved between t-1 and t (metres)."""
        return float(math.dist(self.location_prev, self.location))

    def bbox_corners(self, which: str = "t") -> np.ndarray:
        """The 8 box corners in world coordinates at ``"t"`` or ``"t-1"`` (CARLA frame), ``(8, 3)``."""
        loc, rot = (self.location, self.rotation) if which == "t" else (self.location_prev, self.rotation_prev)
        yaw = math.radians(rot[1])
        c, s = math.cos(yaw), math.sin(yaw)
        r = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], float)
        local = np.asarray(self.bbox_location) + signs * np.asarray(self.bbox_extent)
        return local @ r.T + np.asarray(loc)


@dataclasses.dataclass(frozen=True)
class EgoMotion:
    """The ego vehicle's motion at t (world, CARLA frame): `velocity` (m/s), `acceleration`
    (m/s², without gravity), `angular_velocity` (deg/s, about world z; positive = yaw increasing,
    i.e. turning right in CARLA's left-handed frame)."""

    velocity: tuple[float, float, float]
    acceleration: tuple[float, float, float]
    angular_velocity: tuple[float, float, float]


@dataclasses.dataclass(frozen=True)
class StreetFrame:
    """One frame of the embedded world: the `Scene` (poses at t-1 and t), its actors and timing.

    `timestamp_s` is the simulation time of t (t-1 is ``timestamp_s - dt_s``); `frame` counts frames
    from 0; `actors[0]` is the ego vehicle.
    """

    scene: Scene
    actors: tuple[Actor, ...]
    ego_motion: EgoMotion
    frame: int
    seed: int
    timestamp_s: float
    dt_s: float

    @property
    def ego(self) -> Actor:
        """The ego vehicle's `Actor` record."""
        return self.actors[0]

    def actor_by_id(self, actor_id: int) -> Actor:
        """The actor with CARLA-style id ``actor_id`` (``KeyError`` if none)."""
        for a in self.actors:
            if a.id == actor_id:
                return a
        raise KeyError(f"no actor with id {actor_id} in frame {self.frame}")
