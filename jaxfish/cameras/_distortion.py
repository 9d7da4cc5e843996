"""Lens distortion on a 2-D plane: OpenCV's radial-tangential (rational, thin prism) distortion, the
domain on which it is invertible, and the inverse of any such 2-D distortion by optimistix Newton."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import optimistix as optx
from jaxtyping import Array, Bool, Float

from .._numerics import eps_for
from ._domain import first_increasing_limit

RADTAN_MARGIN_RAD = 1e-3
"""The radial-tangential domain ends this far (in ``atan(r)``, radians) before the first stationary
point of the radial distortion, and at ``atan(r) = pi/2 - margin`` (``r`` ≈ 1000) at most."""
_MAX_NEWTON_STEPS = 32
_GUESS_BISECTIONS = 40
"""Bisection steps of the radial starting point of the 2-D Newton solve (on ``atan(r)``)."""


MAX_DISTORTED_RADIUS = 1e6
"""In the models with a 2-D distortion (`OpenCVPinhole`, `MeiCamera`, `Fisheye624`), no point
projects farther than this many focal lengths from the principal point (in x or y), and such pixels
have no ray: far beyond any lens, and it keeps the Newton solve (and its implicit gradient) away
from overflowing squares."""


def edge_slack(dtype) -> float:
    """``1 + sqrt(eps)``: a point is inside a radial-tangential domain when ``r² <= r_max² (1 +
    sqrt(eps))``. Undistorting the pixel of the edge itself lands beyond ``r_max`` by rounding
    amplified by the small slope there (~1e-13 in float64); ``sqrt(eps)`` covers that and stays far
    inside the `RADTAN_MARGIN_RAD` before the fold."""
    return 1.0 + math.sqrt(eps_for(dtype))


def as_distortion(d, n: int, lengths: tuple[int, ...], dtype, where: str) -> Array:
    """``d`` as an array of ``n`` coefficients (zero-padded from any length in ``lengths``)."""
    d = jnp.asarray(d, dtype=dtype)
    if d.ndim < 1 or d.shape[-1] not in lengths:
        raise ValueError(f"{where}: distortion must have shape (..., L) with L in {lengths}, got {d.shape}")
    pad = [(0, 0)] * (d.ndim - 1) + [(0, n - d.shape[-1])]
    return jnp.pad(d, pad)


def radtan_distort(c: Float[Array, "12"], x: Float[Array, "*batch"], y: Float[Array, "*batch"]
                   ) -> tuple[Float[Array, "*batch"], Float[Array, "*batch"]]:
    """OpenCV's distortion of normalised coordinates ``(x, y)``, ``c`` in OpenCV's order
    ``(k1, k2, p1, p2, k3, k4, k5, k6, s1, s2, s3, s4)``::

        r² = x² + y²,   R = (1 + k1 r² + k2 r⁴ + k3 r⁶) / (1 + k4 r² + k5 r⁴ + k6 r⁶)
        xd = x R + 2 p1 x y + p2 (r² + 2 x²) + s1 r² + s2 r⁴
        yd = y R + p1 (r² + 2 y²) + 2 p2 x y + s3 r² + s4 r⁴

    A non-positive denominator (outside the domain) is replaced by 1: finite, masked by the caller."""
    k1, k2, p1, p2, k3, k4, k5, k6, s1, s2, s3, s4 = (c[..., i] for i in range(12))
    xy = x * y
    r2 = x * x + y * y
    num = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    den = 1 + r2 * (k4 + r2 * (k5 + r2 * k6))
    radial = num / jnp.where(den > 0, den, 1.0)
    xd = x * radial + 2 * p1 * xy + p2 * (r2 + 2 * x * x) + r2 * (s1 + s2 * r2)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * xy + r2 * (s3 + s4 * r2)
    return xd, yd


def _radial_slope(c: Float[Array, "12"], phi: Float[Array, "*batch"]) -> Float[Array, "*batch"]:
    """Sign of ``d(r R(r²))/dr`` at ``r = tan(phi / 2)`` (``phi`` in [0, pi]), -1 where the rational
    denominator is not positive. Evaluated homogeneously (multiplied by ``cos¹² (phi/2)``), so
    finite up to ``r = tan(pi/2 - margin)`` even in float32."""
    k1, k2, k3, k4, k5, k6 = c[0], c[1], c[4], c[5], c[6], c[7]
    beta = jnp.minimum(phi / 2, math.pi / 2 - RADTAN_MARGIN_RAD)
    cc = jnp.cos(beta) ** 2
    q = jnp.sin(beta) ** 2
    nh = cc * cc * cc + q * (k1 * cc * cc + q * (k2 * cc + q * k3))
    snp = q * (k1 * cc * cc + q * (2 * k2 * cc + q * 3 * k3))
    dh = cc * cc * cc + q * (k4 * cc * cc + q * (k5 * cc + q * k6))
    sdp = q * (k4 * cc * cc + q * (2 * k5 * cc + q * 3 * k6))
    g = (nh + 2 * snp) * dh - 2 * nh * sdp
    return jnp.where(dh > 0, g, -1.0)


@jax.jit
def radtan_r_max(c: Float[Array, "12"]) -> Float[Array, ""]:
    """Largest undistorted normalised radius ``r`` of the radial-tangential domain:
    ``tan(min(beta_s, pi/2) - RADTAN_MARGIN_RAD)``, ``beta_s = atan`` of the first radius where
    ``r R(r²)`` stops increasing or the rational denominator stops being positive (a grid and a
    bisection, `first_increasing_limit`). Not differentiated: a boundary is a mask."""
    c = jax.lax.stop_gradient(c)
    phi = first_increasing_limit(_radial_slope, c, c.dtype, margin=0.0)
    beta = jnp.minimum(phi / 2, math.pi / 2) - RADTAN_MARGIN_RAD
    return jnp.tan(jnp.maximum(beta, 0.0))


_FOLD_SAMPLES = 32
"""Points of the segment from the principal point at which `unfolded` checks the Jacobian."""


def unfolded(distort, c, x: Float[Array, "*batch"], y: Float[Array, "*batch"]) -> Bool[Array, "*batch"]:
    """Whether ``distort`` keeps a positive Jacobian determinant along the segment from ``(0, 0)`` to
    ``(x, y)`` (at `_FOLD_SAMPLES` evenly spaced points): the point lies before any fold of the
    distortion, on the sheet around the principal point. (A positive determinant at the point alone
    is not enough: beyond a fold it can turn positive again, on a sheet that overlaps the first.)"""

    def body(i, ok):
        t = (i + 1).astype(x.dtype) / _FOLD_SAMPLES
        return ok & (jacobian_det(distort, c, t * x, t * y) > 0)

    return jax.lax.fori_loop(0, _FOLD_SAMPLES, body, jnp.ones(x.shape, bool))


def jacobian_det(distort, c, x: Float[Array, "*batch"], y: Float[Array, "*batch"]) -> Float[Array, "*batch"]:
    """Determinant of the Jacobian of ``distort(c, x, y) -> (xd, yd)`` (two forward-mode passes, not
    differentiated)."""
    c, x, y = (jax.lax.stop_gradient(a) for a in (c, x, y))
    one = jnp.ones_like(x)
    _, (dxd_dx, dyd_dx) = jax.jvp(lambda a: distort(c, a, y), (x,), (one,))
    _, (dxd_dy, dyd_dy) = jax.jvp(lambda b: distort(c, x, b), (y,), (one,))
    return dxd_dx * dyd_dy - dxd_dy * dyd_dx


def radial_guess(c: Float[Array, "12"], xd: Float[Array, "*batch"], yd: Float[Array, "*batch"],
                 r_max: Float[Array, ""]) -> tuple[Float[Array, "*batch"], Float[Array, "*batch"]]:
    """A start for `undistort`: the radius ``r`` in ``[0, r_max]`` with ``r R(r²) = |(xd, yd)|``
    (bisection on ``atan(r)``, tangential and prism terms ignored), along ``(xd, yd)``."""
    c, xd, yd = (jax.lax.stop_gradient(a) for a in (c, xd, yd))
    rd = jnp.sqrt(xd * xd + yd * yd)
    zero = jnp.zeros_like(rd)
    radial_only = c * jnp.asarray([1, 1, 0, 0, 1, 1, 1, 1, 0, 0, 0, 0], c.dtype)

    def bisect(_, bracket):
        lo, hi = bracket
        m = 0.5 * (lo + hi)
        r = jnp.tan(m)
        low = radtan_distort(radial_only, r, zero)[0] < rd
        return jnp.where(low, m, lo), jnp.where(low, hi, m)

    lo, hi = jax.lax.fori_loop(0, _GUESS_BISECTIONS, bisect, (zero, zero + jnp.arctan(r_max).astype(rd.dtype)))
    r = jnp.tan(0.5 * (lo + hi))
    scale = jnp.where(rd > 0, r / jnp.where(rd > 0, rd, 1.0), 1.0)
    return xd * scale, yd * scale


def undistort(distort, c, xd: Float[Array, "*batch"], yd: Float[Array, "*batch"],
              guess: tuple[Float[Array, "*batch"], Float[Array, "*batch"]]
              ) -> tuple[Float[Array, "*batch"], Float[Array, "*batch"], Bool[Array, "*batch"]]:
    """Solve ``distort(c, x, y) = (xd, yd)`` for ``(x, y)`` point by point with optimistix Newton (a
    2 x 2 system per point, vmapped) from ``guess``; gradients with respect to ``c`` and the targets
    are implicit (exact). Returns ``(x, y, converged)``, `converged` a per-point residual check
    ``|distort - target| <= 64 eps max(|target|, 1)`` on both components. ``distort`` is a static
    function."""
    shape, dtype = xd.shape, xd.dtype
    if xd.size == 0:
        return jnp.zeros(shape, dtype), jnp.zeros(shape, dtype), jnp.zeros(shape, bool)
    tol = 1e-12 if dtype == jnp.float64 else 1e-6
    target = jnp.stack([xd.reshape(-1), yd.reshape(-1)], -1)
    start = jnp.stack([guess[0].reshape(-1), guess[1].reshape(-1)], -1)

    def residual(xy, args):
        cc, t = args
        dx, dy = distort(cc, xy[0], xy[1])
        return jnp.stack([dx, dy]) - t

    def one(t, y0):
        sol = optx.root_find(residual, optx.Newton(rtol=tol, atol=tol), y0, args=(c, t),
                             max_steps=_MAX_NEWTON_STEPS, throw=False)
        return sol.value

    xy = jax.vmap(one)(target, start)
    xy = jnp.where(jnp.isfinite(xy), xy, 0.0)
    x, y = xy[:, 0].reshape(shape), xy[:, 1].reshape(shape)
    bx, by = distort(jax.lax.stop_gradient(c), jax.lax.stop_gradient(x), jax.lax.stop_gradient(y))
    xd0, yd0 = jax.lax.stop_gradient(xd), jax.lax.stop_gradient(yd)
    bound = 64 * eps_for(dtype) * jnp.maximum(jnp.maximum(jnp.abs(xd0), jnp.abs(yd0)), 1.0)
    converged = (jnp.abs(bx - xd0) <= bound) & (jnp.abs(by - yd0) <= bound)
    return x, y, converged
