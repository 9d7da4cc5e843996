"""Devernay and Faugeras' field-of-view (FOV) lens model (COLMAP ``FOV``)."""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Bool, Float

from .._numerics import (
    arctan2,
    eps_for,
    float_dtype,
    incidence_angle,
    radial_ratio,
    resolve_dtype,
    safe_hypot,
    safe_norm,
)
from ._base import (
    AbstractCamera,
    as_coordinates,
    check_image_size,
    clear_of_rim,
    finite_or_invalid,
    finite_pixels,
    focal_problem,
    measurable_radius,
    point_direction,
)


def _tan_half_ratio(w: Array) -> Array:
    """``2 tan(w/2) / w`` (even in w, 1 at w = 0), with its Taylor expansion near 0."""
    small = jnp.abs(w) < jnp.asarray(math.sqrt(math.sqrt(eps_for(w.dtype))), w.dtype)
    safe = jnp.where(small, 1.0, w)
    w2 = w * w
    return jnp.where(small, 1 + w2 / 12 + w2 * w2 / 120, 2 * jnp.tan(safe / 2) / safe)


def _sinc(a: Array) -> Array:
    """``sin(a) / a``, 1 at 0, with its Taylor expansion near 0."""
    small = jnp.abs(a) < jnp.asarray(math.sqrt(math.sqrt(eps_for(a.dtype))), a.dtype)
    safe = jnp.where(small, 1.0, a)
    a2 = a * a
    return jnp.where(small, 1 - a2 / 6 + a2 * a2 / 120, jnp.sin(safe) / safe)


class FieldOfView(AbstractCamera):
    """The FOV model of F. Devernay and O. Faugeras, "Straight lines have to be straight" (MVA
    2001), as COLMAP's ``FOV`` camera, extended beyond 90 degrees.

    With ``r_u = tan(theta)`` the pinhole radius of a point and ``ω = w`` the field of view of the
    ideal fisheye lens (radians)::

        r_d = atan(2 r_u tan(ω/2)) / ω   =   atan2(2 tan(ω/2) sin(theta), cos(theta)) / ω
        u = fx r_d X / chi + cx,   v = fy r_d Y / chi + cy,   chi = sqrt(X² + Y²)

    The second form is the first for ``theta < 90°`` (exactly COLMAP) and continues it behind the
    image plane: ``r_d`` increases strictly on ``[0, pi)`` for ``0 < |ω| < pi``, so the domain is
    every ray but the one straight behind the axis (`theta_max` = pi, exclusive); ``ω = 0`` is the
    pinhole (``theta < 90°``); the model is even in ω (COLMAP accepts either sign), and
    ``|ω| >= pi`` has no valid ray. Unprojection is closed form:
    ``theta = atan2(sin(ω r_d), 2 tan(ω/2) cos(ω r_d))``, valid for ``|ω| r_d < pi``. Finite
    values and gradients everywhere, including ``ω = 0`` and the principal point.

    Fields: `fx`, `fy`, `cx`, `cy` (pixels), `w` (ω, radians), `width`, `height` (static).
    """

    fx: Float[Array, ""]
    fy: Float[Array, ""]
    cx: Float[Array, ""]
    cy: Float[Array, ""]
    w: Float[Array, ""]
    width: int = eqx.field(static=True)
    height: int = eqx.field(static=True)

    def __init__(self, fx, fy, cx, cy, w, *, width: int, height: int, dtype=None):
        dtype = resolve_dtype(dtype, fx)
        self.fx = jnp.asarray(fx, dtype=dtype)
        self.fy = jnp.asarray(fy, dtype=dtype)
        self.cx = jnp.asarray(cx, dtype=dtype)
        self.cy = jnp.asarray(cy, dtype=dtype)
        self.w = jnp.asarray(w, dtype=dtype)
        self.width, self.height = check_image_size(width, height, "FieldOfView")

    def domain_problem(self) -> str | None:
        """Why the parameters lie outside the model's domain (focal lengths positive), or None."""
        return focal_problem(self.fx, self.fy)

    @property
    def principal_point(self) -> Float[Array, "2"]:
        """``(cx, cy)`` in pixel-centre coordinates."""
        return jnp.stack([self.cx, self.cy], axis=-1)

    def theta_max(self, dtype=None) -> Float[Array, ""]:
        """Supremum of the valid incidence angles (radians): pi for ``0 < |ω| < pi``, pi/2 for the
        pinhole ``ω = 0``, 0 for ``|ω| >= pi``."""
        dtype = resolve_dtype(dtype, self.w)
        w = jnp.abs(jax.lax.stop_gradient(self.w.astype(dtype)))
        return jnp.where(w >= math.pi, 0.0, jnp.where(w > 0, math.pi, math.pi / 2)).astype(dtype)

    def r_d(self, theta: Float[ArrayLike, "*batch"]) -> Float[Array, "*batch"]:
        """Distorted radius ``r_d`` (focal lengths) of the incidence angle ``theta`` (radians)."""
        theta = jnp.asarray(theta)
        dtype = float_dtype(theta)
        theta, w = theta.astype(dtype), self.w.astype(dtype)
        a = arctan2(jnp.tan(jnp.abs(w) / 2) * 2 * jnp.sin(theta), jnp.cos(theta))
        return jnp.where(w != 0, a / jnp.where(w != 0, jnp.abs(w), 1.0), jnp.tan(theta))

    @eqx.filter_jit
    def project(
        self, points: Float[ArrayLike, "*batch 3"]
    ) -> tuple[Float[Array, "*batch 2"], Bool[Array, "*batch"]]:
        """Pixels ``(..., 2)`` of camera-frame points ``(..., 3)`` and their validity."""
        p, dtype = as_coordinates(points, 3, "FieldOfView.project: points")
        w = jnp.abs(self.w.astype(dtype))
        lens = w < math.pi
        w = jnp.where(lens, w, 0.0)
        t2 = 2 * jnp.tan(w / 2)  # 2 tan(ω/2) >= 0
        x, y, z, finite = point_direction(p)  # exactly rescaled: huge and tiny points keep their direction
        chi = safe_hypot(x, y)
        # The angle a = ω r_d of the point (t2 chi, z): r_d / chi = a / (t2 chi) · t2 / ω.
        s = t2 * chi
        rr = safe_hypot(s, z)
        # (s, z) within eps of the origin (a grazing point of a lens with ω below ~eps): no image;
        # a safe stand-in keeps ~1/rr² out of the derivatives
        clear = clear_of_rim(rr, x, y, z)
        s, z, rr = jnp.where(clear, s, 0.0), jnp.where(clear, z, 1.0), jnp.where(clear, rr, 1.0)
        nonzero = rr > 0
        a = incidence_angle(jnp.where(nonzero, s, 0.0), jnp.where(nonzero, z, 1.0))
        a_over_s, defined = radial_ratio(a, s, rr, z)
        ratio = a_over_s * _tan_half_ratio(w)
        u = self.fx.astype(dtype) * x * ratio + self.cx.astype(dtype)
        v = self.fy.astype(dtype) * y * ratio + self.cy.astype(dtype)
        valid = finite & defined & lens & clear & (safe_hypot(x, y, z) > 0)
        return finite_or_invalid(jnp.stack([u, v], axis=-1), valid)

    @eqx.filter_jit
    def unproject(
        self, uv: Float[ArrayLike, "*batch 2"]
    ) -> tuple[Float[Array, "*batch 3"], Bool[Array, "*batch"]]:
        """Unit rays ``(..., 3)`` of pixels ``(..., 2)`` and their validity."""
        uv, dtype = as_coordinates(uv, 2, "FieldOfView.unproject: uv")
        uv, finite = finite_pixels(uv)
        w = jnp.abs(self.w.astype(dtype))
        lens = w < math.pi
        w = jnp.where(lens, w, 0.0)
        mx = (uv[..., 0] - self.cx.astype(dtype)) / self.fx.astype(dtype)
        my = (uv[..., 1] - self.cy.astype(dtype)) / self.fy.astype(dtype)
        measurable = measurable_radius(mx, my)
        mx, my = jnp.where(measurable, mx, 0.0), jnp.where(measurable, my, 0.0)
        rd = safe_hypot(mx, my)
        a = w * rd
        inside = a < math.pi
        a = jnp.where(inside, a, 0.0)
        # (t2 chi, z) ∝ (sin a, cos a): ray ∝ (m sin(a) / (t2 r_d), cos a) = (m sinc(a) ω / t2, cos a).
        scale = _sinc(a) / _tan_half_ratio(w)
        ray = jnp.stack([mx * scale, my * scale, jnp.cos(a)], axis=-1)
        ray = ray / safe_norm(ray, keepdims=True)
        return finite_or_invalid(ray, finite & measurable & lens & inside)
