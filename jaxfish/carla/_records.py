"""CARLA actors and snapshots -> the capture's actor and ego records (`jaxfish.scene.Actor`,
`jaxfish.scene.EgoMotion`, `jaxfish.scene.StreetFrame`)."""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence

from ..scene import Actor, EgoMotion, StreetFrame
from ._version import CarlaCaptureError

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

def _vec(v) -> tuple[float, float, float]:
    return float(v.x), float(v.y), float(v.z)



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

