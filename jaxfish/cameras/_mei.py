"""Mei's omnidirectional camera: the unified model (ξ on the unit sphere) with radial-tangential
distortion (``cv2.omnidir``, kalibr ``omni-radtan``)."""

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
    point_direction,
)
from ._distortion import (
    MAX_DISTORTED_RADIUS,
    as_distortion,
    edge_slack,
    radial_guess,
    radtan_distort,
    radtan_r_max,
    undistort,
    unfolded,
)


def _full(d: Array) -> Array:
    """``(k1, k2, p1, p2)`` as OpenCV's 12-coefficient vector (k3..k6 and s1..s4 zero)."""
    zeros = jnp.zeros(d.shape[:-1] + (8,), d.dtype)
    return jnp.concatenate([d, zeros], axis=-1)


def mei_w(xi: Array) -> Array:
    """The unified domain ``Z > -w |p|``: ``w = ξ`` for ξ <= 1, else ``1/ξ``."""
    return jnp.where(xi <= 1, xi, 1.0 / jnp.where(xi > 1, xi, 1.0))


def _cos_theta_of_r(r: Array, xi: Array) -> tuple[Array, Array]:
    """``(cos theta, defined)`` of the ray whose unified normalised radius is ``r``:
    ``λ - ξ`` with ``λ = (ξ + sqrt(1 + (1-ξ²) r²)) / (1 + r²)``; undefined (beyond the fold of
    ξ > 1) where the root is imaginary."""
    r2 = r * r
    disc = 1 + (1 - xi * xi) * r2
    lam = (xi + safe_sqrt(disc)) / (1 + r2)
    return lam - xi, disc >= 0


class MeiCamera(AbstractCamera):
    """Mei's model (C. Mei and P. Rives, ICRA 2007), exactly ``cv2.omnidir.projectPoints`` (with skew
    ``s = 0``) and kalibr's ``omni-radtan``: the unified projection with ξ on the unit sphere, then
    OpenCV's radial-tangential distortion ``(k1, k2, p1, p2)`` of the normalised plane.

    Projection of a camera-frame point ``(X, Y, Z)``, ``d = |(X, Y, Z)|``::

        x = X / (Z + ξ d),  y = Y / (Z + ξ d),  r² = x² + y²
        xd = x (1 + k1 r² + k2 r⁴) + 2 p1 x y + p2 (r² + 2 x²)
        yd = y (1 + k1 r² + k2 r⁴) + p1 (r² + 2 y²) + 2 p2 x y
        u = fx xd + cx,  v = fy yd + cy

    (``fx, fy`` are Mei's generalised focal lengths γ; without distortion this is
    `UnifiedCamera` with ``α = ξ/(1+ξ)``, ``f = γ/(1+ξ)``.) Domain: the unified model's,
    ``Z > -w d`` with ``w = ξ`` for ξ <= 1, else ``1/ξ`` (beyond it the projection folds; ξ <= -1
    sees nothing); ``r <= r_max``, where ``r (1 + k1 r² + k2 r⁴)`` still increases (it ends
    ``RADTAN_MARGIN_RAD`` before its first stationary point, in ``atan(r)``, and at ``r`` ≈ 1000 at
    most); the distortion unfolded from the principal point to the point (a positive Jacobian
    determinant along that segment, `_distortion.unfolded`: strong tangential terms fold the image
    before the radial part does); and a distorted point at most `MAX_DISTORTED_RADIUS` focal
    lengths out. `theta_max` is the largest incidence angle of the radial domain. Unprojection: a 2 x 2 optimistix Newton solve of the
    distortion per pixel (implicit, exact gradients), then the closed-form unified inverse
    ``ray = (λ x, λ y, λ - ξ)``, ``λ = (ξ + sqrt(1 + (1-ξ²) r²)) / (1 + r²)``; a pixel is valid when
    the solve converges to a point of the domain. Pixel-centre convention (as ``cv2.omnidir``).

    Fields: `fx`, `fy`, `cx`, `cy` (pixels), `xi`, `distortion` ``(4,)`` = ``(k1, k2, p1, p2)``
    (``cv2.omnidir``'s ``D``), `width`, `height` (static).
    """

    fx: Float[Array, ""]
    fy: Float[Array, ""]
    cx: Float[Array, ""]
    cy: Float[Array, ""]
    xi: Float[Array, ""]
    distortion: Float[Array, "4"]
    width: int = eqx.field(static=True)
    height: int = eqx.field(static=True)

    def __init__(self, fx, fy, cx, cy, xi, distortion: Float[ArrayLike, "4"] = (0.0, 0.0, 0.0, 0.0), *,
                 width: int, height: int, dtype=None):
        dtype = resolve_dtype(dtype, fx)
        self.fx = jnp.asarray(fx, dtype=dtype)
        self.fy = jnp.asarray(fy, dtype=dtype)
        self.cx = jnp.asarray(cx, dtype=dtype)
        self.cy = jnp.asarray(cy, dtype=dtype)
        self.xi = jnp.asarray(xi, dtype=dtype)
        self.distortion = as_distortion(distortion, 4, (4,), dtype, "MeiCamera")
        self.width, self.height = check_image_size(width, height, "MeiCamera")

    def domain_problem(self) -> str | None:
        """Why the parameters lie outside the model's domain (focal lengths positive), or None."""
        return focal_problem(self.fx, self.fy)

    @property
    def principal_point(self) -> Float[Array, "2"]:
        """``(cx, cy)`` in pixel-centre coordinates."""
        return jnp.stack([self.cx, self.cy], axis=-1)

    @property
    def intrinsic_matrix(self) -> Float[Array, "3 3"]:
        """``cv2.omnidir``'s K (skew 0), used with ``xi`` and ``D = distortion``."""
        z = jnp.zeros_like(self.fx)
        return jnp.stack([jnp.stack([self.fx, z, self.cx]), jnp.stack([z, self.fy, self.cy]),
                          jnp.stack([z, z, jnp.ones_like(self.fx)])])

    def _radii(self, dtype) -> tuple[Array, Array, Array]:
        """``(radial r_max, unified fold radius, xi)``, the fold infinite for ξ <= 1."""
        r = radtan_r_max(_full(self.distortion.astype(dtype)))
        xi = jax.lax.stop_gradient(self.xi.astype(dtype))
        fold = jnp.where(xi > 1, 1.0 / safe_sqrt(jnp.where(xi > 1, xi * xi - 1, 1.0)), jnp.inf)
        return r, fold, xi

    def r_max(self, dtype=None) -> Float[Array, ""]:
        """Largest normalised radius ``|(x, y)|`` (before distortion) of the domain; for ξ > 1
        the unified fold ``1/sqrt(ξ² - 1)`` bounds it too (exclusive there)."""
        dtype = resolve_dtype(dtype, self.distortion)
        r, fold, _ = self._radii(dtype)
        return jnp.minimum(r, fold)

    def theta_max(self, dtype=None) -> Float[Array, ""]:
        """Largest valid incidence angle (radians): that of `r_max`, or the supremum
        ``arccos(-w)`` of the unified domain when the fold (ξ > 1) comes first."""
        dtype = resolve_dtype(dtype, self.distortion)
        r, fold, xi = self._radii(dtype)
        cos_t, _ = _cos_theta_of_r(jnp.minimum(r, fold), xi)
        cos_t = jnp.where(r >= fold, -mei_w(xi), jnp.maximum(cos_t, -mei_w(xi)))
        return jnp.arccos(jnp.clip(cos_t, -1.0, 1.0))

    def _domain(self, c, x, y, dtype) -> Bool[Array, "*batch"]:
        r_max = self.r_max(dtype)
        return (x * x + y * y <= r_max * r_max * edge_slack(dtype)) & (unfolded(radtan_distort, c, x, y))

    @eqx.filter_jit
    def project(
        self, points: Float[ArrayLike, "*batch 3"]
    ) -> tuple[Float[Array, "*batch 2"], Bool[Array, "*batch"]]:
        """Pixels ``(..., 2)`` of camera-frame points ``(..., 3)`` and their validity."""
        p, dtype = as_coordinates(points, 3, "MeiCamera.project: points")
        c = _full(self.distortion.astype(dtype))
        xi = self.xi.astype(dtype)
        x, y, z, finite = point_direction(p)  # exactly rescaled: huge and tiny points keep their direction
        d = safe_hypot(x, y, z)
        front = finite & (d > 0) & (z > -jax.lax.stop_gradient(mei_w(xi)) * d)
        denom = z + xi * d
        front = front & clear_of_rim(denom, x, y, z)
        inv = 1.0 / jnp.where(front, denom, 1.0)
        x, y = x * inv, y * inv
        bound = jax.lax.stop_gradient(self.r_max(dtype))
        inside = front & (x * x + y * y <= bound * bound * edge_slack(dtype))
        x, y = jnp.where(inside, x, 0.0), jnp.where(inside, y, 0.0)  # no overflow beyond the domain
        xd, yd = radtan_distort(c, x, y)
        u = self.fx.astype(dtype) * xd + self.cx.astype(dtype)
        v = self.fy.astype(dtype) * yd + self.cy.astype(dtype)
        near = (jnp.abs(xd) <= MAX_DISTORTED_RADIUS) & (jnp.abs(yd) <= MAX_DISTORTED_RADIUS)
        return finite_or_invalid(jnp.stack([u, v], axis=-1), inside & near & self._domain(c, x, y, dtype))

    @eqx.filter_jit
    def unproject(
        self, uv: Float[ArrayLike, "*batch 2"]
    ) -> tuple[Float[Array, "*batch 3"], Bool[Array, "*batch"]]:
        """Unit rays ``(..., 3)`` of pixels ``(..., 2)`` and their validity."""
        uv, dtype = as_coordinates(uv, 2, "MeiCamera.unproject: uv")
        uv, finite = finite_pixels(uv)
        c = _full(self.distortion.astype(dtype))
        xi = self.xi.astype(dtype)
        xd = (uv[..., 0] - self.cx.astype(dtype)) / self.fx.astype(dtype)
        yd = (uv[..., 1] - self.cy.astype(dtype)) / self.fy.astype(dtype)
        measurable = (jnp.abs(xd) <= MAX_DISTORTED_RADIUS) & (jnp.abs(yd) <= MAX_DISTORTED_RADIUS)
        xd, yd = jnp.where(measurable, xd, 0.0), jnp.where(measurable, yd, 0.0)
        r_max = jax.lax.stop_gradient(self.r_max(dtype))
        x, y, converged = undistort(radtan_distort, c, xd, yd, radial_guess(c, xd, yd, r_max))
        r2 = x * x + y * y
        disc = 1 + (1 - xi * xi) * r2
        lam = (xi + safe_sqrt(disc)) / (1 + r2)
        ray = jnp.stack([lam * x, lam * y, lam - xi], axis=-1)
        norm = safe_norm(ray, keepdims=True)
        ray = ray / jnp.where(norm > 0, norm, 1.0)
        in_front = ray[..., 2] > -jax.lax.stop_gradient(mei_w(xi))
        valid = finite & measurable & converged & (disc >= 0) & in_front & self._domain(c, x, y, dtype)
        return finite_or_invalid(ray, valid)
