"""The JAX ray caster: nearest hit of rays against the scene's ground, boxes and capsules.

Everything here is pure JAX, jitted and chunked (``lax.map`` over fixed-size chunks of rays), so
memory stays bounded at any image size. The `Scene` is a jit *argument*. Frames: world = CARLA
(left-handed, x forward, y right, z up, metres); a camera pose ``camera_to_world`` maps the
camera model's frame (OpenCV) to world coordinates (it has determinant -1: it changes handedness).
"""

from __future__ import annotations

import functools
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from .._constants import FAR_DEPTH_M
from ..cameras import AbstractCamera
from ..transforms import Pose
from ._model import (
    TEXTURE_CHECKER,
    TEXTURE_NOISE,
    TEXTURE_STRIPES,
    TEXTURE_WINDOWS,
    Scene,
)
from ._tags import CARLA_SEMANTIC_TAGS as TAGS
from ._texture import hash_u32, sky_detail, surface_detail, surface_uv

FAR_M = FAR_DEPTH_M
"""Far plane (metres), `jaxfish.reprojection.FAR_DEPTH_M`: no hit beyond it; sky and far pixels
report this range and depth (CARLA's depth camera saturates at 1000 m)."""
DEFAULT_CHUNK = 4096
"""Rays per chunk of the caster (bounds the (rays x primitives) working set)."""
_T_MIN = 1e-4
"""Hits closer than this to the ray origin are ignored (metres)."""
_F32 = jnp.float32


class RenderBuffers(eqx.Module):
    """Per-pixel (or per-ray) results of a render; every field has the batch shape of the pixels.

    - `valid`: the camera has a ray for this pixel (False beyond a fisheye's domain);
    - `hit`: the ray hit geometry closer than `FAR_M` (False: sky, or invalid);
    - `range_m`: distance from the ray origin to the hit along the ray (metres), `FAR_M` for sky;
    - `depth_m`: planar depth, the hit's z in the camera frame (metres), `FAR_M` for sky;
    - `rgb`: linear RGB in [0, 1] (albedo x Lambert shading; sky gradient where no hit);
    - `semantic`: CARLA 0.9.10 tag (13 sky; 0 where the camera has no ray);
    - `object_index`: index into the scene's objects, -1 for ground and sky;
    - `actor_id`: CARLA-style id of the hit actor, 0 for static world, ground and sky;
    - `point_world`, `normal_world`: hit point and outward unit normal (world, CARLA frame);
      for sky the point is at `FAR_M` along the ray and the normal is zero.
    """

    valid: Bool[Array, "*batch"]
    hit: Bool[Array, "*batch"]
    range_m: Float[Array, "*batch"]
    depth_m: Float[Array, "*batch"]
    rgb: Float[Array, "*batch 3"]
    semantic: Int[Array, "*batch"]
    object_index: Int[Array, "*batch"]
    actor_id: Int[Array, "*batch"]
    point_world: Float[Array, "*batch 3"]
    normal_world: Float[Array, "*batch 3"]


# ------------------------------------------------------------------------------ closed forms
def ray_box_distance(
    origin: Float[Array, "*batch 3"], direction: Float[Array, "*batch 3"], half_extent: Float[Array, "*batch 3"]
) -> Float[Array, "*batch"]:
    """Entry distance of rays into axis-aligned boxes centred at the origin (slab method), in the
    box frame; ``inf`` when missed or when the box is behind (or around) the origin. ``direction``
    need not be normalised (the distance is in units of its length)."""
    o, d, h = (tuple(x[..., i] for i in range(3)) for x in (origin, direction, half_extent))
    return _box_entry(*o, *d, *h)


def ray_capsule_distance(
    origin: Float[Array, "*batch 3"], direction: Float[Array, "*batch 3"],
    half_length: Float[Array, "*batch"], radius: Float[Array, "*batch"],
) -> Float[Array, "*batch"]:
    """Entry distance of **unit** rays into capsules whose segment runs from ``(0, 0, -half_length)``
    to ``(0, 0, half_length)`` (capsule frame), ``inf`` when missed. The entry into the union of the
    side cylinder and the two end spheres is the smallest entry of the three; rays parallel to the
    axis (top views) only meet the spheres."""
    o, d = (tuple(x[..., i] for i in range(3)) for x in (origin, direction))
    return _capsule_entry(*o, *d, half_length, radius)


def _slab(o, d, h):
    tiny = 1e-12
    d = jnp.where(jnp.abs(d) < tiny, jnp.where(d < 0, -tiny, tiny), d)
    inv = 1.0 / d
    t1 = (-h - o) * inv
    t2 = (h - o) * inv
    return jnp.minimum(t1, t2), jnp.maximum(t1, t2)


def _box_entry(ox, oy, oz, dx, dy, dz, hx, hy, hz):
    """Slab entry distance into the box ``|x| <= hx, |y| <= hy, |z| <= hz`` of rays given by their
    components in the box frame (any broadcastable shapes); ``inf`` when missed or behind."""
    ax, bx = _slab(ox, dx, hx)
    ay, by = _slab(oy, dy, hy)
    az, bz = _slab(oz, dz, hz)
    t_near = jnp.maximum(jnp.maximum(ax, ay), az)
    t_far = jnp.minimum(jnp.minimum(bx, by), bz)
    return jnp.where((t_near <= t_far) & (t_near > _T_MIN), t_near, jnp.inf)


def _sphere_entry(ox, oy, oz, dx, dy, dz, r):
    """Entry distance of unit rays into the sphere of radius ``r`` at the origin. The discriminant
    is ``r² - |o - (o·d) d|²`` (the squared distance of the ray's closest approach), not
    ``(o·d)² - |o|² + r²``, whose cancellation grows with the distance of the sphere."""
    b = ox * dx + oy * dy + oz * dz
    px, py, pz = ox - b * dx, oy - b * dy, oz - b * dz
    disc = r * r - (px * px + py * py + pz * pz)
    t = -b - jnp.sqrt(jnp.maximum(disc, 0.0))
    return jnp.where((disc >= 0) & (t > _T_MIN), t, jnp.inf)


def _capsule_entry(ox, oy, oz, dx, dy, dz, half_length, r):
    """Entry distance of unit rays (components in the capsule frame, any broadcastable shapes) into
    the upright capsule of segment ``z in [-half_length, half_length]`` and radius ``r``. The side
    cylinder's discriminant is ``a r² - (o × d)_z²`` (``a = dx² + dy²``), the same as
    ``b² - a (ox² + oy² - r²)`` by Lagrange's identity without its cancellation: a thin pole far
    away keeps its silhouette in float32."""
    a = dx * dx + dy * dy
    b = ox * dx + oy * dy
    cross = ox * dy - oy * dx
    disc = a * (r * r) - cross * cross
    ok = (a > 1e-12) & (disc >= 0)
    t_cyl = (-b - jnp.sqrt(jnp.maximum(disc, 0.0))) / jnp.where(ok, a, 1.0)
    t_cyl = jnp.where(ok & (t_cyl > _T_MIN) & (jnp.abs(oz + t_cyl * dz) <= half_length), t_cyl, jnp.inf)
    t_top = _sphere_entry(ox, oy, oz - half_length, dx, dy, dz, r)
    t_bot = _sphere_entry(ox, oy, oz + half_length, dx, dy, dz, r)
    return jnp.minimum(t_cyl, jnp.minimum(t_top, t_bot))


def ray_ground_distance(origin: Float[Array, "*batch 3"], direction: Float[Array, "*batch 3"]) -> Float[Array, "*batch"]:
    """Distance along rays to the ground plane z = 0 from above, ``inf`` when the ray does not
    descend towards it."""
    oz, dz = origin[..., 2], direction[..., 2]
    down = (dz < -1e-9) & (oz > 0)
    return jnp.where(down, -oz / jnp.where(down, dz, -1.0), jnp.inf)


# ------------------------------------------------------------------------------ textures
def _hash(cell: Float[Array, "*batch 3"]) -> Float[Array, "*batch"]:
    h = jnp.sin(cell[..., 0] * 12.9898 + cell[..., 1] * 78.233 + cell[..., 2] * 37.719) * 43758.5453
    return h - jnp.floor(h)


def _texture(q, n_local, kind, scale):
    """Procedural texture value in [0, 1] at object-local point ``q`` (moves with the object)."""
    s = scale[..., None]
    cell = jnp.floor(q / s)
    frac = q / s - cell
    noise = _hash(cell)
    checker = jnp.mod(jnp.sum(cell, axis=-1), 2.0)
    along = jnp.where(jnp.abs(n_local[..., 0]) > 0.5, frac[..., 1], frac[..., 0])
    window = (frac[..., 2] > 0.3) & (frac[..., 2] < 0.75) & (along > 0.2) & (along < 0.8) & (jnp.abs(n_local[..., 2]) < 0.5)
    stripes = jnp.mod(jnp.floor((q[..., 0] + q[..., 1] + q[..., 2]) / scale), 2.0)
    tex = jnp.ones_like(noise)
    tex = jnp.where(kind == TEXTURE_CHECKER, 0.6 + 0.4 * checker, tex)
    tex = jnp.where(kind == TEXTURE_NOISE, 0.55 + 0.45 * noise, tex)
    tex = jnp.where(kind == TEXTURE_WINDOWS, jnp.where(window, 0.25 + 0.2 * noise, 0.85 + 0.15 * noise), tex)
    tex = jnp.where(kind == TEXTURE_STRIPES, 0.55 + 0.45 * stripes, tex)
    return tex


def ground_semantic_and_albedo(scene: Scene, xy: Float[Array, "*batch 2"]) -> tuple[Int[Array, "*batch"], Float[Array, "*batch 3"]]:
    """CARLA tag (road, roadline, sidewalk, terrain) and albedo of ground points ``(x, y)`` (world)."""
    x, y = xy[..., 0], xy[..., 1]
    ay = jnp.abs(y)
    road = ay < scene.road_half_width
    centre = ay < 0.12
    dashes = (jnp.abs(ay - scene.lane_width) < 0.075) & (x / 6.0 - jnp.floor(x / 6.0) < 0.5)
    line = road & (centre | dashes)
    sidewalk = ~road & (ay < scene.road_half_width + scene.sidewalk_width)
    tag = jnp.where(line, TAGS["roadline"], jnp.where(road, TAGS["road"], jnp.where(sidewalk, TAGS["sidewalk"], TAGS["terrain"])))
    z = jnp.zeros_like(x)
    cell = jnp.floor(jnp.stack([x, y, z], axis=-1) / 0.5)
    noise = _hash(cell)
    tiles = jnp.mod(cell[..., 0] + cell[..., 1], 2.0)
    col = lambda r, g, b: jnp.asarray([r, g, b], x.dtype)  # noqa: E731
    albedo = jnp.where(line[..., None], col(0.9, 0.9, 0.85) * (0.9 + 0.1 * noise)[..., None],
             jnp.where(road[..., None], col(0.26, 0.26, 0.28) * (0.7 + 0.3 * noise)[..., None],
             jnp.where(sidewalk[..., None], col(0.62, 0.58, 0.55) * (0.8 + 0.2 * tiles)[..., None],
                       col(0.3, 0.45, 0.18) * (0.6 + 0.4 * noise)[..., None])))
    return tag.astype(jnp.int32), albedo


def sky_rgb(direction: Float[Array, "*batch 3"]) -> Float[Array, "*batch 3"]:
    """The sky colour along world directions (a zenith-to-horizon gradient)."""
    e = jnp.clip(direction[..., 2:3], 0.0, 1.0)
    horizon = jnp.asarray([0.78, 0.84, 0.92], direction.dtype)
    zenith = jnp.asarray([0.32, 0.52, 0.85], direction.dtype)
    return horizon * (1 - e) + zenith * e


# ------------------------------------------------------------------------------ casting
class _Posed(eqx.Module):
    box_center: Array
    box_cos: Array
    box_sin: Array
    cap_center: Array
    cap_cos: Array
    cap_sin: Array


def _pose_primitives(scene: Scene, time) -> _Posed:
    loc, yaw = scene.object_poses(time)

    def place(obj, center, extra_yaw):
        c, s = jnp.cos(yaw[obj]), jnp.sin(yaw[obj])
        x = c * center[:, 0] - s * center[:, 1]
        y = s * center[:, 0] + c * center[:, 1]
        world = jnp.stack([x, y, center[:, 2]], axis=-1) + loc[obj]
        yw = yaw[obj] + extra_yaw
        return world, jnp.cos(yw), jnp.sin(yw)

    bc, bcos, bsin = place(scene.box_object, scene.box_center, jnp.deg2rad(scene.box_yaw_deg))
    kc, kcos, ksin = place(scene.capsule_object, scene.capsule_center, jnp.zeros_like(scene.capsule_radius))
    return _Posed(bc, bcos, bsin, kc, kcos, ksin)


def _to_local(v, c, s):
    """World vectors ``(..., 3)`` -> a primitive's frame rotated by yaw (cos c, sin s)."""
    x = c * v[..., 0] + s * v[..., 1]
    y = -s * v[..., 0] + c * v[..., 1]
    return jnp.stack([x, y, v[..., 2]], axis=-1)


def _from_local(v, c, s):
    x = c * v[..., 0] - s * v[..., 1]
    y = s * v[..., 0] + c * v[..., 1]
    return jnp.stack([x, y, v[..., 2]], axis=-1)


def _nearest(scene: Scene, posed: _Posed, o, d, box_idx, n_boxes, cap_idx, n_capsules):
    """Nearest hit of the rays ``o, d (C, 3)`` among the ground, the first ``n_boxes`` boxes of
    ``box_idx`` and the first ``n_capsules`` capsules of ``cap_idx`` (indices in increasing order):
    ``(t, global index)``, index 0 the ground, ``1..B`` boxes, ``B+1..`` capsules, the lowest index
    among equal distances. One loop over the primitives, each tested on the whole chunk's rays by
    the same compiled body: a ray's result does not depend on which other primitives are tested."""
    n_box = scene.box_center.shape[0]
    ox, oy, oz = o[:, 0], o[:, 1], o[:, 2]
    dx, dy, dz = d[:, 0], d[:, 1], d[:, 2]

    def box(i, carry):
        t, idx = carry
        j = box_idx[i]
        c, s, h = posed.box_cos[j], posed.box_sin[j], scene.box_half_extent[j]
        rx, ry, rz = ox - posed.box_center[j, 0], oy - posed.box_center[j, 1], oz - posed.box_center[j, 2]
        tj = _box_entry(c * rx + s * ry, -s * rx + c * ry, rz, c * dx + s * dy, -s * dx + c * dy, dz, h[0], h[1], h[2])
        closer = tj < t
        return jnp.where(closer, tj, t), jnp.where(closer, 1 + j.astype(jnp.int32), idx)

    def capsule(i, carry):
        t, idx = carry
        j = cap_idx[i]
        centre = posed.cap_center[j]
        tj = _capsule_entry(ox - centre[0], oy - centre[1], oz - centre[2], dx, dy, dz,
                            scene.capsule_half_length[j], scene.capsule_radius[j])
        closer = tj < t
        return jnp.where(closer, tj, t), jnp.where(closer, 1 + n_box + j.astype(jnp.int32), idx)

    t = ray_ground_distance(o, d)
    carry = jax.lax.fori_loop(0, n_boxes, box, (t, jnp.zeros(t.shape, jnp.int32)))
    return jax.lax.fori_loop(0, n_capsules, capsule, carry)


def _candidates(o, d, center, radius, active):
    """Primitives (bounding spheres) that some ray of the bundle may hit: the bundle is bounded by
    a cone (axis = mean direction, half-angle to the widest ray) from a ball around the mean
    origin (radius = farthest origin). Conservative: never drops a primitive a ray can hit."""
    oc = jnp.mean(o, axis=0)
    rho = jnp.sqrt(jnp.max(jnp.sum((o - oc) ** 2, axis=-1)))
    axis = jnp.mean(d, axis=0)
    axis = axis / jnp.maximum(jnp.sqrt(jnp.sum(axis * axis)), 1e-12)
    cos_half = jnp.clip(jnp.min(d @ axis), -1.0, 1.0)
    half = jnp.arccos(cos_half)
    v = center - oc
    dist = jnp.sqrt(jnp.sum(v * v, axis=-1))
    r = radius + rho + 1e-3
    inside = dist <= r
    cos_beta = jnp.clip((v @ axis) / jnp.maximum(dist, 1e-12), -1.0, 1.0)
    beta = jnp.arccos(cos_beta)
    spread = jnp.arcsin(jnp.clip(r / jnp.maximum(dist, 1e-12), 0.0, 1.0))
    ok = inside | (beta <= half + spread + 1e-3) | (half > 1.2)
    return ok & active


def _cast_chunk(scene: Scene, posed: _Posed, o: Float[Array, "C 3"], d: Float[Array, "C 3"]):
    n_box = scene.box_center.shape[0]
    box_radius = jnp.sqrt(jnp.sum(scene.box_half_extent**2, axis=-1))
    cand_b = _candidates(o, d, posed.box_center, box_radius, scene.box_active)
    cand_k = _candidates(o, d, posed.cap_center, scene.capsule_half_length + scene.capsule_radius, scene.capsule_active)
    # only the survivors of the cull, in index order (stable sort: candidates first)
    t, idx = _nearest(scene, posed, o, d, jnp.argsort(~cand_b, stable=True), jnp.sum(cand_b),
                      jnp.argsort(~cand_k, stable=True), jnp.sum(cand_k))
    hit = t < FAR_DEPTH_M
    t_safe = jnp.where(hit, t, FAR_DEPTH_M).astype(o.dtype)
    p = o + t_safe[:, None] * d

    is_gnd = idx == 0
    is_box = (idx >= 1) & (idx <= n_box)
    bi = jnp.clip(idx - 1, 0, n_box - 1)
    ki = jnp.clip(idx - 1 - n_box, 0, scene.capsule_center.shape[0] - 1)
    # the winning primitive's frame
    c = jnp.where(is_box, posed.box_cos[bi], posed.cap_cos[ki])
    s = jnp.where(is_box, posed.box_sin[bi], posed.cap_sin[ki])
    centre = jnp.where(is_box[:, None], posed.box_center[bi], posed.cap_center[ki])
    q = _to_local(p - centre, c, s)
    h = scene.box_half_extent[bi]
    rel = jnp.abs(q) / jnp.maximum(h, 1e-6)
    axis = jnp.argmax(rel, axis=-1)
    n_box_local = jax.nn.one_hot(axis, 3, dtype=o.dtype) * jnp.where(q >= 0, 1.0, -1.0).astype(o.dtype)
    hl = scene.capsule_half_length[ki]
    axis_pt = jnp.stack([jnp.zeros_like(hl), jnp.zeros_like(hl), jnp.clip(q[:, 2], -hl, hl)], axis=-1)
    radial = q - axis_pt
    rn = jnp.sqrt(jnp.maximum(jnp.sum(radial * radial, axis=-1, keepdims=True), 1e-20))
    n_cap_local = radial / rn
    n_local = jnp.where(is_box[:, None], n_box_local, n_cap_local)
    n_world = jnp.where(is_gnd[:, None], jnp.asarray([0.0, 0.0, 1.0], o.dtype), _from_local(n_local, c, s))
    n_world = jnp.where(hit[:, None], n_world, 0.0)

    kind = jnp.where(is_box, scene.box_texture[bi], scene.capsule_texture[ki])
    scale = jnp.where(is_box, scene.box_texture_scale[bi], scene.capsule_texture_scale[ki])
    tex = _texture(q, n_local, kind, scale)
    prim_albedo = jnp.where(is_box[:, None], scene.box_albedo[bi], scene.capsule_albedo[ki]) * tex[:, None]
    gnd_tag, gnd_albedo = ground_semantic_and_albedo(scene, p[:, :2])
    albedo = jnp.where(is_gnd[:, None], gnd_albedo, prim_albedo)
    prim_tag = jnp.where(is_box, scene.box_tag[bi], scene.capsule_tag[ki])
    if scene.textured:  # static: the smooth scene compiles without it
        uv = jnp.where(is_gnd[:, None], p[:, :2], surface_uv(q, n_local))
        salt = hash_u32(scene.texture_seed + idx.astype(jnp.uint32) * jnp.uint32(0x9E3779B9))
        albedo = albedo * surface_detail(uv, jnp.where(is_gnd, gnd_tag, prim_tag), salt).astype(o.dtype)
    shade = 0.4 + 0.6 * jnp.maximum(jnp.sum(n_world * scene.sun_direction, axis=-1), 0.0)
    sky = sky_rgb(d)
    if scene.textured:
        sky = sky * sky_detail(d, scene.texture_seed).astype(o.dtype)
    rgb = jnp.where(hit[:, None], albedo * shade[:, None], sky)

    semantic = jnp.where(hit, jnp.where(is_gnd, gnd_tag, prim_tag), TAGS["sky"])
    obj = jnp.where(is_box, scene.box_object[bi], scene.capsule_object[ki])
    obj = jnp.where(hit & ~is_gnd, obj, -1)
    actor = jnp.where(obj >= 0, scene.object_actor_id[jnp.maximum(obj, 0)], 0)
    return dict(hit=hit, range_m=t_safe, rgb=rgb.astype(o.dtype), semantic=semantic.astype(jnp.int32),
                object_index=obj.astype(jnp.int32), actor_id=actor.astype(jnp.int32), point_world=p,
                normal_world=n_world.astype(o.dtype))


DEFAULT_BLOCK = 65536
"""Rays per jitted call of the caster: every cast is cut into blocks of this many rays (the last one
padded), so every render, of any size, shares one compilation."""


@eqx.filter_jit
def _cast_block(scene: Scene, o, d, time, n_rays, chunk_size: int, fields: tuple[str, ...] | None = None):
    """The first ``n_rays`` rays of the block ``o, d (N, 3)``, chunk by chunk; the chunks past them
    are not cast (their outputs stay zero). ``fields``: the outputs to compute (static), None for all."""
    posed = _pose_primitives(scene, time)

    def cast(oc, dc):
        out = _cast_chunk(scene, posed, oc, dc)
        return out if fields is None else {k: out[k] for k in fields}

    shapes = jax.eval_shape(lambda: cast(o[:chunk_size], d[:chunk_size]))
    out = jax.tree_util.tree_map(lambda s: jnp.zeros((o.shape[0],) + s.shape[1:], s.dtype), shapes)

    def chunk(i, out):
        start = i * chunk_size
        res = cast(jax.lax.dynamic_slice_in_dim(o, start, chunk_size), jax.lax.dynamic_slice_in_dim(d, start, chunk_size))
        return jax.tree_util.tree_map(lambda buf, r: jax.lax.dynamic_update_slice_in_dim(buf, r, start, 0), out, res)

    return jax.lax.fori_loop(0, (n_rays + chunk_size - 1) // chunk_size, chunk, out)


def _cast_flat(scene: Scene, origins, directions, time, chunk_size: int, block_size: int = DEFAULT_BLOCK,
               fields: tuple[str, ...] | None = None):
    """Cast ``(N, 3)`` rays block by block (one shape: one compilation, bounded memory). The
    padding, the blocks' slicing and their joining are one program each per ray count."""
    n = origins.shape[0]
    chunk = max(1, int(chunk_size))
    size = max(chunk, (int(block_size) // chunk) * chunk)
    time = jnp.asarray(time, _F32)
    blocks = max(1, -(-n // size))
    o, d = _padded(origins, directions, blocks * size)
    parts = [_cast_block(scene, *_block(o, d, jnp.int32(i * size), size), time, jnp.int32(min(size, n - i * size)),
                         chunk, fields) for i in range(blocks)]
    return _joined(parts, n)


@functools.partial(jax.jit, static_argnums=2)
def _padded(o, d, length: int):
    """``o, d`` padded to ``length`` rays with copies of their last ray (a tight cull)."""
    pad = length - o.shape[0]
    fill = (lambda x: x[-1:]) if o.shape[0] else (lambda x: jnp.zeros((1, 3), x.dtype))  # no ray: any
    return tuple(x if pad == 0 else jnp.concatenate([x, jnp.broadcast_to(fill(x), (pad, 3))]) for x in (o, d))


@functools.partial(jax.jit, static_argnums=3)
def _block(o, d, start, size: int):
    return jax.lax.dynamic_slice_in_dim(o, start, size), jax.lax.dynamic_slice_in_dim(d, start, size)


@functools.partial(jax.jit, static_argnums=1)
def _joined(parts, n: int):
    """The blocks' outputs as one array per field, the first ``n`` rays."""
    return jax.tree_util.tree_map(lambda *xs: jnp.concatenate(xs)[:n], *parts)


def cast_rays(
    scene: Scene,
    origins: Float[Array, "*batch 3"],
    directions: Float[Array, "*batch 3"],
    *,
    time=1.0,
    chunk_size: int = DEFAULT_CHUNK,
) -> RenderBuffers:
    """Nearest hit of world rays (CARLA frame, float32, ``directions`` unit) at ``time`` (fraction of
    the frame interval: 0 = t-1, 1 = t). `depth_m` equals `range_m` here (no camera axis)."""
    origins = jnp.asarray(origins, _F32)
    directions = jnp.asarray(directions, _F32)
    shape = origins.shape[:-1]
    out = _cast_flat(scene, origins.reshape(-1, 3), directions.reshape(-1, 3), time, chunk_size)
    out = jax.tree_util.tree_map(lambda x: x.reshape(shape + x.shape[1:]), out)
    return RenderBuffers(valid=jnp.ones(shape, bool), depth_m=out["range_m"], **out)


@eqx.filter_jit
def _camera_rays(camera: AbstractCamera, camera_to_world: Pose, uv):
    cam = camera.astype(_F32)
    pose = Pose(camera_to_world.rotation_matrix, camera_to_world.translation, dtype=_F32)
    dirs_cam, valid = cam.unproject(uv)
    o = pose.apply(cam.ray_origins(uv))
    d = pose.rotate(dirs_cam)
    d = d / jnp.sqrt(jnp.maximum(jnp.sum(d * d, axis=-1, keepdims=True), 1e-30))
    return o.reshape(-1, 3), d.reshape(-1, 3), valid, pose


@eqx.filter_jit
def _finish(out, valid, pose: Pose):
    shape = valid.shape
    out = jax.tree_util.tree_map(lambda x: x.reshape(shape + x.shape[1:]), out)
    axis = pose.rotation_matrix[:, 2]
    depth = jnp.sum((out["point_world"] - pose.translation) * axis, axis=-1)
    hit = out["hit"] & valid
    out["semantic"] = jnp.where(valid, out["semantic"], TAGS["unlabeled"])
    out["rgb"] = _finish_rgb(out["rgb"], valid)
    out["object_index"] = jnp.where(valid, out["object_index"], -1)
    out["actor_id"] = jnp.where(valid, out["actor_id"], 0)
    out["hit"] = hit
    return RenderBuffers(valid=valid, depth_m=jnp.where(hit, depth, FAR_DEPTH_M), **out)


def render_pixels(
    scene: Scene,
    camera: AbstractCamera,
    camera_to_world: Pose,
    uv: Float[Array, "*batch 2"],
    *,
    time=1.0,
    chunk_size: int = DEFAULT_CHUNK,
) -> RenderBuffers:
    """Render the pixels ``uv`` (any batch shape) of ``camera`` placed by ``camera_to_world``
    (camera frame -> CARLA world) at ``time`` (0 = t-1, 1 = t). Works for every jaxfish camera
    model, central or not (`AbstractCamera.ray_origins`)."""
    return _finish(*_cast_pixels(scene, camera, camera_to_world, uv, time, chunk_size))


def _cast_pixels(scene: Scene, camera: AbstractCamera, camera_to_world: Pose, uv, time, chunk_size: int,
                 fields: tuple[str, ...] | None = None):
    """The caster's outputs (``fields``, None for all) for the pixels ``uv``, flat in pixel order,
    with the pixels' validity and the camera's float32 pose."""
    uv = jnp.asarray(uv, _F32)
    o, d, valid, pose = _camera_rays(camera, camera_to_world, uv)
    if uv.ndim == 3:  # an image: cast square tiles together (coherent chunks cull well)
        order, inverse = _tile_order(uv.shape[0], uv.shape[1], chunk_size)
        out = _take(_cast_flat(scene, *_take((o, d), order), time, chunk_size, fields=fields), inverse)
    else:
        out = _cast_flat(scene, o, d, time, chunk_size, fields=fields)
    return out, valid, pose


def render_rgb(
    scene: Scene,
    camera: AbstractCamera,
    camera_to_world: Pose,
    *,
    time=1.0,
    chunk_size: int = DEFAULT_CHUNK,
) -> Float[Array, "H W 3"]:
    """`render`'s `RenderBuffers.rgb` alone (the same values), computing nothing else: for renders
    whose colour is all that is kept (the DVS sub-frames)."""
    out, valid, _ = _cast_pixels(scene, camera, camera_to_world, camera.pixel_grid(_F32), time, chunk_size, ("rgb",))
    return _finish_rgb(out["rgb"], valid)


@jax.jit
def _finish_rgb(rgb, valid):
    """The rendered colour of the pixels ``valid`` (shaped like it), black elsewhere."""
    return jnp.where(valid[..., None], rgb.reshape(valid.shape + (3,)), 0.0)


@jax.jit
def _take(tree, index):
    """Every array of ``tree`` gathered along its first axis at ``index`` (one program)."""
    return jax.tree_util.tree_map(lambda x: x[index], tree)


@functools.lru_cache(maxsize=8)
def _tile_order(height: int, width: int, chunk_size: int) -> tuple[np.ndarray, np.ndarray]:
    """Flat pixel indices ordered tile by tile (square tiles of about ``chunk_size`` pixels), and
    the inverse permutation (int32, read-only; one pair per image size, kept)."""
    side = 1 << max(0, int(math.floor(math.log2(max(chunk_size, 1)) / 2)))
    r, c = np.divmod(np.arange(height * width), width)
    key = ((r // side) * ((width + side - 1) // side) + c // side) * side * side + (r % side) * side + (c % side)
    order = np.argsort(key, kind="stable").astype(np.int32)
    inverse = np.empty_like(order)
    inverse[order] = np.arange(order.size, dtype=np.int32)
    for a in (order, inverse):
        a.setflags(write=False)
    return order, inverse


def render(
    scene: Scene,
    camera: AbstractCamera,
    camera_to_world: Pose,
    *,
    time=1.0,
    chunk_size: int = DEFAULT_CHUNK,
) -> RenderBuffers:
    """Render every pixel of ``camera`` (buffers of shape ``(H, W, ...)``); see `render_pixels`."""
    return render_pixels(scene, camera, camera_to_world, camera.pixel_grid(_F32), time=time, chunk_size=chunk_size)
