"""NVIDIA's f-theta model: the ray angle as a polynomial of the pixel radius (Omniverse / Isaac Sim
``fthetaPoly*``, NCore ``FThetaCameraModelParameters``)."""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float

from .._numerics import eps_for, incidence_angle, radial_ratio, resolve_dtype, safe_hypot, stack_last
from ._base import (
    AbstractCamera,
    affine_problem,
    as_coordinates,
    check_image_size,
    finite_or_invalid,
    finite_pixels,
    point_direction,
)
from ._domain import invert_increasing
from ._pixel_radius import affine_solve, first_stationary_radius, polyder, polyval

FTHETA_POLY_LENGTH = 5
"""Coefficients of each polynomial after its constant term (degree 1 to 5: NCore stores 6
coefficients including the constant, Omniverse ``fthetaPolyA..E`` 5 or ``..F`` 6)."""
_MAX_NEWTON_STEPS = 32
_GUESS_STEPS = 3


def _full(k: Array) -> Array:
    return jnp.concatenate([jnp.zeros_like(k[..., :1]), k], axis=-1)


def theta_of_radius(bw: Float[Array, " 5"], r: Float[Array, "*batch"]) -> Float[Array, "*batch"]:
    """The backward polynomial: ray angle (radians) of the pixel radius ``r`` (pixels),
    ``bw1 r + bw2 r² + ... + bw5 r⁵``."""
    return polyval(_full(bw), r)


def _dtheta_dr(bw, r):
    return polyval(polyder(_full(bw)), r)


def _residual(r, args):
    bw, theta = args
    return theta_of_radius(bw, r) - theta  # radians


class FTheta(AbstractCamera):
    """NVIDIA's f-theta camera: the angle between a ray and the optical axis is a polynomial of
    the pixel distance from the principal point (the *backward* polynomial, NCore's
    ``pixeldist_to_angle_poly``, Omniverse's ``fthetaPolyA..E``); the optional *forward*
    polynomial (``angle_to_pixeldist_poly``) is only an approximation of its inverse.

    Unprojection of a pixel ``(u, v)``::

        [u - cx, v - cy] = [[c, d], [e, 1]] [x, y]        # NCore's linear_cde (identity by default)
        r = sqrt(x² + y²),  theta = bw1 r + bw2 r² + ... + bw5 r⁵
        ray = (sin(theta) x / r, sin(theta) y / r, cos(theta))

    Projection is its exact inverse: ``r`` solves ``bw(r) = theta`` (optimistix Newton from the
    forward polynomial ``fw1 θ + ... + fw5 θ⁵`` when given, else from ``theta / bw1``; implicit
    gradients), then ``(x, y) = r (X, Y) / sqrt(X² + Y²)`` and ``[u, v] = [cx, cy] + [[c, d],
    [e, 1]] [x, y]``. Both polynomials have no constant term (a constant would send the principal
    point to a cone of rays: a file with a non-zero one is not representable). ``(cx, cy)``
    are in jaxfish's pixel-centre convention, which is NCore's.

    **Domain**: radii ``r`` in ``[0, r_max]`` where ``bw`` increases (`rho_max`: the image
    diagonal ``sqrt(W² + H²)``, or the first stationary point of ``bw`` before it minus ``1e-3
    sqrt(W² + H²) / pi`` pixels), and angles up to `theta_max` = ``min(bw(r_max), max_angle,
    pi)``. Points beyond `theta_max`, the camera centre, the ray straight behind the axis, and
    pixels beyond either limit are invalid; ``bw1 <= 0`` has no valid ray. Values and gradients
    are finite everywhere.

    Fields: `cx`, `cy` (pixels); `bw` ``(5,)`` (radians per pixel^i); `fw` ``(5,)`` (pixels per
    radian^i); `max_angle` (radians, the largest ray angle from the axis: half the field of
    view); `c`, `d`, `e` (dimensionless); `width`, `height` (static).
    """

    cx: Float[Array, ""]
    cy: Float[Array, ""]
    bw: Float[Array, " 5"]
    fw: Float[Array, " 5"]
    max_angle: Float[Array, ""]
    c: Float[Array, ""]
    d: Float[Array, ""]
    e: Float[Array, ""]
    width: int = eqx.field(static=True)
    height: int = eqx.field(static=True)

    def __init__(self, cx, cy, bw: Float[ArrayLike, " n"], fw: Float[ArrayLike, " n"] = (), *, max_angle=math.pi,
                 c=1.0, d=0.0, e=0.0, width: int, height: int, dtype=None):
        dtype = resolve_dtype(dtype, bw, cx)
        self.cx = jnp.asarray(cx, dtype=dtype)
        self.cy = jnp.asarray(cy, dtype=dtype)
        self.bw = _padded(bw, "bw", dtype)
        self.fw = _padded(fw, "fw", dtype)
        self.max_angle = jnp.asarray(max_angle, dtype=dtype)
        self.c = jnp.asarray(c, dtype=dtype)
        self.d = jnp.asarray(d, dtype=dtype)
        self.e = jnp.asarray(e, dtype=dtype)
        self.width, self.height = check_image_size(width, height, "FTheta")

    def domain_problem(self) -> str | None:
        """Why the parameters lie outside the model's domain (an invertible affine matrix
        ``[[c, d], [e, 1]]``: ``c - d e != 0``), or None."""
        return affine_problem(self.c, self.d, self.e)

    @property
    def principal_point(self) -> Float[Array, " 2"]:
        """``(cx, cy)`` in pixel-centre coordinates."""
        return jnp.stack([self.cx, self.cy], axis=-1)

    def rho_max(self, dtype=None) -> Float[Array, ""]:
        """Largest pixel radius (sensor plane) where the backward polynomial still increases."""
        dtype = resolve_dtype(dtype, self.bw)
        bw = jax.lax.stop_gradient(self.bw.astype(dtype))
        return first_stationary_radius(_dtheta_dr, bw, jnp.asarray(math.hypot(self.width, self.height), dtype), dtype)

    def theta_max(self, dtype=None) -> Float[Array, ""]:
        """Largest valid ray angle (radians): ``min(bw(rho_max), max_angle, pi)``."""
        dtype = resolve_dtype(dtype, self.bw)
        bw = jax.lax.stop_gradient(self.bw.astype(dtype))
        top = jnp.minimum(theta_of_radius(bw, self.rho_max(dtype)),
                          jax.lax.stop_gradient(self.max_angle.astype(dtype)))
        return jnp.clip(top, 0.0, math.pi)

    def _limits(self, bw, dtype):
        """``(r_lim, theta_lim)``: the radius of `theta_max` and `theta_max` itself."""
        r_max = self.rho_max(dtype)
        theta_lim = self.theta_max(dtype)
        bw_sg = jax.lax.stop_gradient(bw)
        r_lim, _ = invert_increasing(theta_of_radius, _residual, bw_sg, theta_lim, r_max,
                                     jnp.minimum(theta_lim / bw_sg[0], r_max), rtol=1e-12, atol=1e-12)
        return jax.lax.stop_gradient(r_lim), theta_lim

    def with_fitted_inverse(self) -> FTheta:
        """A copy whose forward polynomial ``fw`` is the least-squares fit of the exact inverse of
        ``bw`` over the domain (NCore keeps both). Only the Newton start of `project` depends on
        it; NumPy, not traceable."""
        dtype = np.float64 if jax.config.jax_enable_x64 else np.float32
        bw = np.concatenate([[0.0], np.asarray(self.bw, dtype=np.float64)])
        r_lim = float(self._limits(jnp.asarray(self.bw, dtype), dtype)[0])
        r = np.linspace(0.0, r_lim, 1024)
        theta = np.polynomial.polynomial.polyval(r, bw)
        fw = np.linalg.lstsq(np.stack([theta**i for i in range(1, FTHETA_POLY_LENGTH + 1)], -1), r, rcond=None)[0]
        return eqx.tree_at(lambda c: c.fw, self, jnp.asarray(fw, self.fw.dtype))

    @eqx.filter_jit
    def project(
        self, points: Float[ArrayLike, "*batch 3"]
    ) -> tuple[Float[Array, "*batch 2"], Bool[Array, "*batch"]]:
        """Pixels ``(..., 2)`` of camera-frame points ``(..., 3)`` and their validity."""
        p, dtype = as_coordinates(points, 3, "FTheta.project: points")
        bw = self.bw.astype(dtype)
        lens = bw[0] > 0
        bw = jnp.where(lens, bw, jnp.zeros_like(bw).at[0].set(1.0))
        x, y, z, finite = point_direction(p)
        chi = safe_hypot(x, y)
        r = safe_hypot(x, y, z)
        nonzero = r > 0
        theta = incidence_angle(jnp.where(nonzero, chi, 0.0), jnp.where(nonzero, z, 1.0))
        theta_over_chi, defined = radial_ratio(theta, chi, r, z)
        r_lim, theta_lim = self._limits(bw, dtype)
        inside = theta <= theta_lim
        target = jnp.minimum(theta, theta_lim)
        radius0 = self._initial_radius(jax.lax.stop_gradient(bw), jax.lax.stop_gradient(target), r_lim, dtype)
        tol = 1e-11 if dtype == jnp.float64 else 4e-6
        radius, converged = invert_increasing(theta_of_radius, _residual, bw, target, r_lim, radius0, rtol=tol,
                                              atol=tol, max_steps=_MAX_NEWTON_STEPS)
        tiny = jnp.asarray(math.sqrt(eps_for(dtype)), dtype)
        small = target < tiny
        r_over_theta = jnp.where(small, 1.0 / bw[0] - bw[1] * target / bw[0] ** 3,
                                 radius / jnp.where(small, jnp.ones_like(target), target))
        ratio = r_over_theta * theta_over_chi
        xs, ys = x * ratio, y * ratio
        u = self.c.astype(dtype) * xs + self.d.astype(dtype) * ys + self.cx.astype(dtype)
        v = self.e.astype(dtype) * xs + ys + self.cy.astype(dtype)
        invertible = self.c.astype(dtype) - self.d.astype(dtype) * self.e.astype(dtype) != 0  # else one line of pixels
        valid = finite & defined & inside & converged & lens & invertible
        return finite_or_invalid(jnp.stack([u, v], axis=-1), valid)

    def _initial_radius(self, bw, theta, r_lim, dtype) -> Array:
        fw = jax.lax.stop_gradient(self.fw.astype(dtype))
        use_fw = jnp.any(fw != 0)
        radius = jnp.clip(jnp.where(use_fw, polyval(_full(fw), theta), theta / bw[0]), 0.0, r_lim)
        for _ in range(_GUESS_STEPS):
            step = (theta_of_radius(bw, radius) - theta) / jnp.maximum(_dtheta_dr(bw, radius), eps_for(dtype) * bw[0])
            radius = jnp.clip(radius - step, 0.0, r_lim)
        return radius

    @eqx.filter_jit
    def unproject(
        self, uv: Float[ArrayLike, "*batch 2"]
    ) -> tuple[Float[Array, "*batch 3"], Bool[Array, "*batch"]]:
        """Unit rays ``(..., 3)`` of pixels ``(..., 2)``; invalid beyond the domain."""
        uv, dtype = as_coordinates(uv, 2, "FTheta.unproject: uv")
        uv, finite = finite_pixels(uv)
        bw = self.bw.astype(dtype)
        lens = bw[0] > 0
        bw = jnp.where(lens, bw, jnp.zeros_like(bw).at[0].set(1.0))
        c, d, e = self.c.astype(dtype), self.d.astype(dtype), self.e.astype(dtype)
        invertible = c - d * e != 0
        xs, ys = affine_solve(c, d, e, uv[..., 0] - self.cx.astype(dtype), uv[..., 1] - self.cy.astype(dtype))
        radius = safe_hypot(xs, ys)
        measurable = jnp.isfinite(radius)
        radius = jnp.where(measurable, radius, 0.0)
        xs, ys = jnp.where(measurable, xs, 0.0), jnp.where(measurable, ys, 0.0)
        r_lim, theta_lim = self._limits(bw, dtype)
        rc = jnp.minimum(radius, r_lim)
        theta = theta_of_radius(bw, rc)
        inside = (radius <= r_lim * (1 + 4 * eps_for(dtype))) & (theta <= theta_lim * (1 + 4 * eps_for(dtype)))
        tiny = jnp.asarray(math.sqrt(eps_for(dtype)), dtype)
        small = rc < tiny
        s = jnp.where(small, bw[0] + bw[1] * rc, jnp.sin(theta) / jnp.where(small, jnp.ones_like(rc), rc))
        ray = stack_last([xs * s, ys * s, jnp.cos(theta)])
        return finite_or_invalid(ray, inside & measurable & finite & lens & invertible)


def _padded(values, name: str, dtype) -> Array:
    a = jnp.asarray(values, dtype=dtype)
    if a.ndim == 0:
        raise ValueError(f"FTheta: {name} must be a sequence of coefficients, got a scalar")
    n = FTHETA_POLY_LENGTH
    if a.shape[-1] > n:
        raise ValueError(f"FTheta: {name} has {a.shape[-1]} coefficients, at most {n} (degrees 1 to {n}) are supported")
    return jnp.pad(a, [(0, 0)] * (a.ndim - 1) + [(0, n - a.shape[-1])])
