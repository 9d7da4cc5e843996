"""The unified camera model (Mei / UCM) and the extended unified camera model (EUCM).

Formulas of Usenko, Demmel and Cremers, "The Double Sphere Camera Model" (3DV 2018), §3.2-3.3,
in jaxfish's pixel-centre convention.
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Bool, Float

from .._numerics import resolve_dtype, safe_norm, safe_sqrt
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


def unified_w(alpha: Array) -> Array:
    """w = α/(1-α) for α <= 0.5, else (1-α)/α: the projection domain is ``z > -w d``."""
    one = jnp.ones_like(alpha)
    low = alpha / jnp.where(alpha < 1, 1 - alpha, one)
    high = (1 - alpha) / jnp.where(alpha > 0, alpha, one)
    return jnp.where(alpha <= 0.5, low, high)


def _pixels_to_m(cam, uv: Array, dtype) -> tuple[Array, Array]:
    mx = (uv[..., 0] - cam.cx.astype(dtype)) / cam.fx.astype(dtype)
    my = (uv[..., 1] - cam.cy.astype(dtype)) / cam.fy.astype(dtype)
    return mx, my


def eucm_project(cam, points, alpha, beta, name: str):
    """Shared EUCM projection (UCM is beta = 1)."""
    p, dtype = as_coordinates(points, 3, f"{name}.project: points")
    alpha = alpha.astype(dtype)
    beta = beta.astype(dtype)
    x, y, z, finite = point_direction(p)  # exactly rescaled: huge and tiny points keep their direction
    nonzero = finite & ((x != 0) | (y != 0) | (z != 0))
    d = safe_sqrt(beta * (x * x + y * y) + z * z)
    w = unified_w(alpha)
    in_domain = (alpha >= 0) & (alpha <= 1) & (beta > 0)  # traced parameters outside it: nothing is valid
    valid = nonzero & in_domain & (z > -w * d)
    denom = alpha * d + (1 - alpha) * z
    valid = valid & clear_of_rim(denom, x, y, z)
    inv = 1.0 / jnp.where(valid, denom, jnp.ones_like(denom))
    u = cam.fx.astype(dtype) * x * inv + cam.cx.astype(dtype)
    v = cam.fy.astype(dtype) * y * inv + cam.cy.astype(dtype)
    return finite_or_invalid(jnp.stack([u, v], axis=-1), valid)


def eucm_unproject(cam, uv, alpha, beta, name: str):
    """Shared EUCM unprojection (UCM is beta = 1); rays are normalised."""
    uv, dtype = as_coordinates(uv, 2, f"{name}.unproject: uv")
    uv, finite = finite_pixels(uv)
    alpha = alpha.astype(dtype)
    beta = beta.astype(dtype)
    mx, my = _pixels_to_m(cam, uv, dtype)
    measurable = measurable_radius(mx, my)
    mx, my = jnp.where(measurable, mx, 0.0), jnp.where(measurable, my, 0.0)
    r2 = mx * mx + my * my
    disc = 1 - (2 * alpha - 1) * beta * r2
    den = alpha * safe_sqrt(disc) + (1 - alpha)
    inside = ((alpha <= 0.5) | (disc >= 0)) & (den > 0)  # den = 0: alpha = 1 at or beyond the domain's rim
    mz = (1 - beta * alpha * alpha * r2) / jnp.where(den > 0, den, 1.0)
    ray = jnp.stack([mx, my, mz], axis=-1)
    ray = ray / safe_norm(ray, keepdims=True)
    _, back = eucm_project(cam, ray, alpha, beta, name)
    return finite_or_invalid(ray, inside & back & measurable & finite)


def eucm_theta_max(alpha: Array, beta: Array) -> Array:
    """Largest valid incidence angle of ``z > -w sqrt(beta chi² + z²)`` (radians, exclusive)."""
    alpha, beta = jax.lax.stop_gradient(alpha), jax.lax.stop_gradient(beta)
    w = unified_w(alpha)
    return math.pi - jnp.arctan2(jnp.sqrt(jnp.maximum(1 - w * w, 0.0)), w * jnp.sqrt(beta))


class UnifiedCamera(AbstractCamera):
    """The unified camera model (UCM; Mei's model without distortion), in the α form.

    Projection of a camera-frame point ``(X, Y, Z)`` (OpenCV frame), ``d = |(X, Y, Z)|``::

        u = fx X / (α d + (1-α) Z) + cx,   v = fy Y / (α d + (1-α) Z) + cy

    with ``α`` in [0, 1] (α = 0 is a pinhole). Mei's ``(ξ, γ)``: ``ξ = α/(1-α)``,
    ``γ = f/(1-α)`` (`from_mei`, `xi`). Valid domain: ``Z > -w d`` with ``w = α/(1-α)`` for
    α <= 0.5 else ``(1-α)/α``, i.e. incidence angles below ``theta_max = arccos(-w)`` (more
    than 90 degrees for every α > 0). A pixel has a ray when α <= 0.5 or
    ``r² <= 1/(2α-1)`` (``r`` = distance to the principal point in focal units) and the ray
    lies in the valid domain. Pixel-centre convention; finite values and gradients everywhere.

    Fields: `fx`, `fy`, `cx`, `cy` (pixels), `alpha`, `width`, `height` (static).
    """

    fx: Float[Array, ""]
    fy: Float[Array, ""]
    cx: Float[Array, ""]
    cy: Float[Array, ""]
    alpha: Float[Array, ""]
    width: int = eqx.field(static=True)
    height: int = eqx.field(static=True)

    def __init__(self, fx, fy, cx, cy, alpha, *, width: int, height: int, dtype=None):
        dtype = resolve_dtype(dtype, fx)
        self.fx = jnp.asarray(fx, dtype=dtype)
        self.fy = jnp.asarray(fy, dtype=dtype)
        self.cx = jnp.asarray(cx, dtype=dtype)
        self.cy = jnp.asarray(cy, dtype=dtype)
        self.alpha = jnp.asarray(alpha, dtype=dtype)
        width, height = check_image_size(width, height, "UnifiedCamera")
        self.width = width
        self.height = height

    def domain_problem(self) -> str | None:
        """Why the parameters lie outside the model's domain (focal lengths positive, ``alpha`` in
        [0, 1]), or None."""
        return focal_problem(self.fx, self.fy) or interval_problem("alpha", self.alpha, 0.0, 1.0)

    @classmethod
    def from_mei(cls, xi, gamma_x, gamma_y, cx, cy, *, width: int, height: int, dtype=None) -> UnifiedCamera:
        """From Mei's parameters ``(ξ, γx, γy)`` (no distortion): ``u = γx X/(Z + ξ d) + cx``."""
        xi = float(xi)
        if xi < 0:
            raise ValueError(f"UnifiedCamera.from_mei: xi must be >= 0, got {xi}")
        return cls(gamma_x / (1 + xi), gamma_y / (1 + xi), cx, cy, xi / (1 + xi), width=width, height=height,
                   dtype=dtype)

    @property
    def xi(self) -> Float[Array, ""]:
        """Mei's ξ = α/(1-α)."""
        return self.alpha / (1 - self.alpha)

    @property
    def principal_point(self) -> Float[Array, "2"]:
        """``(cx, cy)`` in pixel-centre coordinates."""
        return jnp.stack([self.cx, self.cy], axis=-1)

    def theta_max(self, dtype=None) -> Float[Array, ""]:
        """Supremum of the valid incidence angles (radians): ``arccos(-w)``."""
        dtype = resolve_dtype(dtype, self.alpha)
        a = self.alpha.astype(dtype)
        return eucm_theta_max(a, jnp.ones_like(a))

    def project(
        self, points: Float[ArrayLike, "*batch 3"]
    ) -> tuple[Float[Array, "*batch 2"], Bool[Array, "*batch"]]:
        """Pixels ``(..., 2)`` of camera-frame points ``(..., 3)`` and their validity."""
        return eucm_project(self, points, self.alpha, jnp.ones_like(self.alpha), "UnifiedCamera")

    def unproject(
        self, uv: Float[ArrayLike, "*batch 2"]
    ) -> tuple[Float[Array, "*batch 3"], Bool[Array, "*batch"]]:
        """Unit rays ``(..., 3)`` of pixels ``(..., 2)`` and their validity."""
        return eucm_unproject(self, uv, self.alpha, jnp.ones_like(self.alpha), "UnifiedCamera")


class ExtendedUnifiedCamera(AbstractCamera):
    """The extended unified camera model (EUCM, Khomutenko et al. 2016).

    With ``d = sqrt(β (X² + Y²) + Z²)`` (OpenCV camera frame)::

        u = fx X / (α d + (1-α) Z) + cx,   v = fy Y / (α d + (1-α) Z) + cy

    ``α`` in [0, 1], ``β > 0``; β = 1 is the UCM. Valid domain ``Z > -w d`` (w as in
    `UnifiedCamera`), i.e. incidence angles below
    ``theta_max = pi - atan2(sqrt(1 - w²), w sqrt(β))`` (beyond 90 degrees for α > 0).
    Unprojection (closed form)::

        mz = (1 - β α² r²) / (α sqrt(1 - (2α-1) β r²) + 1 - α),   ray ∝ (mx, my, mz)

    defined for α <= 0.5 or ``r² <= 1/(β(2α-1))``; a pixel is valid when its ray is in the domain.
    Pixel-centre convention; finite values and gradients everywhere.

    Fields: `fx`, `fy`, `cx`, `cy` (pixels), `alpha`, `beta`, `width`, `height` (static).
    """

    fx: Float[Array, ""]
    fy: Float[Array, ""]
    cx: Float[Array, ""]
    cy: Float[Array, ""]
    alpha: Float[Array, ""]
    beta: Float[Array, ""]
    width: int = eqx.field(static=True)
    height: int = eqx.field(static=True)

    def __init__(self, fx, fy, cx, cy, alpha, beta=1.0, *, width: int, height: int, dtype=None):
        dtype = resolve_dtype(dtype, fx)
        self.fx = jnp.asarray(fx, dtype=dtype)
        self.fy = jnp.asarray(fy, dtype=dtype)
        self.cx = jnp.asarray(cx, dtype=dtype)
        self.cy = jnp.asarray(cy, dtype=dtype)
        self.alpha = jnp.asarray(alpha, dtype=dtype)
        self.beta = jnp.asarray(beta, dtype=dtype)
        width, height = check_image_size(width, height, "ExtendedUnifiedCamera")
        self.width = width
        self.height = height

    def domain_problem(self) -> str | None:
        """Why the parameters lie outside the model's domain (focal lengths positive, ``alpha`` in
        [0, 1], ``beta > 0``), or None."""
        return (focal_problem(self.fx, self.fy) or interval_problem("alpha", self.alpha, 0.0, 1.0)
                or interval_problem("beta", self.beta, 0.0, open_low=True))

    @property
    def principal_point(self) -> Float[Array, "2"]:
        """``(cx, cy)`` in pixel-centre coordinates."""
        return jnp.stack([self.cx, self.cy], axis=-1)

    def theta_max(self, dtype=None) -> Float[Array, ""]:
        """Supremum of the valid incidence angles (radians), see the class docstring."""
        dtype = resolve_dtype(dtype, self.alpha)
        return eucm_theta_max(self.alpha.astype(dtype), self.beta.astype(dtype))

    def project(
        self, points: Float[ArrayLike, "*batch 3"]
    ) -> tuple[Float[Array, "*batch 2"], Bool[Array, "*batch"]]:
        """Pixels ``(..., 2)`` of camera-frame points ``(..., 3)`` and their validity."""
        return eucm_project(self, points, self.alpha, self.beta, "ExtendedUnifiedCamera")

    def unproject(
        self, uv: Float[ArrayLike, "*batch 2"]
    ) -> tuple[Float[Array, "*batch 3"], Bool[Array, "*batch"]]:
        """Unit rays ``(..., 3)`` of pixels ``(..., 2)`` and their validity."""
        return eucm_unproject(self, uv, self.alpha, self.beta, "ExtendedUnifiedCamera")
