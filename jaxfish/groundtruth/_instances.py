"""Instance and motion segmentation: every instance-class pixel's 3D point tested against the
oriented 3D boxes of the actors (six planes), with tile culling so that the cost is
``pixels x candidates`` rather than ``pixels x actors``."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float, Int, UInt8

from ._boxes3d import Boxes3D
from ._classes import CLASS_EGO, CLASS_PEDESTRIAN, CLASS_TWO_WHEELER, CLASS_VEHICLE

BOX_MARGIN_M = 0.05
"""Default growth of every box (metres) in the inside test: absorbs depth quantisation and the
sub-pixel error of the cube -> fisheye depth resampling."""
FALLBACK_DISTANCE_M = 0.3
"""Default distance (metres) within which an instance pixel in no box goes to the nearest
class-consistent box; farther pixels stay unassigned (actor id 0)."""
TILE_SIZE = 16
"""Default tile side (pixels) of the culling grid."""
MOTION_THRESHOLD_M = 0.5
"""Default motion threshold (metres of displacement between t-1 and t)."""


class InstanceMap(eqx.Module):
    """Per-pixel instance labels ``(H, W)``.

    - `box_index`: index into the `Boxes3D` (-1: no instance);
    - `actor_id`: CARLA actor id (0: no instance); `class_id`: the box's SynWoodScape class (-1);
    - `unassigned`: an instance-class pixel (vehicle, two-wheeler, pedestrian, ego) that lies in no
      class-consistent box, not even within the fallback distance;
    - `fallback`: assigned by the nearest-box fallback rather than lying inside a box.
    """

    box_index: Int[Array, "H W"]
    actor_id: Int[Array, "H W"]
    class_id: Int[Array, "H W"]
    unassigned: Bool[Array, "H W"]
    fallback: Bool[Array, "H W"]


def _pixel_groups(pixel_class: Array) -> Array:
    """Class group of a pixel: 0 none, 1 pedestrian, 2 vehicle-like (vehicle, two-wheeler, ego)."""
    veh = (pixel_class == CLASS_VEHICLE) | (pixel_class == CLASS_TWO_WHEELER) | (pixel_class == CLASS_EGO)
    return jnp.where(pixel_class == CLASS_PEDESTRIAN, 1, jnp.where(veh, 2, 0)).astype(jnp.int32)


def _tiles(x: Array, tile: int, fill) -> Array:
    """``(H, W, ...)`` -> ``(T, tile * tile, ...)`` (padded with ``fill``)."""
    h, w = x.shape[:2]
    th, tw = -(-h // tile), -(-w // tile)
    pad = [(0, th * tile - h), (0, tw * tile - w)] + [(0, 0)] * (x.ndim - 2)
    x = jnp.pad(x, pad, constant_values=fill)
    x = x.reshape((th, tile, tw, tile) + x.shape[2:])
    x = jnp.swapaxes(x, 1, 2)
    return x.reshape((th * tw, tile * tile) + x.shape[4:])


def _tile_blocks(x: Array, tile: int, fill) -> Array:
    """``(H, W, ...)`` -> ``(th, tile, tw, tile, ...)`` (padded with ``fill``; a reshape, no transpose)."""
    h, w = x.shape[:2]
    th, tw = -(-h // tile), -(-w // tile)
    pad = [(0, th * tile - h), (0, tw * tile - w)] + [(0, 0)] * (x.ndim - 2)
    return jnp.pad(x, pad, constant_values=fill).reshape((th, tile, tw, tile) + x.shape[2:])


def _tile_reduce(x: Array, tile: int, fill, op) -> Array:
    """Per-tile reduction ``op`` of ``(H, W, ...)`` -> ``(T, ...)`` in `_tiles` order, reducing the
    ``(th, tile, tw, tile)`` blocks in place (3x cheaper on CPU than reducing transposed tiles)."""
    r = op(_tile_blocks(x, tile, fill), axis=(1, 3))
    return r.reshape((r.shape[0] * r.shape[1],) + r.shape[2:])


def _candidates(points_world, pixel_class, boxes: Boxes3D, tile: int, reach: float):
    """Per tile, which boxes may hold one of its instance pixels: the world AABB of the tile's
    instance points against each box's world AABB grown by ``reach``. Returns ``(T, B)``."""
    dtype = points_world.dtype
    grp = _pixel_groups(pixel_class)
    use = grp > 0
    big = jnp.asarray(np.finfo(np.float32).max / 4, dtype)
    # Coordinate by coordinate: XLA:CPU reduces planes far faster than the interleaved (H, W, 3)
    # points (the same minima and maxima).
    lo = jnp.stack([_tile_reduce(jnp.where(use, points_world[..., i], big), tile, big, jnp.min) for i in range(3)], -1)
    hi = jnp.stack([_tile_reduce(jnp.where(use, points_world[..., i], -big), tile, -big, jnp.max) for i in range(3)], -1)
    has_ped = _tile_reduce(grp == 1, tile, False, jnp.any)
    has_veh = _tile_reduce(grp == 2, tile, False, jnp.any)
    c = boxes.corners().astype(dtype)
    r = jnp.asarray(reach, dtype)
    blo, bhi = jnp.min(c, axis=1) - r, jnp.max(c, axis=1) + r
    overlap = jnp.all((lo[:, None, :] <= bhi[None]) & (hi[:, None, :] >= blo[None]), axis=-1)
    ped_box = boxes.class_id == CLASS_PEDESTRIAN
    veh_box = (boxes.class_id == CLASS_VEHICLE) | (boxes.class_id == CLASS_TWO_WHEELER) | (boxes.class_id == CLASS_EGO)
    consistent = (has_ped[:, None] & ped_box[None]) | (has_veh[:, None] & veh_box[None])
    return overlap & consistent & boxes.active[None]


def max_box_candidates(
    points_world: Float[ArrayLike, "H W 3"], pixel_class: Int[ArrayLike, "H W"], boxes: Boxes3D, *,
    tile: int = TILE_SIZE, margin_m: float = BOX_MARGIN_M, fallback_m: float = FALLBACK_DISTANCE_M,
) -> int:
    """The largest number of candidate boxes of any culling tile (host value): the static
    ``max_candidates`` that makes `instance_segmentation` exact."""
    cand = _jit_candidates(jnp.asarray(points_world), jnp.asarray(pixel_class), boxes, tile, max(margin_m, fallback_m))
    return int(jnp.max(jnp.sum(cand, axis=-1))) if cand.size else 0


_jit_candidates = jax.jit(_candidates, static_argnums=(3, 4))


def instance_plan(
    points_world: Float[Array, "H W 3"], pixel_class: Int[Array, "H W"], boxes: Boxes3D, tile: int, reach: float,
) -> tuple[Int[Array, ""], Int[Array, ""], Int[Array, ""], Bool[Array, "T B"]]:
    """The culling plan of `instance_segmentation` (traceable; ``tile`` and ``reach`` are static):
    ``(most candidate boxes of any tile, number of tiles holding instance pixels, number of those
    with more than one candidate, the (T, B) candidate mask)`` over the ``T`` tiles of side
    ``tile`` and the ``B`` boxes. The three counts, read back on the host, size the static
    arguments of `assign_instances` (``k``, and ``capacity`` / ``capacity_many`` through
    `tile_capacity`); the mask is its ``cand``. ``points_world``: CARLA world points (metres);
    ``pixel_class``: SynWoodScape classes before the two-wheeler / ego split (-1: no pixel);
    ``reach``: the larger of the box margin and the fallback distance (metres)."""
    cand = _candidates(points_world, pixel_class, boxes, tile, reach)
    busy = _tile_reduce(_pixel_groups(pixel_class) > 0, tile, False, jnp.any)
    n_cand = jnp.sum(cand, axis=-1)
    return jnp.max(n_cand), jnp.sum(busy), jnp.sum(busy & (n_cand > 1)), cand


_jit_plan = jax.jit(instance_plan, static_argnums=(3, 4))


def tile_capacity(n: int) -> int:
    """Static capacity for ``n`` culling tiles holding instance pixels: the next power of two (at
    least 64), so that frames of similar content share one compilation."""
    return max(64, 1 << max(int(n) - 1, 0).bit_length())


def instance_segmentation(
    points_world: Float[ArrayLike, "H W 3"],
    pixel_class: Int[ArrayLike, "H W"],
    boxes: Boxes3D,
    *,
    valid: Bool[ArrayLike, "H W"] | None = None,
    margin_m: float = BOX_MARGIN_M,
    fallback_m: float = FALLBACK_DISTANCE_M,
    tile: int = TILE_SIZE,
    max_candidates: int | None = None,
    capacity: int | None = None,
    capacity_many: int | None = None,
) -> InstanceMap:
    """Assign every instance-class pixel to the actor whose 3D box holds its point.

    ``points_world`` are the pixels' 3D points (CARLA world, metres; `pixel_points` then the
    camera -> world pose); ``pixel_class`` their SynWoodScape class *before* the two-wheeler / ego
    split (`carla_to_synwoodscape` without ``box_class``). Rules (``docs/groundtruth.md``):

    1. only pixels of class pedestrian (4), vehicle (10), two-wheeler (21) or ego (24) are tested,
       and only against class-consistent boxes: pedestrian pixels against pedestrian boxes,
       vehicle-like pixels against vehicle, two-wheeler and ego boxes;
    2. a point is inside a box when all six plane tests pass with the half extents grown by
       ``margin_m``; inside several boxes it goes to the one it is deepest in (smallest
       ``max_i |x_i| / h_i``);
    3. a pixel in no box goes to the nearest consistent box if its distance to that box is at most
       ``fallback_m`` (`InstanceMap.fallback`), else it stays unassigned (actor id 0, its semantic
       class unchanged; `InstanceMap.unassigned`).

    Culling: the image is cut into ``tile x tile`` tiles; a tile only tests the boxes whose world
    AABB (grown by the larger of the two margins) meets the AABB of the tile's instance points and
    whose class is consistent with one of them. ``max_candidates`` (static) bounds the candidates
    per tile; ``None`` computes the exact bound on the host first (`max_box_candidates`; not inside
    `jax.jit`). Only the tiles holding instance pixels are tested: they are gathered into a static
    ``capacity`` (default: `tile_capacity` of their count, computed on the host with the candidate
    bound; inside `jax.jit` pass it, or 0 to test every tile). Most busy tiles have a single
    candidate (often the ego's own box): they test only that one, and the tiles with more
    candidates (static ``capacity_many``, sized on the host like ``capacity``; 0 inside `jax.jit`
    unless given: one group) test ``max_candidates``. Cost: about ``busy tiles x tile²`` box tests
    plus ``many-candidate tiles x tile² x max_candidates``, plus ``tiles x boxes`` AABB tests.
    """
    pts = jnp.asarray(points_world)
    cls = jnp.asarray(pixel_class).astype(jnp.int32)
    if pts.shape[:-1] != cls.shape or pts.shape[-1:] != (3,):
        raise ValueError(f"instance_segmentation: points {pts.shape} and classes {cls.shape} must be (H, W, 3) and (H, W)")
    if valid is not None:
        cls = jnp.where(jnp.asarray(valid, bool), cls, -1)
    cand = None
    if max_candidates is None or capacity is None:
        if isinstance(pts, jax.core.Tracer):
            raise ValueError("instance_segmentation: pass static max_candidates and capacity inside jax.jit")
        k_host, n_host, m_host, cand = _jit_plan(pts, cls, boxes, int(tile), float(max(margin_m, fallback_m)))
        max_candidates = int(k_host) if max_candidates is None else max_candidates
        capacity = tile_capacity(int(n_host)) if capacity is None else capacity
        capacity_many = tile_capacity(int(m_host)) if capacity_many is None else capacity_many
    k = int(min(max(max_candidates, 1), max(boxes.num_boxes, 1)))
    return _jit_assign(pts, cls, boxes, float(margin_m), float(fallback_m), int(tile), k, int(capacity), cand,
                       int(capacity_many or 0))


def _untile(x: Array, h: int, w: int, tile: int) -> Array:
    th, tw = -(-h // tile), -(-w // tile)
    x = x.reshape((th, tw, tile, tile) + x.shape[2:])
    x = jnp.swapaxes(x, 1, 2).reshape((th * tile, tw * tile) + x.shape[4:])
    return x[:h, :w]


def assign_instances(
    pts: Float[Array, "H W 3"], cls: Int[Array, "H W"], boxes: Boxes3D, margin_m: float, fallback_m: float, tile: int,
    k: int, capacity: int = 0, cand: Bool[Array, "T B"] | None = None, capacity_many: int = 0,
) -> InstanceMap:
    """`instance_segmentation` with every static size given (traceable; ``margin_m``,
    ``fallback_m``, ``tile``, ``k``, ``capacity`` and ``capacity_many`` are static): ``pts`` the
    pixels' CARLA world points (metres), ``cls`` their SynWoodScape classes before the two-wheeler
    / ego split (-1: no pixel), ``k`` the candidate boxes tested per tile (exact when at least
    `instance_plan`'s largest count), ``capacity`` / ``capacity_many`` the tiles tested (0: every
    tile; see `instance_segmentation`) and ``cand`` the ``(T, B)`` candidate mask of
    `instance_plan` (recomputed when None)."""
    h, w = cls.shape
    dtype = pts.dtype
    grp_img = _pixel_groups(cls)
    if boxes.num_boxes == 0:
        none = jnp.full((h, w), -1, jnp.int32)
        return InstanceMap(none, jnp.zeros((h, w), jnp.int32), none, grp_img > 0, jnp.zeros((h, w), bool))
    if cand is None:
        cand = _candidates(pts, cls, boxes, tile, max(margin_m, fallback_m))  # (T, B)
    top, top_ok = _first_candidates(cand, k)  # (T, K)
    tp = _tiles(pts, tile, 0.0)  # (T, P, 3)
    tg = _tiles(grp_img, tile, 0)  # (T, P)
    n_tiles, n_px = tg.shape
    boxes_f = (boxes.box_to_world.rotation_matrix.astype(dtype), boxes.box_to_world.translation.astype(dtype),
               boxes.half_extent.astype(dtype),
               jnp.where(boxes.class_id == CLASS_PEDESTRIAN, 1, jnp.where(boxes.class_id >= 0, 2, 0)))
    if capacity > 0:
        # Only the tiles holding instance pixels (static capacities sized on the host): those with
        # one candidate test it alone, those with several (few) test all k.
        busy = jnp.any(tg > 0, axis=1)
        groups = [(busy, capacity, k)]
        if capacity_many > 0 and k > 1:
            several = jnp.sum(cand, axis=1) > 1
            groups = [(busy & ~several, capacity, 1), (busy & several, capacity_many, k)]
        chosen = jnp.full((n_tiles, n_px), -1, jnp.int32)
        any_near = jnp.zeros((n_tiles, n_px), bool)
        for mask, cap, kk in groups:
            sel = jnp.nonzero(mask, size=min(cap, n_tiles), fill_value=n_tiles)[0]
            sel_ok = sel < n_tiles
            safe = jnp.where(sel_ok, sel, 0)
            c_sel, n_sel = _test_tiles(tp[safe], jnp.where(sel_ok[:, None], tg[safe], 0), top[safe, :kk],
                                       top_ok[safe, :kk] & sel_ok[:, None], boxes_f, margin_m, fallback_m)
            chosen = chosen.at[sel].set(c_sel, mode="drop")
            any_near = any_near.at[sel].set(n_sel, mode="drop")
    else:
        chosen, any_near = _test_tiles(tp, tg, top, top_ok, boxes_f, margin_m, fallback_m)
    box_index = _untile(chosen, h, w, tile)
    fallback = _untile(any_near, h, w, tile)
    safe_b = jnp.clip(box_index, 0, boxes.num_boxes - 1)
    has = box_index >= 0
    return InstanceMap(
        box_index=box_index,
        actor_id=jnp.where(has, boxes.actor_id[safe_b], 0).astype(jnp.int32),
        class_id=jnp.where(has, boxes.class_id[safe_b], -1).astype(jnp.int32),
        unassigned=(grp_img > 0) & ~has,
        fallback=fallback,
    )


def _first_candidates(cand: Array, k: int) -> tuple[Array, Array]:
    """Per row of ``cand (T, B)``, the indices of its first ``k`` True entries in ascending order
    ``(T, k)`` and which slots hold one (a cumulative count and a scatter: XLA's top-k sorts)."""
    t, b = cand.shape
    slot = jnp.where(cand, jnp.cumsum(cand, axis=1, dtype=jnp.int32) - 1, k)  # k: dropped
    rows = jnp.broadcast_to(jnp.arange(t, dtype=jnp.int32)[:, None], (t, b))
    cols = jnp.broadcast_to(jnp.arange(b, dtype=jnp.int32)[None, :], (t, b))
    top = jnp.zeros((t, k), jnp.int32).at[rows, slot].set(cols, mode="drop")
    n = jnp.sum(cand, axis=1, dtype=jnp.int32)
    return top, jnp.arange(k, dtype=jnp.int32)[None, :] < n[:, None]


def _test_tiles(tp, tg, top, top_ok, boxes_f, margin_m: float, fallback_m: float):
    """The six-plane test of tiles' points ``tp (T, P, 3)`` (groups ``tg (T, P)``) against their
    candidate boxes ``top (T, K)`` (valid where ``top_ok``): ``(box index or -1, by fallback)``."""
    rot_all, ctr_all, he_all, grp_all = boxes_f
    dtype = tp.dtype
    k = top.shape[1]
    big = jnp.asarray(np.inf, dtype)
    margin = jnp.asarray(margin_m, dtype)
    reach = jnp.asarray(fallback_m, dtype)
    tx = [tp[..., i] for i in range(3)]  # coordinate planes (T, P)

    def step(j, carry):
        in_d, in_i, near_d, near_i = carry
        b = top[:, j]  # (T,)
        # R^T d written out per component on (T, P) planes (no batched tiny matmuls, no (T, P, 3, 3)
        # intermediates: both are slow on CPU).
        r = rot_all[b]  # (T, 3, 3)
        c = ctr_all[b]
        he = he_all[b]
        d = [tx[c_] - c[:, c_][:, None] for c_ in range(3)]  # 3 x (T, P)
        a = [jnp.abs(d[0] * r[:, 0, i][:, None] + d[1] * r[:, 1, i][:, None] + d[2] * r[:, 2, i][:, None]) for i in range(3)]
        h3 = [he[:, i][:, None] for i in range(3)]
        ok = top_ok[:, j][:, None] & (grp_all[b][:, None] == tg) & (tg > 0)
        depth = jnp.maximum(jnp.maximum(a[0] / h3[0], a[1] / h3[1]), a[2] / h3[2])
        inside = ok & (a[0] <= h3[0] + margin) & (a[1] <= h3[1] + margin) & (a[2] <= h3[2] + margin) & (depth < in_d)
        e = [jnp.maximum(a[i] - h3[i], 0.0) for i in range(3)]
        outside = jnp.sqrt(e[0] * e[0] + e[1] * e[1] + e[2] * e[2])
        closer = ok & (outside <= reach) & (outside < near_d)
        bj = jnp.broadcast_to(b[:, None], in_i.shape)
        return (jnp.where(inside, depth, in_d), jnp.where(inside, bj, in_i),
                jnp.where(closer, outside, near_d), jnp.where(closer, bj, near_i))

    shape = tg.shape
    init = (jnp.full(shape, big), jnp.full(shape, -1, jnp.int32), jnp.full(shape, big), jnp.full(shape, -1, jnp.int32))
    _, in_i, _, near_i = jax.lax.fori_loop(0, k, step, init)
    any_in = in_i >= 0
    any_near = (near_i >= 0) & ~any_in
    return jnp.where(any_in, in_i, near_i).astype(jnp.int32), any_near


_jit_assign = jax.jit(assign_instances, static_argnums=(3, 4, 5, 6, 7, 9))


def instance_colors(actor_id: Int[ArrayLike, "*batch"]) -> UInt8[Array, "*batch 3"]:
    """A colour per actor id, the same in every frame and recording (an integer hash of the id);
    id 0 (no instance) is black. Channels lie in 48..255 so no actor is black."""
    x = jnp.asarray(actor_id).astype(jnp.uint32)
    h = x * jnp.uint32(0x9E3779B1)
    h = (h ^ (h >> 15)) * jnp.uint32(0x85EBCA77)
    h = (h ^ (h >> 13)) * jnp.uint32(0xC2B2AE3D)
    h = h ^ (h >> 16)
    ch = jnp.stack([(h >> 0) & 255, (h >> 8) & 255, (h >> 16) & 255], axis=-1)
    col = (jnp.uint32(48) + (ch * jnp.uint32(207)) // jnp.uint32(255)).astype(jnp.uint8)
    return jnp.where((x == 0)[..., None], jnp.uint8(0), col)


def box_displacements(boxes_prev: Boxes3D, boxes_curr: Boxes3D) -> Float[Array, " B"]:
    """Displacement (metres) of every box centre between t-1 and t (the same box order)."""
    d = boxes_curr.box_to_world.translation - boxes_prev.box_to_world.translation
    return jnp.sqrt(jnp.sum(d * d, axis=-1))


def motion_segmentation(
    box_index: Int[ArrayLike, "H W"],
    displacement_m: Float[ArrayLike, " B"],
    class_id: Int[ArrayLike, " B"] | None = None,
    *,
    threshold_m: float = MOTION_THRESHOLD_M,
    include_ego: bool = False,
) -> Bool[Array, "H W"]:
    """Moving-object mask: pixels of an instance whose box moved more than ``threshold_m`` between
    t-1 and t (`box_displacements`). The ego vehicle's own body (class 24) is excluded unless
    ``include_ego`` (it is static relative to the cameras)."""
    bi = jnp.asarray(box_index).astype(jnp.int32)
    disp = jnp.asarray(displacement_m)
    moving = disp > jnp.asarray(threshold_m, disp.dtype)
    if class_id is not None and not include_ego:
        moving = moving & (jnp.asarray(class_id) != CLASS_EGO)
    if moving.shape[0] == 0:
        return jnp.zeros(bi.shape, bool)
    return (bi >= 0) & moving[jnp.clip(bi, 0, moving.shape[0] - 1)]
