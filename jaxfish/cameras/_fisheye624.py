"""Project Aria's ``Fisheye624``: Kannala-Brandt with 6 radial, 2 tangential and 4 thin-prism
coefficients (projectaria_tools ``FisheyeRadTanThinPrism``)."""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Bool, Float

from .._numerics import eps_for, float_dtype, incidence_angle, radial_ratio, resolve_dtype, safe_hypot, stack_last
from ._base import (
    AbstractCamera,
    as_coordinates,
    check_image_size,
    finite_or_invalid,
    finite_pixels,
    focal_problem,
    point_direction,
)
from ._distortion import MAX_DISTORTED_RADIUS, as_distortion, undistort, unfolded
from ._domain import first_increasing_limit, invert_increasing
from ._kannala_brandt import KB_THETA_MAX_MARGIN_RAD

_MAX_NEWTON_STEPS = 32
_GUESS_STEPS = 3


def theta_d_of_theta_624(k: Float[Array, "6"], theta: Float[Array, "*batch"]) -> Float[Array, "*batch"]:
    """theta_d = θ (1 + k0 θ² + k1 θ⁴ + k2 θ⁶ + k3 θ⁸ + k4 θ¹⁰ + k5 θ¹²)."""
    return theta * _td_over_theta(k, theta * theta)


def _td_over_theta(k: Array, t2: Array) -> Array:
    return 1 + t2 * (k[0] + t2 * (k[1] + t2 * (k[2] + t2 * (k[3] + t2 * (k[4] + t2 * k[5])))))


def dtheta_d_dtheta_624(k: Float[Array, "6"], theta: Float[Array, "*batch"]) -> Float[Array, "*batch"]:
    """d theta_d / d theta = 1 + 3 k0 θ² + 5 k1 θ⁴ + ... + 13 k5 θ¹²."""
    t2 = theta * theta
    return 1 + t2 * (3 * k[0] + t2 * (5 * k[1] + t2 * (7 * k[2] + t2 * (9 * k[3] + t2 * (11 * k[4]
                                                                                        + t2 * 13 * k[5])))))


@jax.jit
def _theta_max_624(k: Float[Array, "6"]) -> Float[Array, ""]:
    return first_increasing_limit(dtheta_d_dtheta_624, k, k.dtype, margin=KB_THETA_MAX_MARGIN_RAD)


def tangential_prism(ps: Float[Array, "6"], xr: Float[Array, "*batch"], yr: Float[Array, "*batch"]
                     ) -> tuple[Float[Array, "*batch"], Float[Array, "*batch"]]:
    """projectaria's tangential and thin-prism terms on the radially distorted ``(xr, yr)``,
    ``ps = (p0, p1, s0, s1, s2, s3)``::

        r² = xr² + yr²,  t = 2 (p0 xr + p1 yr)
        xd = xr (1 + t) + p0 r² + s0 r² + s1 r⁴
        yd = yr (1 + t) + p1 r² + s2 r² + s3 r⁴
    """
    p0, p1, s0, s1, s2, s3 = (ps[..., i] for i in range(6))
    r2 = xr * xr + yr * yr
    t = 1 + 2 * (p0 * xr + p1 * yr)
    return xr * t + r2 * (p0 + s0 + s1 * r2), yr * t + r2 * (p1 + s2 + s3 * r2)


def _residual(theta, args):
    k, theta_d = args
    return theta_d_of_theta_624(k, theta) - theta_d


class Fisheye624(AbstractCamera):
    """Project Aria's ``Fisheye624`` model (projectaria_tools ``FisheyeRadTanThinPrism`` with
    separate ``fx, fy``; Aria's single focal length is ``fx = fy``).

    Projection of a camera-frame point ``(X, Y, Z)`` (OpenCV frame)::

        theta = atan2(sqrt(X² + Y²), Z)
        theta_d = θ (1 + k0 θ² + k1 θ⁴ + k2 θ⁶ + k3 θ⁸ + k4 θ¹⁰ + k5 θ¹²)
        (xr, yr) = theta_d (X, Y) / sqrt(X² + Y²),   r² = xr² + yr²
        xd = xr + p0 (2 xr² + r²) + 2 p1 xr yr + s0 r² + s1 r⁴
        yd = yr + p1 (2 yr² + r²) + 2 p0 xr yr + s2 r² + s3 r⁴
        u = fx xd + cx,   v = fy yd + cy

    (projectaria's ``p0`` multiplies OpenCV's ``p2`` term and ``p1`` its ``p1`` term.) Like
    `KannalaBrandt`, the model is used on its whole domain, beyond 90 degrees: ``theta <=
    theta_max``, pi when theta_d increases on ``[0, pi]``, else its first stationary point minus
    `KB_THETA_MAX_MARGIN_RAD`; and the tangential and prism map must be unfolded from the principal
    point to ``(xr, yr)`` (a positive Jacobian determinant along that segment; beyond a fold the
    point is invalid), with the distorted point at most `MAX_DISTORTED_RADIUS` focal lengths out. The camera centre and the
    ray straight behind the axis are invalid. Unprojection inverts the tangential and prism map by
    a 2 x 2 optimistix Newton solve per pixel from ``(xd, yd)``, then theta_d by the element-wise
    Newton solve of `KannalaBrandt`; gradients are implicit (exact). Pixel-centre convention.

    Fields: `fx`, `fy`, `cx`, `cy` (pixels), `k` ``(6,)`` = k0..k5, `p` ``(2,)`` = p0, p1,
    `s` ``(4,)`` = s0..s3 (dimensionless), `width`, `height` (static).
    """

    fx: Float[Array, ""]
    fy: Float[Array, ""]
    cx: Float[Array, ""]
    cy: Float[Array, ""]
    k: Float[Array, "6"]
    p: Float[Array, "2"]
    s: Float[Array, "4"]
    width: int = eqx.field(static=True)
    height: int = eqx.field(static=True)

    def __init__(self, fx, fy, cx, cy, k: Float[ArrayLike, "6"] = (0.0,) * 6, p: Float[ArrayLike, "2"] = (0.0, 0.0),
                 s: Float[ArrayLike, "4"] = (0.0,) * 4, *, width: int, height: int, dtype=None):
        dtype = resolve_dtype(dtype, fx)
        self.fx = jnp.asarray(fx, dtype=dtype)
        self.fy = jnp.asarray(fy, dtype=dtype)
        self.cx = jnp.asarray(cx, dtype=dtype)
        self.cy = jnp.asarray(cy, dtype=dtype)
        self.k = as_distortion(k, 6, (6,), dtype, "Fisheye624 (k)")
        self.p = as_distortion(p, 2, (2,), dtype, "Fisheye624 (p)")
        self.s = as_distortion(s, 4, (4,), dtype, "Fisheye624 (s)")
        self.width, self.height = check_image_size(width, height, "Fisheye624")

    def domain_problem(self) -> str | None:
        """Why the parameters lie outside the model's domain (focal lengths positive), or None."""
        return focal_problem(self.fx, self.fy)

    @property
    def principal_point(self) -> Float[Array, "2"]:
        """``(cx, cy)`` in pixel-centre coordinates."""
        return jnp.stack([self.cx, self.cy], axis=-1)

    def theta_d(self, theta: Float[ArrayLike, "*batch"]) -> Float[Array, "*batch"]:
        """Radially distorted angle theta_d (radians) of the incidence angle theta (radians)."""
        theta = jnp.asarray(theta)
        dtype = float_dtype(theta)
        return theta_d_of_theta_624(self.k.astype(dtype), theta.astype(dtype))

    def theta_max(self, dtype=None) -> Float[Array, ""]:
        """Largest valid incidence angle of the radial part (radians), see the class docstring."""
        dtype = resolve_dtype(dtype, self.k)
        return _theta_max_624(self.k.astype(dtype))

    def _ps(self, dtype) -> Array:
        return jnp.concatenate([self.p.astype(dtype), self.s.astype(dtype)], axis=-1)

    @eqx.filter_jit
    def project(
        self, points: Float[ArrayLike, "*batch 3"]
    ) -> tuple[Float[Array, "*batch 2"], Bool[Array, "*batch"]]:
        """Pixels ``(..., 2)`` of camera-frame points ``(..., 3)`` and their validity."""
        p, dtype = as_coordinates(points, 3, "Fisheye624.project: points")
        k = self.k.astype(dtype)
        ps = self._ps(dtype)
        x, y, z, finite = point_direction(p)  # exactly rescaled: huge and tiny points keep their direction
        chi = safe_hypot(x, y)
        r = safe_hypot(x, y, z)
        nonzero = r > 0
        theta = incidence_angle(jnp.where(nonzero, chi, 0.0), jnp.where(nonzero, z, 1.0))
        theta_over_chi, defined = radial_ratio(theta, chi, r, z)
        ratio = _td_over_theta(k, theta * theta) * theta_over_chi
        xr, yr = x * ratio, y * ratio
        xd, yd = tangential_prism(ps, xr, yr)
        u = self.fx.astype(dtype) * xd + self.cx.astype(dtype)
        v = self.fy.astype(dtype) * yd + self.cy.astype(dtype)
        near = (jnp.abs(xd) <= MAX_DISTORTED_RADIUS) & (jnp.abs(yd) <= MAX_DISTORTED_RADIUS)
        valid = (finite & defined & near & (theta <= self.theta_max(dtype))
                 & unfolded(tangential_prism, ps, xr, yr))
        return finite_or_invalid(jnp.stack([u, v], axis=-1), valid)

    @eqx.filter_jit
    def unproject(
        self, uv: Float[ArrayLike, "*batch 2"]
    ) -> tuple[Float[Array, "*batch 3"], Bool[Array, "*batch"]]:
        """Unit rays ``(..., 3)`` of pixels ``(..., 2)`` and their validity."""
        uv, dtype = as_coordinates(uv, 2, "Fisheye624.unproject: uv")
        uv, finite = finite_pixels(uv)
        k = self.k.astype(dtype)
        ps = self._ps(dtype)
        xd = (uv[..., 0] - self.cx.astype(dtype)) / self.fx.astype(dtype)
        yd = (uv[..., 1] - self.cy.astype(dtype)) / self.fy.astype(dtype)
        measurable = (jnp.abs(xd) <= MAX_DISTORTED_RADIUS) & (jnp.abs(yd) <= MAX_DISTORTED_RADIUS)
        xd, yd = jnp.where(measurable, xd, 0.0), jnp.where(measurable, yd, 0.0)
        xr, yr, converged = undistort(tangential_prism, ps, xd, yd, (xd, yd))
        folded = ~unfolded(tangential_prism, ps, xr, yr)
        td2 = xr * xr + yr * yr
        td = jnp.where(td2 > 0, jnp.sqrt(jnp.where(td2 > 0, td2, 1.0)), 0.0)
        theta_max = self.theta_max(dtype)
        td_max = theta_d_of_theta_624(jax.lax.stop_gradient(k), theta_max)
        inside = td <= td_max * (1 + 4 * eps_for(dtype))  # the pixel of theta_max itself, after rounding
        kk, td0 = jax.lax.stop_gradient(k), jax.lax.stop_gradient(jnp.minimum(td, td_max))
        theta0 = td0
        for _ in range(_GUESS_STEPS):
            step = (theta_d_of_theta_624(kk, theta0) - td0) / jnp.maximum(dtheta_d_dtheta_624(kk, theta0), eps_for(dtype))
            theta0 = jnp.clip(theta0 - step, 0.0, theta_max)
        tol = 1e-11 if dtype == jnp.float64 else 4e-6
        theta, solved = invert_increasing(theta_d_of_theta_624, _residual, k, jnp.minimum(td, td_max), theta_max, theta0,
                                          rtol=tol, atol=tol, max_steps=_MAX_NEWTON_STEPS)
        # sin(θ)/theta_d, with its Taylor expansion near the principal point.
        tau = jnp.asarray(math.sqrt(eps_for(dtype)) * 100, dtype)
        small = td < tau
        safe_td = jnp.where(small, jnp.ones_like(td), td)
        s = jnp.where(small, 1 - (k[0] + 1.0 / 6.0) * td * td, jnp.sin(theta) / safe_td)
        ray = stack_last([xr * s, yr * s, jnp.cos(theta)])
        valid = finite & measurable & converged & ~folded & inside & solved
        return finite_or_invalid(ray, valid)
