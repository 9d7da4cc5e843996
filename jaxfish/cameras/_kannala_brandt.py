"""The Kannala-Brandt / OpenCV fisheye model (4 odd distortion coefficients), valid beyond 90 degrees."""

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
from ._domain import first_increasing_limit, invert_increasing

KB_THETA_MAX_MARGIN_RAD = 1e-3
"""When theta_d(theta) has a stationary point theta_s <= pi, the valid domain is
[0, theta_s - margin] (same rule as `WoodScapeFisheye`)."""
_MAX_NEWTON_STEPS = 32
_GUESS_STEPS = 3


def theta_d_of_theta(k: Float[Array, "4"], theta: Float[Array, "*batch"]) -> Float[Array, "*batch"]:
    """theta_d = θ (1 + k1 θ² + k2 θ⁴ + k3 θ⁶ + k4 θ⁸) (OpenCV fisheye distortion)."""
    t2 = theta * theta
    return theta * (1 + t2 * (k[0] + t2 * (k[1] + t2 * (k[2] + t2 * k[3]))))


def dtheta_d_dtheta(k: Float[Array, "4"], theta: Float[Array, "*batch"]) -> Float[Array, "*batch"]:
    """d theta_d / d theta = 1 + 3 k1 θ² + 5 k2 θ⁴ + 7 k3 θ⁶ + 9 k4 θ⁸."""
    t2 = theta * theta
    return 1 + t2 * (3 * k[0] + t2 * (5 * k[1] + t2 * (7 * k[2] + t2 * (9 * k[3]))))


@jax.jit
def kb_theta_max(k: Float[Array, "4"]) -> Float[Array, ""]:
    """The end of the Kannala-Brandt domain for coefficients ``k`` (radians): where ``theta_d(theta)``
    stops increasing, less `KB_THETA_MAX_MARGIN_RAD` (jitted once per dtype)."""
    return first_increasing_limit(dtheta_d_dtheta, k, k.dtype, margin=KB_THETA_MAX_MARGIN_RAD)


def _residual(theta, args):
    k, theta_d = args
    return theta_d_of_theta(k, theta) - theta_d  # radians already


@jax.jit
def solve_theta_kb(
    k: Float[Array, "4"], theta_d: Float[Array, "*batch"], theta_max: Float[Array, ""]
) -> tuple[Float[Array, "*batch"], Bool[Array, "*batch"]]:
    """Invert theta_d(theta) = theta_d on [0, theta_max] with an element-wise optimistix Newton
    (diagonal Jacobian, fused clipped-Newton initial guess from ``theta = theta_d``; repeated from
    a bisection should it fail anywhere: `invert_increasing`). Gradients are implicit (exact).
    Returns ``(theta, converged)`` with a per-element residual check."""
    dtype = theta_d.dtype
    tol = 1e-11 if dtype == jnp.float64 else 4e-6
    kk = jax.lax.stop_gradient(k)
    td0 = jax.lax.stop_gradient(theta_d)
    theta0 = jnp.clip(td0, 0.0, theta_max)
    for _ in range(_GUESS_STEPS):
        step = (theta_d_of_theta(kk, theta0) - td0) / jnp.maximum(dtheta_d_dtheta(kk, theta0), eps_for(dtype))
        theta0 = jnp.clip(theta0 - step, 0.0, theta_max)

    return invert_increasing(theta_d_of_theta, _residual, k, theta_d, theta_max, theta0, rtol=tol, atol=tol,
                             max_steps=_MAX_NEWTON_STEPS)


class KannalaBrandt(AbstractCamera):
    """The Kannala-Brandt model as OpenCV's ``cv2.fisheye`` (4 odd coefficients, no skew).

    Projection of a camera-frame point ``(X, Y, Z)`` (OpenCV frame)::

        theta = atan2(sqrt(X² + Y²), Z)                       # in [0, pi]
        theta_d = θ (1 + k1 θ² + k2 θ⁴ + k3 θ⁶ + k4 θ⁸)
        u = fx theta_d X / chi + cx,   v = fy theta_d Y / chi + cy

    ``(cx, cy)`` is the pixel of the optical axis in jaxfish's pixel-centre convention (integer
    coordinates at pixel centres: the same as OpenCV's). Unlike ``cv2.fisheye`` (which clamps at
    90 degrees), the model is used on its whole **valid domain** ``[0, theta_max]``: ``theta_max``
    is pi when theta_d(θ) increases on [0, pi], else its first stationary point minus
    `KB_THETA_MAX_MARGIN_RAD`. Points beyond it, the camera centre and the ray straight behind
    the axis are invalid; pixels with ``|((u-cx)/fx, (v-cy)/fy)| > theta_d(theta_max)`` have no
    ray. Values and gradients are finite everywhere, including the principal point.

    Fields: `fx`, `fy`, `cx`, `cy` (pixels), `k` ``(4,)`` (dimensionless), `width`, `height` (static).
    """

    fx: Float[Array, ""]
    fy: Float[Array, ""]
    cx: Float[Array, ""]
    cy: Float[Array, ""]
    k: Float[Array, "4"]
    width: int = eqx.field(static=True)
    height: int = eqx.field(static=True)

    def __init__(self, fx, fy, cx, cy, k: Float[ArrayLike, "4"] = (0.0, 0.0, 0.0, 0.0), *, width: int, height: int,
                 dtype=None):
        dtype = resolve_dtype(dtype, fx)
        self.fx = jnp.asarray(fx, dtype=dtype)
        self.fy = jnp.asarray(fy, dtype=dtype)
        self.cx = jnp.asarray(cx, dtype=dtype)
        self.cy = jnp.asarray(cy, dtype=dtype)
        k = jnp.asarray(k, dtype=dtype)
        if k.shape[-1:] != (4,):
            raise ValueError(f"KannalaBrandt: k must have shape (..., 4), got {k.shape}")
        self.k = k
        width, height = check_image_size(width, height, "KannalaBrandt")
        self.width = width
        self.height = height

    def domain_problem(self) -> str | None:
        """Why the parameters lie outside the model's domain (focal lengths positive), or None."""
        return focal_problem(self.fx, self.fy)

    @property
    def principal_point(self) -> Float[Array, "2"]:
        """``(cx, cy)`` in pixel-centre coordinates."""
        return jnp.stack([self.cx, self.cy], axis=-1)

    @property
    def intrinsic_matrix(self) -> Float[Array, "3 3"]:
        """OpenCV's K (pixel-centre convention, no skew), for ``cv2.fisheye`` with ``D = k``."""
        z = jnp.zeros_like(self.fx)
        return jnp.stack([jnp.stack([self.fx, z, self.cx]), jnp.stack([z, self.fy, self.cy]),
                          jnp.stack([z, z, jnp.ones_like(self.fx)])])

    def theta_d(self, theta: Float[ArrayLike, "*batch"]) -> Float[Array, "*batch"]:
        """Distorted angle theta_d (radians) of the incidence angle theta (radians)."""
        theta = jnp.asarray(theta)
        dtype = float_dtype(theta)
        return theta_d_of_theta(self.k.astype(dtype), theta.astype(dtype))

    def theta_max(self, dtype=None) -> Float[Array, ""]:
        """Largest valid incidence angle (radians), see the class docstring."""
        dtype = resolve_dtype(dtype, self.k)
        return kb_theta_max(self.k.astype(dtype))

    def project(
        self, points: Float[ArrayLike, "*batch 3"]
    ) -> tuple[Float[Array, "*batch 2"], Bool[Array, "*batch"]]:
        """Pixels ``(..., 2)`` of camera-frame points ``(..., 3)`` and their validity."""
        p, dtype = as_coordinates(points, 3, "KannalaBrandt.project: points")
        k = self.k.astype(dtype)
        x, y, z, finite = point_direction(p)  # exactly rescaled: huge and tiny points keep their direction
        chi = safe_hypot(x, y)
        r = safe_hypot(x, y, z)
        nonzero = r > 0
        theta = incidence_angle(jnp.where(nonzero, chi, 0.0), jnp.where(nonzero, z, 1.0))
        # theta_d / chi = (theta_d / θ) (θ / chi): smooth at chi = 0, exact near the back axis.
        theta_over_chi, defined = radial_ratio(theta, chi, r, z)
        t2 = theta * theta
        td_over_t = 1 + t2 * (k[0] + t2 * (k[1] + t2 * (k[2] + t2 * k[3])))
        ratio = td_over_t * theta_over_chi
        u = self.fx.astype(dtype) * x * ratio + self.cx.astype(dtype)
        v = self.fy.astype(dtype) * y * ratio + self.cy.astype(dtype)
        valid = finite & defined & (theta <= self.theta_max(dtype))
        return finite_or_invalid(jnp.stack([u, v], axis=-1), valid)

    def unproject(
        self, uv: Float[ArrayLike, "*batch 2"]
    ) -> tuple[Float[Array, "*batch 3"], Bool[Array, "*batch"]]:
        """Unit rays ``(..., 3)`` of pixels ``(..., 2)``; invalid beyond ``theta_d(theta_max)``."""
        uv, dtype = as_coordinates(uv, 2, "KannalaBrandt.unproject: uv")
        uv, finite = finite_pixels(uv)
        k = self.k.astype(dtype)
        mx = (uv[..., 0] - self.cx.astype(dtype)) / self.fx.astype(dtype)
        my = (uv[..., 1] - self.cy.astype(dtype)) / self.fy.astype(dtype)
        r2 = mx * mx + my * my
        measurable = jnp.isfinite(r2)  # squares overflow for huge pixels (float32): invalid, not NaN
        r2 = jnp.where(measurable, r2, 0.0)
        td = jnp.where(r2 > 0, jnp.sqrt(jnp.where(r2 > 0, r2, 1.0)), 0.0)
        td = jax.lax.optimization_barrier(td)
        theta_max = self.theta_max(dtype)
        td_max = theta_d_of_theta(jax.lax.stop_gradient(k), theta_max)
        inside = td <= td_max * (1 + 4 * eps_for(dtype))  # the pixel of theta_max itself, after rounding
        theta, converged = solve_theta_kb(k, jnp.minimum(td, td_max), theta_max)
        # sin(θ)/theta_d, with its Taylor expansion near the principal point.
        tau = jnp.asarray(math.sqrt(eps_for(dtype)) * 100, dtype)
        small = td < tau
        safe_td = jnp.where(small, jnp.ones_like(td), td)
        taylor = 1 - (k[0] + 1.0 / 6.0) * td * td
        s = jnp.where(small, taylor, jnp.sin(theta) / safe_td)
        ray = stack_last([mx * s, my * s, jnp.cos(theta)])
        return finite_or_invalid(ray, inside & converged & measurable & finite)
