"""The double sphere camera model (Usenko, Demmel and Cremers, 3DV 2018)."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Bool, Float

from .._numerics import resolve_dtype, safe_hypot, safe_norm, safe_sqrt
from ._base import (
    AbstractCamera,
    as_coordinates,
    check_image_size,
    clear_of_rim,
    finite_or_invalid,
    finite_pixels,
    focal_problem,
    interval_problem,
    measurable_radius,
    point_direction,
)
from ._unified import unified_w


def double_sphere_cos_theta_max(xi: Array, alpha: Array) -> Array:
    """Cosine of the end of the double sphere's domain (`DoubleSphere`): ``c* = -ξ(1 - w₁²) - w₁
    sqrt(1 - ξ²(1 - w₁²))`` with ``w₁ = unified_w(α)``, for ξ <= 1; ``-1/ξ`` for ξ > 1 (where
    ``d1 + ξ Z`` vanishes first). May lie below -1 (then the domain reaches pi)."""
    w1 = unified_w(alpha)
    rest = 1 - w1 * w1
    inner = -xi * rest - w1 * safe_sqrt(1 - xi * xi * rest)
    return jnp.where(xi > 1, -1.0 / jnp.where(xi > 1, xi, 1.0), inner)


class DoubleSphere(AbstractCamera):
    """The double sphere model: a point is projected onto a unit sphere, shifted by ``ξ`` along the
    axis, then projected by the unified model UCM(α).

    With ``d1 = |(X, Y, Z)|``, the shifted point ``(X, Y, zz)``, ``zz = ξ d1 + Z``, and
    ``d2 = |(X, Y, zz)|`` (OpenCV camera frame)::

        u = fx X / (α d2 + (1-α) zz) + cx,   v = fy Y / (α d2 + (1-α) zz) + cy

    ``ξ`` in (-1, 1] (at ξ = -1 the optical axis itself is degenerate), ``α`` in [0, 1];
    ξ = 0 is the UCM, ξ = 1 with α = 0 the stereographic projection.

    Domain, from the construction: on the unit sphere (``d1 = 1``, incidence angle θ,
    ``c = cos θ``) the normalised image radius is ``r = sin θ / D`` with
    ``D = α d2 + (1-α)(ξ + c)`` and ``d2 = sqrt(1 + 2ξc + ξ²)``, and::

        dr/dθ = (1 + ξc) (α (ξ + c) + (1-α) d2) / (d2 D²)

    so a point is valid exactly where ``D > 0`` and the radius still increases:
    ``α zz + (1-α) d2 > 0`` (and ``d1 + ξ Z > 0``, always true for ξ in (-1, 1] off the back
    axis). Together: ``zz > -w1 d2`` with ``w1 = unified_w(α)``, the UCM(α) domain applied to the
    shifted point. The shifted point's cosine ``zz / d2`` increases with ``c`` (derivative
    ``(1 + ξc) / d2³``), so the domain is ``θ < theta_max``, ``cos(theta_max)`` the root of
    ``(ξ + c)² = w1² (1 + 2ξc + ξ²)`` with ``ξ + c <= 0``::

        cos(theta_max) = -ξ (1 - w1²) - w1 sqrt(1 - ξ² (1 - w1²))

    (`double_sphere_cos_theta_max`; pi when that is <= -1). This is wider or narrower than the
    paper's ``w2 = (w1 + ξ) / sqrt(2 w1 ξ + ξ² + 1)`` bound, which is not the model's boundary:
    ξ = -0.9, α = 0.7 folds at 60.97 degrees (the paper's bound: 62.4), the stereographic
    ξ = 1, α = 0 is valid up to 180 degrees (the paper's bound: 135).

    Unprojection (closed form: the UCM(α) inverse, then the unique point of the unit sphere on
    that ray from the shifted centre)::

        mz = (1 - α² r²) / (α sqrt(1 - (2α-1) r²) + 1 - α)
        ray = (mz ξ + sqrt(mz² + (1-ξ²) r²)) / (mz² + r²) (mx, my, mz) - (0, 0, ξ)

    defined for α <= 0.5 or ``r² <= 1/(2α-1)`` (``r`` = distance to the principal point in
    focal units, the image of the domain's rim); a pixel is valid when its ray is in the domain.
    Pixel-centre convention; finite values and gradients everywhere.

    Fields: `fx`, `fy`, `cx`, `cy` (pixels), `xi`, `alpha`, `width`, `height` (static).
    """

    fx: Float[Array, ""]
    fy: Float[Array, ""]
    cx: Float[Array, ""]
    cy: Float[Array, ""]
    xi: Float[Array, ""]
    alpha: Float[Array, ""]
    width: int = eqx.field(static=True)
    height: int = eqx.field(static=True)

    def __init__(self, fx, fy, cx, cy, xi, alpha, *, width: int, height: int, dtype=None):
        dtype = resolve_dtype(dtype, fx)
        self.fx = jnp.asarray(fx, dtype=dtype)
        self.fy = jnp.asarray(fy, dtype=dtype)
        self.cx = jnp.asarray(cx, dtype=dtype)
        self.cy = jnp.asarray(cy, dtype=dtype)
        self.xi = jnp.asarray(xi, dtype=dtype)
        self.alpha = jnp.asarray(alpha, dtype=dtype)
        width, height = check_image_size(width, height, "DoubleSphere")
        self.width = width
        self.height = height

    def domain_problem(self) -> str | None:
        """Why the parameters lie outside the model's domain (focal lengths positive, ``alpha`` in
        [0, 1]), or None."""
        return focal_problem(self.fx, self.fy) or interval_problem("alpha", self.alpha, 0.0, 1.0)

    @property
    def principal_point(self) -> Float[Array, "2"]:
        """``(cx, cy)`` in pixel-centre coordinates."""
        return jnp.stack([self.cx, self.cy], axis=-1)

    def theta_max(self, dtype=None) -> Float[Array, ""]:
        """Supremum of the valid incidence angles (radians, exclusive), in closed form (class
        docstring): pi when the whole sphere but the back axis is valid."""
        dtype = resolve_dtype(dtype, self.alpha)
        xi = jax.lax.stop_gradient(self.xi.astype(dtype))
        alpha = jax.lax.stop_gradient(self.alpha.astype(dtype))
        return jnp.arccos(jnp.clip(double_sphere_cos_theta_max(xi, alpha), -1.0, 1.0))

    def project(
        self, points: Float[ArrayLike, "*batch 3"]
    ) -> tuple[Float[Array, "*batch 2"], Bool[Array, "*batch"]]:
        """Pixels ``(..., 2)`` of camera-frame points ``(..., 3)`` and their validity."""
        p, dtype = as_coordinates(points, 3, "DoubleSphere.project: points")
        xi = self.xi.astype(dtype)
        alpha = self.alpha.astype(dtype)
        x, y, z, finite = point_direction(p)  # exactly rescaled: huge and tiny points keep their direction
        d1 = safe_hypot(x, y, z)
        zz = xi * d1 + z
        d2 = safe_sqrt(x * x + y * y + zz * zz)
        denom = alpha * d2 + (1 - alpha) * zz
        rising = alpha * zz + (1 - alpha) * d2  # the sign of dr/dtheta (with d1 + xi z)
        in_domain = (alpha >= 0) & (alpha <= 1)  # traced parameters outside it: nothing is valid
        valid = finite & in_domain & (d1 > 0) & (d1 + xi * z > 0) & clear_of_rim(denom, x, y, z) & (rising > 0)
        inv = 1.0 / jnp.where(valid, denom, jnp.ones_like(denom))
        u = self.fx.astype(dtype) * x * inv + self.cx.astype(dtype)
        v = self.fy.astype(dtype) * y * inv + self.cy.astype(dtype)
        return finite_or_invalid(jnp.stack([u, v], axis=-1), valid)

    def unproject(
        self, uv: Float[ArrayLike, "*batch 2"]
    ) -> tuple[Float[Array, "*batch 3"], Bool[Array, "*batch"]]:
        """Unit rays ``(..., 3)`` of pixels ``(..., 2)`` and their validity."""
        uv, dtype = as_coordinates(uv, 2, "DoubleSphere.unproject: uv")
        uv, finite = finite_pixels(uv)
        xi = self.xi.astype(dtype)
        alpha = self.alpha.astype(dtype)
        mx = (uv[..., 0] - self.cx.astype(dtype)) / self.fx.astype(dtype)
        my = (uv[..., 1] - self.cy.astype(dtype)) / self.fy.astype(dtype)
        measurable = measurable_radius(mx, my)
        mx, my = jnp.where(measurable, mx, 0.0), jnp.where(measurable, my, 0.0)
        r2 = mx * mx + my * my
        disc = 1 - (2 * alpha - 1) * r2
        den = alpha * safe_sqrt(disc) + 1 - alpha
        inside = ((alpha <= 0.5) | (disc >= 0)) & (den > 0)  # den = 0: alpha = 1 at or beyond the rim
        mz = (1 - alpha * alpha * r2) / jnp.where(den > 0, den, 1.0)
        disc2 = mz * mz + (1 - xi * xi) * r2
        inside = inside & (disc2 >= 0)
        factor = (mz * xi + safe_sqrt(disc2)) / (mz * mz + r2)
        ray = jnp.stack([factor * mx, factor * my, factor * mz - xi], axis=-1)
        norm = safe_norm(ray, keepdims=True)
        ray = ray / jnp.where(norm > 0, norm, jnp.ones_like(norm))
        _, back = self.project(ray)
        return finite_or_invalid(ray, inside & back & (norm[..., 0] > 0) & measurable & finite)
