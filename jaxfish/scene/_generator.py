"""The procedural street generator: a seeded, deterministic world evaluated at any frame."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Mapping

import jax.numpy as jnp
import numpy as np

from ..calibration import Calibration
from ._model import (
    EGO_OBJECT,
    STATIC_OBJECT,
    TEXTURE_CHECKER,
    TEXTURE_NOISE,
    TEXTURE_PLAIN,
    TEXTURE_STRIPES,
    TEXTURE_WINDOWS,
    Actor,
    EgoMotion,
    Scene,
    StreetFrame,
)
from ._tags import CARLA_SEMANTIC_TAGS as TAGS
from ._texture import seed_u32

DEFAULT_DT_S = 0.1
"""Frame interval of a capture (seconds): 10 FPS as SynWoodScape."""
_T0_S = 1.0
"""Simulation time of frame 0's t-1 instant (seconds)."""
_PAD = 32
"""Primitive arrays are padded to a multiple of this (inactive entries), to share compilations."""
FIRST_ACTOR_ID = 100
"""Actor ids start here (CARLA-style integers); the ego is the first."""
_ROAD_HALF_WIDTH = 7.0
_LANE_WIDTH = 3.5
_SIDEWALK_WIDTH = 4.0
_EGO_LANE_Y = 1.75  # CARLA y is right: the ego drives in the inner right lane along +x


@dataclasses.dataclass
class _Prim:
    kind: str  # "box" | "capsule"
    obj: int
    center: tuple[float, float, float]
    size: tuple[float, float, float]  # box half extents, or (half_length, radius, 0)
    yaw_deg: float
    tag: int
    albedo: tuple[float, float, float]
    texture: int
    texture_scale: float


@dataclasses.dataclass
class _Mover:
    """A dynamic object: analytic pose ``(location (3,), yaw_deg)`` as a function of time (s)."""

    actor_id: int
    type_id: str
    category: str
    tag: int
    pose: Callable[[float], tuple[np.ndarray, float]]


def _straight(x0: float, y0: float, yaw_deg: float, speed: float) -> Callable[[float], tuple[np.ndarray, float]]:
    c, s = math.cos(math.radians(yaw_deg)), math.sin(math.radians(yaw_deg))

    def pose(t: float) -> tuple[np.ndarray, float]:
        return np.array([x0 + speed * t * c, y0 + speed * t * s, 0.0]), yaw_deg

    return pose


def _weaving(x0: float, y0: float, speed: float, amplitude: float, omega: float) -> Callable[[float], tuple[np.ndarray, float]]:
    def pose(t: float) -> tuple[np.ndarray, float]:
        y = y0 + amplitude * math.sin(omega * t)
        yaw = math.degrees(math.atan2(amplitude * omega * math.cos(omega * t), speed))
        return np.array([x0 + speed * t, y, 0.0]), yaw

    return pose


def _rgb(rng: np.random.Generator, lo: float = 0.15, hi: float = 0.9) -> tuple[float, float, float]:
    return tuple(float(v) for v in rng.uniform(lo, hi, 3))


def ego_body_boxes(rig: Mapping[str, Calibration] | None) -> list[tuple[tuple[float, float, float], tuple[float, float, float]]]:
    """The ego body as ``[(centre, half extents)]`` boxes in the ego **CARLA actor** frame, sized to
    stay strictly inside the rig's cameras: every camera is outside the body (a box containing a
    camera, e.g. below a roof camera, is lowered under it or dropped)."""
    if rig:
        t = np.stack([np.asarray(c.camera_to_vehicle.translation, np.float64) for c in rig.values()])
        t[:, 1] *= -1.0  # ISO -> CARLA
        x_lo, x_hi = float(t[:, 0].min()) + 0.08, float(t[:, 0].max()) - 0.08
        side = np.abs(t[:, 1])[np.abs(t[:, 1]) > 0.3]
        half_w = float(side.min()) - 0.1 if side.size else 0.95
        z_cam = float(t[:, 2].min())
    else:
        x_lo, x_hi, half_w, z_cam = -1.0, 3.6, 0.95, 0.6
    if x_hi - x_lo < 1.0:
        x_lo, x_hi = min(x_lo, -1.0), max(x_hi, 1.5)
    half_w = min(max(half_w, 0.4), 1.0)
    top = max(0.9, min(z_cam + 0.3, 1.05))
    length = x_hi - x_lo
    lower = ((0.5 * (x_lo + x_hi), 0.0, 0.5 * (0.3 + top)), (0.5 * length, half_w, 0.5 * (top - 0.3)))
    cabin_lo, cabin_hi = x_lo + 0.25 * length, x_hi - 0.35 * length
    cabin = ((0.5 * (cabin_lo + cabin_hi), 0.0, top + 0.25), (0.5 * (cabin_hi - cabin_lo), 0.85 * half_w, 0.25))
    boxes = [lower, cabin]
    if not rig:
        return boxes
    kept = []
    for c, h in boxes:  # keep every camera outside the body: lower a box's top below a camera in it
        c, h = np.asarray(c, float), np.asarray(h, float)
        inside = np.all(np.abs(t - c) < h + 0.02, axis=-1)
        if np.any(inside):
            bottom, top_ = c[2] - h[2], min(c[2] + h[2], float(t[inside, 2].min()) - 0.05)
            if top_ - bottom < 0.1:
                continue
            c[2], h[2] = 0.5 * (bottom + top_), 0.5 * (top_ - bottom)
        kept.append((tuple(float(v) for v in c), tuple(float(v) for v in h)))
    return kept


class _World:
    """The static layout and actor kinematics of one seed (pure numpy, deterministic)."""

    def __init__(self, seed: int, rig: Mapping[str, Calibration] | None, *, n_vehicles: int, n_two_wheelers: int, n_pedestrians: int):
        rng = np.random.default_rng(seed)
        self.seed = seed
        self.prims: list[_Prim] = []
        self.movers: list[_Mover] = []
        self._static(rng)
        ego_speed = float(rng.uniform(6.0, 9.0))
        self.movers.append(
            _Mover(FIRST_ACTOR_ID, "vehicle.jaxfish.ego", "ego", TAGS["vehicle"],
                   _weaving(0.0, _EGO_LANE_Y, ego_speed, 0.25, 0.6))
        )
        for c, h in ego_body_boxes(rig):
            self._add(_Prim("box", EGO_OBJECT, c, h, 0.0, TAGS["vehicle"], (0.75, 0.1, 0.1), TEXTURE_NOISE, 0.3))
        self._dynamic(rng, ego_speed, n_vehicles, n_two_wheelers, n_pedestrians)

    def _add(self, p: _Prim) -> None:
        self.prims.append(p)

    # --------------------------------------------------------------------------------- static
    def _static(self, rng: np.random.Generator) -> None:
        sw_out = _ROAD_HALF_WIDTH + _SIDEWALK_WIDTH
        for side in (-1.0, 1.0):
            x = -120.0
            while x < 280.0:
                width = float(rng.uniform(8.0, 20.0))
                depth = float(rng.uniform(8.0, 14.0))
                height = float(rng.uniform(6.0, 26.0))
                setback = sw_out + 1.5 + float(rng.uniform(0.0, 2.5))
                cx, cy = x + width / 2, side * (setback + depth / 2)
                colour = _rgb(rng, 0.35, 0.85)
                self._add(_Prim("box", STATIC_OBJECT, (cx, cy, height / 2), (width / 2, depth / 2, height / 2), 0.0,
                                TAGS["building"], colour, TEXTURE_WINDOWS, 3.0))
                gap = float(rng.uniform(0.0, 6.0))
                if gap > 2.0:  # fill some gaps with a wall or a fence
                    tag = TAGS["wall"] if rng.uniform() < 0.5 else TAGS["fence"]
                    hh = 0.6 if tag == TAGS["wall"] else 0.5
                    thick = 0.15 if tag == TAGS["wall"] else 0.03
                    self._add(_Prim("box", STATIC_OBJECT, (x + width + gap / 2, side * (sw_out + 0.6), hh), (gap / 2, thick, hh),
                                    0.0, tag, (0.6, 0.6, 0.55) if tag == TAGS["wall"] else (0.35, 0.3, 0.25),
                                    TEXTURE_CHECKER if tag == TAGS["wall"] else TEXTURE_STRIPES, 0.4 if tag == TAGS["wall"] else 0.15))
                x += width + gap
            # street furniture on the sidewalk edge
            x = -100.0 + float(rng.uniform(0.0, 10.0))
            while x < 250.0:
                y_edge = side * (_ROAD_HALF_WIDTH + 0.5)
                what = rng.uniform()
                if what < 0.45:  # street lamp pole
                    self._add(_Prim("capsule", STATIC_OBJECT, (x, y_edge, 3.0), (2.9, 0.1, 0.0), 0.0, TAGS["pole"],
                                    (0.45, 0.45, 0.48), TEXTURE_STRIPES, 0.5))
                elif what < 0.65:  # traffic sign
                    self._add(_Prim("capsule", STATIC_OBJECT, (x, y_edge, 1.2), (1.15, 0.05, 0.0), 0.0, TAGS["pole"],
                                    (0.5, 0.5, 0.5), TEXTURE_PLAIN, 1.0))
                    self._add(_Prim("box", STATIC_OBJECT, (x, y_edge, 2.6), (0.04, 0.4, 0.4), 0.0, TAGS["trafficsign"],
                                    (0.85, 0.1, 0.1), TEXTURE_CHECKER, 0.2))
                elif what < 0.78:  # traffic light
                    self._add(_Prim("capsule", STATIC_OBJECT, (x, y_edge, 2.0), (1.9, 0.08, 0.0), 0.0, TAGS["pole"],
                                    (0.3, 0.3, 0.3), TEXTURE_PLAIN, 1.0))
                    self._add(_Prim("box", STATIC_OBJECT, (x, y_edge - side * 0.1, 4.3), (0.2, 0.2, 0.5), 0.0, TAGS["trafficlight"],
                                    (0.15, 0.15, 0.12), TEXTURE_STRIPES, 0.33))
                else:  # tree
                    y_tree = side * (sw_out - 1.0)
                    self._add(_Prim("capsule", STATIC_OBJECT, (x, y_tree, 1.5), (1.5, 0.15, 0.0), 0.0, TAGS["vegetation"],
                                    (0.35, 0.25, 0.15), TEXTURE_NOISE, 0.2))
                    r = float(rng.uniform(1.2, 2.0))
                    self._add(_Prim("capsule", STATIC_OBJECT, (x, y_tree, 3.0 + r), (float(rng.uniform(0.0, 0.8)), r, 0.0), 0.0,
                                    TAGS["vegetation"], (0.15, float(rng.uniform(0.35, 0.55)), 0.12), TEXTURE_NOISE, 0.25))
                x += float(rng.uniform(8.0, 20.0))

    # --------------------------------------------------------------------------------- dynamic
    def _dynamic(self, rng: np.random.Generator, ego_speed: float, n_vehicles: int, n_two_wheelers: int, n_pedestrians: int) -> None:
        lanes = [(_EGO_LANE_Y, 0.0, ego_speed), (_EGO_LANE_Y + _LANE_WIDTH, 0.0, float(rng.uniform(8.0, 12.0))),
                 (-_EGO_LANE_Y, 180.0, float(rng.uniform(7.0, 11.0))), (-_EGO_LANE_Y - _LANE_WIDTH, 180.0, float(rng.uniform(5.0, 9.0)))]
        occupied: dict[int, list[float]] = {i: [] for i in range(len(lanes) + 2)}
        occupied[0] = [0.0]  # the ego is at x = 0 at simulation time 0, in lane 0

        def free_x(slot: int, lo: float, hi: float, gap: float) -> float | None:
            for _ in range(50):
                x = float(rng.uniform(lo, hi))
                if all(abs(x - o) > gap for o in occupied[slot]):
                    occupied[slot].append(x)
                    return x
            return None

        next_id = FIRST_ACTOR_ID + 1
        road_users = [("four_wheeler", i) for i in range(n_vehicles)] + [("two_wheeler", i) for i in range(n_two_wheelers)]
        for category, i in road_users:
            parked = category == "four_wheeler" and i % 4 == 3
            if parked:
                side = 1.0 if rng.uniform() < 0.5 else -1.0
                slot, y, yaw, speed = (4 if side > 0 else 5), side * (_ROAD_HALF_WIDTH - 1.0), (0.0 if side > 0 else 180.0), 0.0
            else:
                slot = int(rng.integers(0, len(lanes)))
                y, yaw, speed = lanes[slot]
            x = free_x(slot, -50.0, 90.0, 12.0)
            if x is None:
                continue
            obj = len(self.movers) + 1
            if category == "four_wheeler":
                length, width, height = float(rng.uniform(3.8, 5.0)), float(rng.uniform(1.7, 2.0)), float(rng.uniform(1.4, 1.9))
                colour = _rgb(rng, 0.1, 0.95)
                self._add(_Prim("box", obj, (0.0, 0.0, 0.25 + 0.3 * height), (length / 2, width / 2, 0.3 * height), 0.0,
                                TAGS["vehicle"], colour, TEXTURE_NOISE, 0.3))
                self._add(_Prim("box", obj, (-0.1 * length, 0.0, 0.25 + 0.8 * height), (0.3 * length, 0.45 * width, 0.2 * height), 0.0,
                                TAGS["vehicle"], tuple(0.6 * c for c in colour), TEXTURE_STRIPES, 0.25))
                type_id = "vehicle.jaxfish.car"
            else:
                colour = _rgb(rng, 0.1, 0.9)
                self._add(_Prim("box", obj, (0.0, 0.0, 0.55), (0.9, 0.15, 0.35), 0.0, TAGS["vehicle"], colour, TEXTURE_STRIPES, 0.2))
                self._add(_Prim("capsule", obj, (0.0, 0.0, 1.35), (0.25, 0.25, 0.0), 0.0, TAGS["vehicle"], _rgb(rng), TEXTURE_NOISE, 0.15))
                type_id = "vehicle.jaxfish.bicycle"
            # x is the position at simulation time 0, where the ego is at x = 0
            self.movers.append(_Mover(next_id, type_id, category, TAGS["vehicle"], _straight(x, y, yaw, speed)))
            next_id += 1
        for _ in range(n_pedestrians):
            side = 1.0 if rng.uniform() < 0.5 else -1.0
            y = side * float(rng.uniform(_ROAD_HALF_WIDTH + 0.9, _ROAD_HALF_WIDTH + _SIDEWALK_WIDTH - 0.6))
            standing = rng.uniform() < 0.3
            speed = 0.0 if standing else float(rng.uniform(1.0, 1.6))
            yaw = float(rng.uniform(-180.0, 180.0)) if standing else (0.0 if rng.uniform() < 0.5 else 180.0)
            x = float(rng.uniform(-40.0, 60.0))
            height, radius = float(rng.uniform(1.6, 1.9)), float(rng.uniform(0.22, 0.3))
            obj = len(self.movers) + 1
            self._add(_Prim("capsule", obj, (0.0, 0.0, height / 2), (height / 2 - radius, radius, 0.0), 0.0,
                            TAGS["pedestrian"], _rgb(rng, 0.1, 0.8), TEXTURE_NOISE, 0.12))
            self.movers.append(_Mover(next_id, "walker.pedestrian.jaxfish", "pedestrian", TAGS["pedestrian"], _straight(x, y, yaw, speed)))
            next_id += 1

    # --------------------------------------------------------------------------------- evaluation
    def frame(self, frame: int, dt_s: float, textured: bool = False) -> StreetFrame:
        t_prev = _T0_S + frame * dt_s
        t_curr = _T0_S + (frame + 1) * dt_s  # bit for bit the next frame's t_prev
        n_obj = len(self.movers) + 1
        loc = np.zeros((2, n_obj, 3))
        yaw = np.zeros((2, n_obj))
        for i, m in enumerate(self.movers):
            for k, t in enumerate((t_prev, t_curr)):
                p, y = m.pose(t)
                loc[k, i + 1], yaw[k, i + 1] = p, y
        actor_ids = np.zeros(n_obj, np.int32)
        actor_ids[1:] = [m.actor_id for m in self.movers]
        scene = self._scene(loc, yaw, actor_ids, dt_s, textured)
        actors = []
        h = 1e-3
        for i, m in enumerate(self.movers):
            obj = i + 1
            p_a, y_a = m.pose(t_curr - h)
            p_b, y_b = m.pose(t_curr + h)
            vel = (p_b - p_a) / (2 * h)
            dyaw = (y_b - y_a + 180.0) % 360.0 - 180.0
            center, extent = self._bbox(obj)
            actors.append(Actor(
                id=m.actor_id, type_id=m.type_id, category=m.category, semantic_tag=m.tag, object_index=obj,
                bbox_location=center, bbox_extent=extent,
                location_prev=_tup(loc[0, obj]), rotation_prev=(0.0, float(yaw[0, obj]), 0.0),
                location=_tup(loc[1, obj]), rotation=(0.0, float(yaw[1, obj]), 0.0),
                velocity=_tup(vel), angular_velocity=(0.0, 0.0, float(dyaw / (2 * h))),
            ))
        ego = self.movers[0]
        p0, _ = ego.pose(t_curr - h)
        p1, y1 = ego.pose(t_curr)
        p2, _ = ego.pose(t_curr + h)
        motion = EgoMotion(
            velocity=_tup((p2 - p0) / (2 * h)),
            acceleration=_tup((p2 - 2 * p1 + p0) / (h * h)),
            angular_velocity=actors[0].angular_velocity,
        )
        return StreetFrame(scene, tuple(actors), motion, frame, self.seed, t_curr, dt_s)

    def _bbox(self, obj: int) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
        lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
        for p in self.prims:
            if p.obj != obj:
                continue
            c = np.asarray(p.center)
            if p.kind == "box":
                yaw = math.radians(p.yaw_deg)
                ca, sa = abs(math.cos(yaw)), abs(math.sin(yaw))
                hx, hy, hz = p.size
                h = np.array([ca * hx + sa * hy, sa * hx + ca * hy, hz])
            else:
                hl, r, _ = p.size
                h = np.array([r, r, hl + r])
            lo, hi = np.minimum(lo, c - h), np.maximum(hi, c + h)
        return _tup((lo + hi) / 2), _tup((hi - lo) / 2)

    def _scene(self, loc: np.ndarray, yaw: np.ndarray, actor_ids: np.ndarray, dt_s: float, textured: bool) -> Scene:
        f32 = jnp.float32
        boxes = [p for p in self.prims if p.kind == "box"]
        caps = [p for p in self.prims if p.kind == "capsule"]

        def pad(n: int) -> int:
            return max(_PAD, -(-n // _PAD) * _PAD)

        def arrays(prims: list[_Prim]) -> dict[str, np.ndarray]:
            n = pad(len(prims))
            out = dict(
                obj=np.zeros(n, np.int32), center=np.zeros((n, 3)), size=np.zeros((n, 3)), yaw=np.zeros(n),
                tag=np.zeros(n, np.int32), albedo=np.zeros((n, 3)), texture=np.zeros(n, np.int32),
                scale=np.ones(n), active=np.zeros(n, bool),
            )
            out["center"][:, 2] = -1000.0  # inactive entries sit far below the ground
            for i, p in enumerate(prims):
                out["obj"][i], out["center"][i], out["size"][i], out["yaw"][i] = p.obj, p.center, p.size, p.yaw_deg
                out["tag"][i], out["albedo"][i], out["texture"][i] = p.tag, p.albedo, p.texture
                out["scale"][i], out["active"][i] = p.texture_scale, True
            return out

        b, k = arrays(boxes), arrays(caps)
        sun = np.array([0.45, -0.35, 0.82])
        return Scene(
            object_location=jnp.asarray(loc, f32), object_yaw_deg=jnp.asarray(yaw, f32),
            object_actor_id=jnp.asarray(actor_ids, jnp.int32),
            box_object=jnp.asarray(b["obj"]), box_center=jnp.asarray(b["center"], f32),
            box_half_extent=jnp.asarray(b["size"], f32), box_yaw_deg=jnp.asarray(b["yaw"], f32),
            box_tag=jnp.asarray(b["tag"]), box_albedo=jnp.asarray(b["albedo"], f32), box_texture=jnp.asarray(b["texture"]),
            box_texture_scale=jnp.asarray(b["scale"], f32), box_active=jnp.asarray(b["active"]),
            capsule_object=jnp.asarray(k["obj"]), capsule_center=jnp.asarray(k["center"], f32),
            capsule_half_length=jnp.asarray(k["size"][:, 0], f32), capsule_radius=jnp.asarray(k["size"][:, 1], f32),
            capsule_tag=jnp.asarray(k["tag"]), capsule_albedo=jnp.asarray(k["albedo"], f32),
            capsule_texture=jnp.asarray(k["texture"]), capsule_texture_scale=jnp.asarray(k["scale"], f32),
            capsule_active=jnp.asarray(k["active"]),
            road_half_width=jnp.asarray(_ROAD_HALF_WIDTH, f32), lane_width=jnp.asarray(_LANE_WIDTH, f32),
            sidewalk_width=jnp.asarray(_SIDEWALK_WIDTH, f32), sun_direction=jnp.asarray(sun / np.linalg.norm(sun), f32),
            dt_s=float(dt_s), textured=bool(textured), texture_seed=jnp.asarray(seed_u32(self.seed)),
        )


def _tup(v) -> tuple[float, float, float]:
    a = np.asarray(v, dtype=np.float64)
    return (float(a[0]), float(a[1]), float(a[2]))


def generate_street(
    seed: int = 0,
    *,
    frame: int = 0,
    rig: Mapping[str, Calibration] | None = None,
    dt_s: float = DEFAULT_DT_S,
    n_vehicles: int = 12,
    n_two_wheelers: int = 3,
    n_pedestrians: int = 10,
    textured: bool = False,
) -> StreetFrame:
    """The embedded street scene of ``seed`` at frame ``frame`` (poses at t-1 and t, ``dt_s`` apart).

    Deterministic: the same arguments give the same scene. A straight four-lane road along world +x
    (right-hand traffic, CARLA frame: the ego drives along +x at y = +1.75 m with a gentle weave),
    sidewalks with poles, signs, traffic lights and trees, buildings, walls and fences; moving and
    parked cars, two-wheelers in the lanes, walking and standing pedestrians on the sidewalks.
    ``rig`` sizes the ego body so that every camera of the rig is outside it (default: jaxfish's rig
    proportions). Successive frames continue the same motion (frame k's t is frame k+1's t-1).
    ``textured`` gives every material surface detail (`Scene`, `surface_detail`) seeded by
    ``seed``; the geometry, labels and motion do not depend on it.
    """
    if frame < 0:
        raise ValueError(f"generate_street: frame must be >= 0, got {frame}")
    if dt_s <= 0:
        raise ValueError(f"generate_street: dt_s must be positive, got {dt_s}")
    world = _World(int(seed), rig, n_vehicles=n_vehicles, n_two_wheelers=n_two_wheelers, n_pedestrians=n_pedestrians)
    return world.frame(int(frame), float(dt_s), bool(textured))
