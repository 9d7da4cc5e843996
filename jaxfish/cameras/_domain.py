"""Validity domains of radial lens models: where the image radius stops increasing."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

_GRID = 2048
"""Grid and bisection steps used to locate the first stationary point on [0, pi]."""
_BISECTIONS = 60
_GUESS_BISECTIONS = 20
"""Bisection steps of `bisection_guess` (the fallback start of the inverse-polynomial Newton solves)."""


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


def bisection_guess(f, params, target: Float[Array, "*batch"], theta_max: Float[Array, ""]) -> Float[Array, "*batch"]:
    """Element-wise bisection of ``f(params, theta) = target`` on ``[0, theta_max]``, where ``f``
    increases (the valid domain), to ``pi / 2**20`` (3e-6 rad): inside Newton's quadratic basin
    even next to a stationary point (``THETA_MAX_MARGIN_RAD`` = 1e-3 away), so the Newton solve
    that starts from it converges. Not differentiated (that solve is)."""
    params = jax.lax.stop_gradient(params)
    target = jax.lax.stop_gradient(target)
    steps = _GUESS_BISECTIONS

    def bisect(_, bracket):
        a, b = bracket
        m = 0.5 * (a + b)
        low = f(params, m) < target
        return jnp.where(low, m, a), jnp.where(low, b, m)

    zero = jnp.zeros_like(target)
    lo, hi = jax.lax.fori_loop(0, steps, bisect, (zero, zero + theta_max.astype(target.dtype)))
    return 0.5 * (lo + hi)


@jax.custom_batching.custom_vmap
def all_of_batch(flags):
    """``jnp.all(flags)``, and under ``vmap`` the ``all`` over the whole batch as one unbatched
    scalar: a ``lax.cond`` on it stays a branch (a batched predicate turns ``cond`` into a select
    that runs both branches)."""
    return jnp.all(flags)


@all_of_batch.def_vmap
def _all_of_batch_vmap(axis_size, in_batched, flags):
    return all_of_batch(flags), False


def solve_with_fallback(solve, f, params, target: Float[Array, "*batch"], theta_max: Float[Array, ""],
                        theta0: Float[Array, "*batch"]):
    """``solve(theta0)`` -> ``(theta, converged)``; if any element did not converge (Newton can
    cycle where the lens polynomial has an inflection, near a stationary point), solve again from
    `bisection_guess`. The retry runs only when needed: a ``lax.cond`` on `all_of_batch`, which
    stays a branch under ``vmap`` over cameras."""
    theta, converged = solve(theta0)
    return jax.lax.cond(all_of_batch(jax.lax.stop_gradient(converged)), lambda: (theta, converged),
                        lambda: solve(bisection_guess(f, params, target, theta_max)))
