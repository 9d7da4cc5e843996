"""The standard optical-flow colour coding (Baker et al. 2007, as the ``flow_vis`` package) and
the event colour rendering, as pure JAX functions."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float, UInt8

from .._numerics import arctan2, materialize

WHEEL_SEGMENTS: tuple[int, ...] = (15, 6, 4, 11, 13, 6)
"""Hues of the colour wheel: red-yellow 15, yellow-green 6, green-cyan 4, cyan-blue 11,
blue-magenta 13, magenta-red 6 (55 in all)."""


def flow_colour_wheel() -> np.ndarray:
    """The 55 x 3 colour wheel (RGB, float values in 0..255) of Baker et al. (``flow_vis``)."""
    ry, yg, gc, cb, bm, mr = WHEEL_SEGMENTS
    wheel = np.zeros((sum(WHEEL_SEGMENTS), 3))
    ramp = lambda n: np.floor(255 * np.arange(n) / n)  # noqa: E731
    col = 0
    wheel[col : col + ry, 0] = 255
    wheel[col : col + ry, 1] = ramp(ry)
    col += ry
    wheel[col : col + yg, 0] = 255 - ramp(yg)
    wheel[col : col + yg, 1] = 255
    col += yg
    wheel[col : col + gc, 1] = 255
    wheel[col : col + gc, 2] = ramp(gc)
    col += gc
    wheel[col : col + cb, 1] = 255 - ramp(cb)
    wheel[col : col + cb, 2] = 255
    col += cb
    wheel[col : col + bm, 2] = 255
    wheel[col : col + bm, 0] = ramp(bm)
    col += bm
    wheel[col : col + mr, 2] = 255 - ramp(mr)
    wheel[col : col + mr, 0] = 255
    return wheel


def flow_to_color(
    flow: Float[ArrayLike, "*batch H W 2"],
    *,
    valid: Bool[ArrayLike, "*batch H W"] | None = None,
    max_radius: float | None = None,
) -> UInt8[Array, "*batch H W 3"]:
    """RGB uint8 colour coding of a flow field ``(u, v)`` in pixels (u right, v down).

    Hue is the direction and saturation the magnitude, normalised by ``max_radius`` (default: the
    largest magnitude over the valid pixels of each image, plus 1e-5, as ``flow_vis``); magnitudes
    beyond 1 are darkened by 0.75. Invalid pixels (``valid`` False) are black. Matches
    ``flow_vis.flow_to_color`` bit for bit in float64.
    """
    f = jnp.asarray(flow)
    if f.shape[-1:] != (2,) or f.ndim < 3:
        raise ValueError(f"flow_to_color: flow must have shape (..., H, W, 2), got {f.shape}")
    dtype = f.dtype if jnp.issubdtype(f.dtype, jnp.floating) else jnp.float32
    f = f.astype(dtype)
    ok = jnp.ones(f.shape[:-1], bool) if valid is None else jnp.asarray(valid, bool)
    f = jnp.where(ok[..., None], f, 0.0)
    # Planes, computed once: XLA:CPU reduces (the max) and fuses interleaved (..., 2) data far more
    # slowly than separate planes.
    u, v = materialize((f[..., 0], f[..., 1]), f.reshape(-1)[0])
    if max_radius is None:
        # max(sqrt(x)) == sqrt(max(x)) exactly (sqrt is monotone and correctly rounded): one sqrt.
        rmax = jnp.sqrt(jnp.max(u * u + v * v, axis=(-2, -1), keepdims=True))
    else:
        rmax = jnp.asarray(max_radius, dtype)
    scale = rmax + jnp.asarray(1e-5, dtype)
    u, v = u / scale, v / scale
    wheel = jnp.asarray(flow_colour_wheel(), dtype) / 255.0
    n = wheel.shape[0]
    rad = jnp.sqrt(u * u + v * v)
    a = arctan2(-v, -u) / jnp.pi  # float32: a polynomial that vectorises; float64: jnp.arctan2 (flow_vis parity)
    fk = (a + 1) / 2 * (n - 1)
    k0 = jnp.floor(fk).astype(jnp.int32)
    k1 = jnp.where(k0 + 1 == n, 0, k0 + 1)
    frac = fk - k0.astype(dtype)
    inside = rad <= 1
    # One plane per channel, materialised before the interleave: fused into the minor-axis
    # (..., 3) output, XLA:CPU runs the whole colour computation in a loop that does not vectorise.
    planes = []
    for c in range(3):
        w = wheel[:, c]
        col = (1 - frac) * w[k0] + frac * w[k1]
        col = jnp.where(inside, 1 - rad * (1 - col), col * 0.75)
        planes.append(jnp.where(ok, jnp.floor(255 * col).astype(jnp.uint8), jnp.uint8(0)))
    return jnp.stack(materialize(planes, u.reshape(-1)[0]), axis=-1)


def events_to_color(
    x: ArrayLike, y: ArrayLike, polarity: ArrayLike, *, width: int, height: int, valid: ArrayLike | None = None
) -> UInt8[Array, "H W 3"]:
    """Render events on a white ``height x width`` image: pixels whose events sum to a net positive
    polarity are blue ``(0, 0, 255)``, net negative red ``(255, 0, 0)``, no event or a tie white."""
    xi = jnp.asarray(x).astype(jnp.int32)
    yi = jnp.asarray(y).astype(jnp.int32)
    ok = (xi >= 0) & (xi < width) & (yi >= 0) & (yi < height)
    if valid is not None:
        ok = ok & jnp.asarray(valid, bool)
    sign = jnp.where(jnp.asarray(polarity, bool), 1, -1).astype(jnp.int32)
    flat = jnp.where(ok, yi * width + xi, 0)
    net = jnp.zeros(width * height, jnp.int32).at[flat].add(jnp.where(ok, sign, 0)).reshape(height, width)
    white = jnp.full((height, width, 3), 255, jnp.uint8)
    blue = jnp.asarray([0, 0, 255], jnp.uint8)
    red = jnp.asarray([255, 0, 0], jnp.uint8)
    out = jnp.where((net > 0)[..., None], blue, white)
    return jnp.where((net < 0)[..., None], red, out)
