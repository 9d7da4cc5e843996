"""3D boxes of actors (CARLA bounding boxes) as a batched pytree, with CARLA's box bugs fixed."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from ..transforms import Pose
from ._classes import CATEGORY_CLASS, CLASS_PEDESTRIAN, CLASS_TWO_WHEELER

TWO_WHEELER_FALLBACK_HALF_EXTENT: tuple[float, float, float] = (1.0, 0.45, 0.85)
"""Half extents (metres, actor frame x forward, y right, z up) substituted for the zero (or
near-zero, below `DEGENERATE_EXTENT_M`) axes of two-wheeler boxes (CARLA <= 0.9.14 bug)."""
DEGENERATE_EXTENT_M = 0.05
"""An extent below this (metres) is treated as missing."""
PEDESTRIAN_PADDING_M: tuple[float, float, float] = (0.2, 0.2, 0.1)
"""Padding (metres) added to pedestrian half extents ``(x, y, z)``: CARLA's walker boxes come from
the collision capsule and miss arms, bags and hair."""
CORNER_SIGNS: np.ndarray = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=np.float64)
"""Sign pattern of the 8 box corners: corner ``k = 4 ix + 2 iy + iz`` has sign ``(-1)^(1 - i)`` on
each box axis, i.e. CARLA's ``BoundingBox.get_local_vertices`` order
``(---), (--+), (-+-), (-++), (+--), (+-+), (++-), (+++)``."""


class Boxes3D(eqx.Module):
    """Oriented 3D boxes of ``B`` actors at one instant (a pytree; pad with inactive boxes to keep
    shapes fixed across frames).

    - `box_to_world`: batched `Pose` ``(B,)``: box frame (centred on the box, axes along its edges,
      CARLA actor axes x forward, y right, z up) -> CARLA world, metres;
    - `half_extent` ``(B, 3)``: half sizes (metres, CARLA's ``extent``), after `fix_carla_extents`;
    - `actor_id` ``(B,)``: CARLA actor ids; `class_id` ``(B,)``: SynWoodScape class of the box
      (10 vehicle, 21 two-wheeler, 4 pedestrian, 24 ego); `active` ``(B,)``: False for padding.
    """

    box_to_world: Pose
    half_extent: Float[Array, "B 3"]
    actor_id: Int[Array, " B"]
    class_id: Int[Array, " B"]
    active: Bool[Array, " B"]

    @property
    def num_boxes(self) -> int:
        """Number of box slots ``B`` (active or not)."""
        return int(self.actor_id.shape[-1])

    def corners(self) -> Float[Array, "B 8 3"]:
        """The 8 corners of every box in CARLA world coordinates (order: `CORNER_SIGNS`)."""
        local = jnp.asarray(CORNER_SIGNS, self.half_extent.dtype) * self.half_extent[..., None, :]
        rot = self.box_to_world.rotation_matrix
        return jnp.einsum("...ij,...kj->...ki", rot, local) + self.box_to_world.translation[..., None, :]

    def contains(self, points_world: Float[Array, "*batch 3"], box: Int[Array, "*batch"], *, margin_m: float = 0.0) -> Bool[Array, "*batch"]:
        """Whether each point lies inside box ``box`` (six-plane test, half extents grown by ``margin_m``)."""
        local = _to_box(self, points_world, box)
        h = self.half_extent[box] + jnp.asarray(margin_m, self.half_extent.dtype)
        return jnp.all(jnp.abs(local) <= h, axis=-1)


def _to_box(boxes: Boxes3D, points: Array, box: Array) -> Array:
    rot = boxes.box_to_world.rotation_matrix[box]
    d = points - boxes.box_to_world.translation[box]
    return jnp.einsum("...ji,...j->...i", rot, d)


def fix_carla_extents(half_extent: np.ndarray, class_id: np.ndarray) -> np.ndarray:
    """CARLA's box bugs, fixed (NumPy, ``(B, 3)`` half extents, metres):

    - two-wheelers (class 21): every axis below `DEGENERATE_EXTENT_M` takes
      `TWO_WHEELER_FALLBACK_HALF_EXTENT` (CARLA up to 0.9.14 reports zero y, or x and y, extents);
    - pedestrians (class 4): half extents grown by `PEDESTRIAN_PADDING_M` (capsule-sized boxes);
    - any other degenerate axis is raised to `DEGENERATE_EXTENT_M`.
    """
    h = np.array(half_extent, dtype=np.float64, copy=True).reshape(-1, 3)
    c = np.asarray(class_id).reshape(-1)
    tw = c == CLASS_TWO_WHEELER
    fb = np.broadcast_to(np.asarray(TWO_WHEELER_FALLBACK_HALF_EXTENT), h.shape)
    h = np.where(tw[:, None] & (h < DEGENERATE_EXTENT_M), fb, h)
    h = np.where((c == CLASS_PEDESTRIAN)[:, None], h + np.asarray(PEDESTRIAN_PADDING_M), h)
    return np.maximum(h, DEGENERATE_EXTENT_M)


def _carla_rotation_np(pyr: np.ndarray) -> np.ndarray:
    """CARLA ``get_matrix()`` rotation blocks ``(B, 3, 3)`` of ``(pitch, yaw, roll)`` degrees, in NumPy float64."""
    p, y, r = (np.deg2rad(pyr[:, i]) for i in range(3))
    cp, sp, cy, sy, cr, sr = np.cos(p), np.sin(p), np.cos(y), np.sin(y), np.cos(r), np.sin(r)
    rows = [[cp * cy, cy * sp * sr - sy * cr, -cy * sp * cr - sy * sr],
            [cp * sy, sy * sp * sr + cy * cr, -sy * sp * cr + cy * sr],
            [sp, -cp * sr, cp * cr]]
    return np.stack([np.stack(row, axis=-1) for row in rows], axis=-2)


def boxes_from_carla(
    actor_id: Sequence[int],
    class_id: Sequence[int],
    location: np.ndarray,
    rotation: np.ndarray,
    bbox_location: np.ndarray,
    bbox_extent: np.ndarray,
    *,
    fix_extents: bool = True,
    pad_to: int | None = None,
    dtype=jnp.float32,
) -> Boxes3D:
    """`Boxes3D` from CARLA actor data (NumPy in, arrays out):

    ``location (B, 3)`` and ``rotation (B, 3)`` ``(pitch, yaw, roll)`` degrees are the actors'
    transforms (world); ``bbox_location (B, 3)`` the box centre in the **actor** frame and
    ``bbox_extent (B, 3)`` its **half** size (``actor.bounding_box``). ``fix_extents`` applies
    `fix_carla_extents`; ``pad_to`` pads with inactive boxes up to that many slots.
    """
    ids = np.asarray(actor_id, np.int64).reshape(-1)
    cls = np.asarray(class_id, np.int64).reshape(-1)
    n = ids.shape[0]
    loc = np.asarray(location, np.float64).reshape(n, 3)
    rot = np.asarray(rotation, np.float64).reshape(n, 3)
    bl = np.asarray(bbox_location, np.float64).reshape(n, 3)
    ext = np.asarray(bbox_extent, np.float64).reshape(n, 3)
    if fix_extents:
        ext = fix_carla_extents(ext, cls)
    m = max(n, int(pad_to or 0))
    if pad_to is not None and pad_to < n:
        raise ValueError(f"boxes_from_carla: pad_to={pad_to} is smaller than the {n} actors")
    pad = m - n
    r = _carla_rotation_np(np.pad(rot, ((0, pad), (0, 0))))
    centre = np.einsum("bij,bj->bi", r, np.pad(bl, ((0, pad), (0, 0)))) + np.pad(loc, ((0, pad), (0, 0)))
    # Padding boxes sit far below the ground with a tiny extent: they never contain anything.
    centre[n:] = (0.0, 0.0, -1e6)
    return Boxes3D(
        box_to_world=Pose(r, centre, dtype=dtype),
        half_extent=jnp.asarray(np.pad(ext, ((0, pad), (0, 0)), constant_values=DEGENERATE_EXTENT_M), dtype),
        actor_id=jnp.asarray(np.pad(ids, (0, pad)), jnp.int32),
        class_id=jnp.asarray(np.pad(cls, (0, pad), constant_values=-1), jnp.int32),
        active=jnp.asarray(np.arange(m) < n),
    )


def boxes_from_actors(
    actors: Sequence[Mapping[str, Any]], instant: str = "t", *, fix_extents: bool = True, pad_to: int | None = None,
    include_ego: bool = True, dtype=jnp.float32,
) -> Boxes3D:
    """`Boxes3D` of the actors of a capture frame (the dicts of ``actors.json``: ``id``,
    ``category``, ``bounding_box {location, extent}``, ``transform``/``transform_prev``
    ``{location, rotation}``) at ``instant`` ``"t"`` or ``"t-1"``, in the list's order."""
    if instant not in ("t", "t-1"):
        raise ValueError(f"boxes_from_actors: instant must be 't' or 't-1', got {instant!r}")
    key = "transform" if instant == "t" else "transform_prev"
    sel = [a for a in actors if include_ego or a.get("category") != "ego"]
    for a in sel:
        if a.get("category") not in CATEGORY_CLASS:
            raise ValueError(f"boxes_from_actors: actor {a.get('id')} has unknown category {a.get('category')!r}; "
                             f"expected one of {sorted(CATEGORY_CLASS)}")
    get = lambda f: np.asarray([f(a) for a in sel], np.float64).reshape(-1, 3)  # noqa: E731
    return boxes_from_carla(
        [a["id"] for a in sel], [CATEGORY_CLASS[a["category"]] for a in sel],
        get(lambda a: a[key]["location"]), get(lambda a: a[key]["rotation"]),
        get(lambda a: a["bounding_box"]["location"]), get(lambda a: a["bounding_box"]["extent"]),
        fix_extents=fix_extents, pad_to=pad_to, dtype=dtype,
    )


def boxes_in_frame(boxes: Boxes3D, world_to_frame: Pose) -> Float[Array, "B 8 3"]:
    """Box corners in another frame, e.g. the ISO 8855 vehicle frame with
    ``world_to_frame = vehicle_to_world.inverse()``."""
    return world_to_frame.apply(boxes.corners())
