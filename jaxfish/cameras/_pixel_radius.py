"""Helpers shared by the lens models whose polynomial is a function of the *pixel* radius
(`OCamCalib`, `FTheta`): polynomial evaluation, the ``[c, d; e, 1]`` affine sensor map, and the
radius at which such a polynomial stops being usable."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from ._domain import first_increasing_limit

RADIUS_MARGIN = 1e-3
"""Relative margin (of the search bound) kept below the first stationary point of a pixel-radius
polynomial: at the stationary point itself the inverse has infinite slope."""


def polyval(coeffs: Float[Array, " n"], x: Float[Array, "*batch"]) -> Float[Array, "*batch"]:
    """``sum_i coeffs[i] x**i`` (lowest degree first), Horner form."""
    out = jnp.zeros_like(x) + coeffs[..., -1]
    for i in range(coeffs.shape[-1] - 2, -1, -1):
        out = out * x + coeffs[..., i]
    return out


def polyder(coeffs: Float[Array, " n"]) -> Float[Array, " n"]:
    """Coefficients of the derivative, padded with a trailing 0 to the same length."""
    n = coeffs.shape[-1]
    d = coeffs[..., 1:] * jnp.arange(1, n, dtype=coeffs.dtype)
    return jnp.concatenate([d, jnp.zeros_like(coeffs[..., :1])], axis=-1)


def first_stationary_radius(derivative, params, bound: Float[Array, ""], dtype) -> Float[Array, ""]:
    """Largest ``r`` in ``[0, bound]`` up to which ``derivative(params, r) > 0`` holds from 0 on:
    ``bound`` when it holds on the whole interval, else the first sign change minus
    ``RADIUS_MARGIN * bound / pi``; 0 when the derivative is not positive at 0. Not
    differentiated (a domain boundary is a mask). Uses `first_increasing_limit` on ``[0, pi]``
    through ``r = s * bound / pi``."""
    bound = jax.lax.stop_gradient(jnp.asarray(bound, dtype))
    scale = bound / math.pi

    def rescaled(p, s):
        return derivative(p, s * scale)

    s = first_increasing_limit(rescaled, params, dtype, margin=RADIUS_MARGIN)
    return s * scale


def affine_solve(c, d, e, a: Array, b: Array) -> tuple[Array, Array]:
    """``(x, y)`` with ``[a, b] = [[c, d], [e, 1]] [x, y]`` (the inverse of the affine sensor map)."""
    det = c - d * e
    inv = 1.0 / jnp.where(det != 0, det, 1.0)
    return inv * (a - d * b), inv * (-e * a + c * b)
