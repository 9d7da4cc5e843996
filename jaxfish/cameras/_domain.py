"""Validity domains of radial lens models: where the image radius stops increasing."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

_GRID = 2048
"""Grid and bisection steps used to locate the first stationary point on [0, pi]."""
_BISECTIONS = 60


def first_increasing_limit(derivative, params, dtype, *, margin: float) -> Float[Array, ""]:
    """Largest theta in [0, pi] up to which ``derivative(params, theta) > 0`` holds from 0 on.

    Returns pi when the derivative stays positive on the whole grid, else the first sign change
    (grid + bisection, exact to float precision) minus ``margin``; 0 if the derivative is not
    positive at 0. Not differentiated: a domain boundary is a mask, not a value.
    """
    params = jax.lax.stop_gradient(params)
    grid = jnp.linspace(0.0, math.pi, _GRID + 1, dtype=dtype)
    bad = derivative(params, grid) <= 0
    first = jnp.argmax(bad)
    lo = grid[jnp.maximum(first - 1, 0)]
    hi = grid[first]

    def bisect(_, bracket):
        a, b = bracket
        m = 0.5 * (a + b)
        m_bad = derivative(params, m) <= 0
        return jnp.where(m_bad, a, m), jnp.where(m_bad, m, b)

    lo, hi = jax.lax.fori_loop(0, _BISECTIONS, bisect, (lo, hi))
    stationary = jnp.maximum(lo - margin, 0.0)
    return jnp.where(jnp.any(bad), stationary, jnp.asarray(math.pi, dtype))
