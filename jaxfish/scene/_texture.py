"""Surface detail: deterministic procedural texture that gives the embedded scene's renders the
pixel statistics of a CARLA render (grain, blotches, per-material colour variation).

The detail is a pure function of a surface point in the texture frame of its surface (the
primitive's own frame for boxes and capsules, so it moves with its object; the world for the
ground), of a 32-bit seed and of the material (the semantic tag picks the amplitudes and scales, a
per-surface salt decorrelates surfaces of one material). Every camera and both instants of a frame
therefore see the same texture on the same surface point, and optical flow and events stay
consistent with the geometry.

Noise is 2-D value noise on the two coordinates across the surface's dominant normal axis
(``uv``): a coarse octave (blotches and tint), a medium octave, and a *grain* with no
interpolation whose cells are a few millimetres wide, i.e. about a pixel at a few metres in a
768 px cube face (asphalt and plaster in CARLA look like this).
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int, UInt32

from ._tags import CARLA_SEMANTIC_TAGS as TAGS

_U32 = jnp.uint32
_GRAIN_OCTAVES = 3
"""Grain octaves (cells of the material's grain size, a third and a ninth of it)."""
_CHROMA = 0.5
"""Chroma grain amplitude relative to the luminance grain."""
_SKY_CLOUD, _SKY_GRAIN, _SKY_GRAIN_RAD = 0.25, 0.06, 0.0015
"""Sky cloud amplitude, sky grain amplitude, and sky grain cell (radians, about 0.09 degrees)."""

# Per-material parameters, indexed by CARLA tag: coarse cell (m), coarse amplitude, medium cell (m),
# medium amplitude, grain cell (m), grain amplitude, tint amplitude (relative; per channel).
_DEFAULT = (2.0, 0.25, 0.25, 0.18, 0.006, 0.22, 0.10)
_MATERIALS: dict[str, tuple[float, ...]] = {
    "road": (3.0, 0.20, 0.30, 0.20, 0.008, 0.45, 0.06),
    "roadline": (2.0, 0.15, 0.30, 0.15, 0.008, 0.25, 0.04),
    "sidewalk": (2.0, 0.20, 0.25, 0.20, 0.006, 0.35, 0.08),
    "terrain": (1.5, 0.35, 0.20, 0.30, 0.010, 0.45, 0.20),
    "vegetation": (0.8, 0.35, 0.12, 0.35, 0.010, 0.45, 0.25),
    "building": (3.0, 0.25, 0.40, 0.20, 0.006, 0.25, 0.12),
    "wall": (1.0, 0.25, 0.20, 0.20, 0.006, 0.30, 0.10),
    "fence": (1.0, 0.20, 0.10, 0.20, 0.006, 0.25, 0.08),
    "vehicle": (2.0, 0.10, 0.30, 0.08, 0.004, 0.12, 0.05),
    "pedestrian": (0.6, 0.20, 0.10, 0.20, 0.004, 0.25, 0.15),
    "pole": (1.0, 0.15, 0.20, 0.15, 0.004, 0.20, 0.05),
}


def _material_table() -> np.ndarray:
    table = np.tile(np.asarray(_DEFAULT, np.float32), (max(TAGS.values()) + 1, 1))
    for name, row in _MATERIALS.items():
        table[TAGS[name]] = row
    return table


MATERIAL_TABLE = _material_table()
"""``(23, 7)`` float32 per CARLA tag: coarse cell (m), coarse amplitude, medium cell (m), medium
amplitude, grain cell (m), grain amplitude, tint amplitude."""


def hash_u32(x: UInt32[Array, "*batch"]) -> UInt32[Array, "*batch"]:
    """A 32-bit integer mix (``lowbias32``): every output bit depends on every input bit."""
    x = x ^ (x >> 16)
    x = x * _U32(0x7FEB352D)
    x = x ^ (x >> 15)
    x = x * _U32(0x846CA68B)
    return x ^ (x >> 16)


def seed_u32(seed: int) -> np.uint32:
    """A scene seed (0 .. 2**63 - 1) folded to the 32-bit texture seed."""
    s = int(seed)
    return np.uint32((s ^ (s >> 32)) & 0xFFFFFFFF)


def _unit(h: UInt32[Array, "*batch"]) -> Float[Array, "*batch"]:
    """The top 24 bits of a hash as a float32 in [0, 1)."""
    return (h >> 8).astype(jnp.float32) * jnp.float32(1.0 / (1 << 24))


def _lattice(i, j, salt):
    return hash_u32(i.astype(_U32) * _U32(0x8DA6B343) + j.astype(_U32) * _U32(0xD8163841) + salt)


def _value_noise(u, v, cell, salt):
    """Smooth 2-D value noise in [0, 1) with lattice spacing ``cell`` (metres)."""
    x, y = u / cell, v / cell
    fx, fy = jnp.floor(x), jnp.floor(y)
    tx, ty = x - fx, y - fy
    tx, ty = tx * tx * (3 - 2 * tx), ty * ty * (3 - 2 * ty)
    i, j = fx.astype(jnp.int32), fy.astype(jnp.int32)
    a, b = _unit(_lattice(i, j, salt)), _unit(_lattice(i + 1, j, salt))
    c, d = _unit(_lattice(i, j + 1, salt)), _unit(_lattice(i + 1, j + 1, salt))
    return (a + (b - a) * tx) + ((c + (d - c) * tx) - (a + (b - a) * tx)) * ty


def surface_uv(q: Float[Array, "*batch 3"], normal: Float[Array, "*batch 3"]) -> Float[Array, "*batch 2"]:
    """The two coordinates of ``q`` across the dominant axis of ``normal`` (both in one frame)."""
    an = jnp.abs(normal)
    x_major = (an[..., 0] >= an[..., 1]) & (an[..., 0] >= an[..., 2])
    y_major = ~x_major & (an[..., 1] >= an[..., 2])
    u = jnp.where(x_major, q[..., 1], q[..., 0])
    v = jnp.where(x_major | y_major, q[..., 2], q[..., 1])
    return jnp.stack([u, v], axis=-1)


def surface_detail(
    uv: Float[Array, "*batch 2"],
    tag: Int[Array, "*batch"],
    salt: UInt32[Array, "*batch"],
) -> Float[Array, "*batch 3"]:
    """Per-channel multiplicative detail (around 1) of surface points ``uv`` (metres, the
    surface's texture frame) of material ``tag`` (CARLA tag) on the surface ``salt`` (the seed
    mixed with a per-surface number, `hash_u32`)."""
    params = jnp.asarray(MATERIAL_TABLE)[jnp.clip(tag, 0, MATERIAL_TABLE.shape[0] - 1)]
    coarse_cell, coarse_amp, mid_cell, mid_amp, grain_cell, grain_amp, tint_amp = (params[..., k] for k in range(7))
    u, v = uv[..., 0], uv[..., 1]
    coarse = _value_noise(u, v, coarse_cell, salt)
    mid = _value_noise(u, v, mid_cell, salt ^ _U32(0x9E3779B9))
    g = [_cell_hash(u, v, grain_cell / 3.0**k, salt ^ _U32(0x85EBCA6B + k)) for k in range(_GRAIN_OCTAVES)]
    grain = sum(_unit(h) for h in g) / _GRAIN_OCTAVES - 0.5
    lum = 1.0 + 2 * coarse_amp * (coarse - 0.5) + 2 * mid_amp * (mid - 0.5) + 2 * grain_amp * grain
    # colour: a per-surface tint direction scaled by the coarse noise, and a little chroma in the grain
    tint = jnp.stack([_unit(hash_u32(salt ^ _U32(k))) for k in (0x1B873593, 0xCC9E2D51, 0xE6546B64)], axis=-1) - 0.5
    chroma = jnp.stack([_unit(g[-1] * _U32(m)) for m in (0x2545F491, 0x9E3779B1, 0x632BE5AB)], axis=-1) - 0.5
    rgb = lum[..., None] * (1.0 + 2 * tint_amp[..., None] * tint * (0.5 + coarse[..., None])) \
        + _CHROMA * grain_amp[..., None] * chroma
    return jnp.maximum(rgb, 0.0)


def _cell_hash(u, v, cell, salt):
    return _lattice(jnp.floor(u / cell).astype(jnp.int32), jnp.floor(v / cell).astype(jnp.int32), salt)


def sky_detail(direction: Float[Array, "*batch 3"], seed: UInt32[Array, ""]) -> Float[Array, "*batch 3"]:
    """Multiplicative detail (around 1) of the sky along unit world ``direction`` (CARLA frame):
    soft clouds on a dome projection and a fine grain, both functions of the direction alone (the
    sky is at infinity), so every camera sees the same sky."""
    dx, dy, dz = direction[..., 0], direction[..., 1], direction[..., 2]
    lift = 1.0 / (jnp.maximum(dz, 0.0) + 0.25)
    salt = hash_u32(seed ^ _U32(0x27D4EB2F))
    cloud = _value_noise(dx * lift, dy * lift, jnp.float32(0.35), salt)
    cloud = cloud + 0.5 * _value_noise(dx * lift, dy * lift, jnp.float32(0.12), salt ^ _U32(0x165667B1))
    cell = jnp.float32(_SKY_GRAIN_RAD)
    g = hash_u32(_lattice(jnp.floor(dx / cell).astype(jnp.int32), jnp.floor(dy / cell).astype(jnp.int32), salt)
                 + jnp.floor(dz / cell).astype(jnp.int32).astype(_U32))
    grain = _unit(g) - 0.5
    lum = 1.0 + _SKY_CLOUD * (cloud - 0.75) + _SKY_GRAIN * grain
    return jnp.broadcast_to(jnp.maximum(lum, 0.0)[..., None], direction.shape)
