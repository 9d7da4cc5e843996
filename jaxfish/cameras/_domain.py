"""Validity domains of radial lens models (where the image radius stops increasing) and the inverse of
the radius polynomial on them."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import lineax as lx
import optimistix as optx
from jaxtyping import Array, ArrayLike, Bool, Float

from .._numerics import eps_for

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
    lo, hi = bisection_bracket(lambda theta: f(params, theta), target, theta_max, _GUESS_BISECTIONS)
    return 0.5 * (lo + hi)


def bisection_bracket(f, target: Float[Array, "*batch"], upper: Float[ArrayLike, ""], steps: int
                      ) -> tuple[Float[Array, "*batch"], Float[Array, "*batch"]]:
    """``(lo, hi)`` after ``steps`` element-wise bisections of ``f(theta) = target`` on
    ``[0, upper]`` (``f`` increasing there; ``target``'s dtype): ``f(lo) < target <= f(hi)`` when
    the root lies inside, the bracket ``upper / 2**steps`` wide."""

    def bisect(_, bracket):
        a, b = bracket
        m = 0.5 * (a + b)
        low = f(m) < target
        return jnp.where(low, m, a), jnp.where(low, b, m)

    zero = jnp.zeros_like(target)
    return jax.lax.fori_loop(0, steps, bisect, (zero, zero + jnp.asarray(upper).astype(target.dtype)))


@jax.custom_batching.custom_vmap
def all_of_batch(flags):
    """``jnp.all(flags)``, and under ``vmap`` the ``all`` over the whole batch as one unbatched
    scalar: a ``lax.cond`` on it stays a branch (a batched predicate turns ``cond`` into a select
    that runs both branches)."""
    return jnp.all(flags)


@all_of_batch.def_vmap
def _all_of_batch_vmap(axis_size, in_batched, flags):
    return all_of_batch(flags), False


def invert_increasing(f, residual, params, target: Float[Array, "*batch"], theta_max: Float[Array, ""],
                      theta0: Float[Array, "*batch"], *, rtol: float, atol: float, max_steps: int = 32
                      ) -> tuple[Float[Array, "*batch"], Bool[Array, "*batch"]]:
    """Solve ``f(params, theta) = target`` element-wise on ``[0, theta_max]`` (where ``f`` increases)
    with optimistix Newton from ``theta0``: one root-finding problem with a *diagonal* Jacobian,
    ``residual(theta, (params, target))`` in radians; gradients implicit (exact). Returns
    ``(theta, converged)``, `converged` a per-element check ``|f - target| <= 64 eps max(|target|, 1)``.

    Should Newton fail anywhere (it can cycle where ``f`` has an inflection before a stationary
    point), the solve is repeated from `bisection_guess`: a ``lax.cond`` on `all_of_batch`, so it
    runs only when needed and stays a branch under ``vmap`` over cameras."""
    dtype = target.dtype
    if target.size == 0:  # no pixels: nothing to solve (lineax's diagonal solve reduces over them)
        return jnp.zeros(target.shape, dtype), jnp.zeros(target.shape, bool)

    def newton(start):
        sol = optx.root_find(
            residual, optx.Newton(rtol=rtol, atol=atol), start, args=(params, target),
            options=dict(lower=jnp.zeros((), dtype), upper=theta_max.astype(dtype)),
            max_steps=max_steps, throw=False, tags=frozenset({lx.diagonal_tag}),
        )
        theta = sol.value
        error = jnp.abs(f(params, theta) - target)
        converged = (error <= 64 * eps_for(dtype) * jnp.maximum(jnp.abs(target), 1.0)) & jnp.isfinite(theta)
        return jnp.where(jnp.isfinite(theta), theta, jnp.zeros_like(theta)), converged

    theta, converged = newton(theta0)
    return jax.lax.cond(all_of_batch(jax.lax.stop_gradient(converged)), lambda: (theta, converged),
                        lambda: newton(bisection_guess(f, params, target, theta_max)))
