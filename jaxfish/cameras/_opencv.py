"""OpenCV's pinhole camera with radial-tangential, rational and thin-prism distortion (``cv2.projectPoints``)."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Bool, Float

from .._numerics import resolve_dtype, safe_norm
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

OPENCV_DISTORTION_LENGTHS = (4, 5, 8, 12)
"""Accepted lengths of an OpenCV distortion vector (``cv2.calibrateCamera``'s ``distCoeffs``
without and with k3, the rational model and the thin-prism model); missing coefficients are 0."""


class OpenCVPinhole(AbstractCamera):
    """A pinhole camera with OpenCV's full distortion, exactly ``cv2.projectPoints`` with
    ``CALIB_RATIONAL_MODEL | CALIB_THIN_PRISM_MODEL`` (COLMAP ``OPENCV`` / ``FULL_OPENCV``, kalibr
    ``pinhole-radtan``: the coefficients they do not have are 0).

    Projection of a camera-frame point ``(X, Y, Z)``, ``Z > 0`` (OpenCV frame)::

        x = X / Z,  y = Y / Z,  r² = x² + y²
        R = (1 + k1 r² + k2 r⁴ + k3 r⁶) / (1 + k4 r² + k5 r⁴ + k6 r⁶)
        xd = x R + 2 p1 x y + p2 (r² + 2 x²) + s1 r² + s2 r⁴
        yd = y R + p1 (r² + 2 y²) + 2 p2 x y + s3 r² + s4 r⁴
        u = fx xd + cx,  v = fy yd + cy

    Domain: in front of the camera, ``r <= r_max`` (`r_max`): ``r R(r²)`` increases and the rational
    denominator stays positive from 0 to ``r_max``, which ends ``RADTAN_MARGIN_RAD`` (1e-3 rad, in
    ``atan(r)``) before the first stationary point, and at ``theta = pi/2 - 1e-3`` at most; the
    distortion unfolded from the principal point to the point (a positive Jacobian determinant along
    that segment, `_distortion.unfolded`: tangential and prism terms can fold the image before the
    radial part does); and a distorted point at most `MAX_DISTORTED_RADIUS` focal lengths out.
    Points elsewhere are invalid. Unprojection
    inverts the distortion by a 2 x 2 optimistix Newton solve per pixel (implicit, exact
    gradients) from the radial inverse; a pixel is valid when the solve converges to a point of
    the domain. Pixel-centre convention (the same as OpenCV's ``K``).

    Fields: `fx`, `fy`, `cx`, `cy` (pixels); `distortion` ``(12,)`` in OpenCV's order ``(k1, k2, p1,
    p2, k3, k4, k5, k6, s1, s2, s3, s4)`` (the constructor accepts 4, 5, 8 or 12, padding with 0);
    `width`, `height` (static).
    """

    fx: Float[Array, ""]
    fy: Float[Array, ""]
    cx: Float[Array, ""]
    cy: Float[Array, ""]
    distortion: Float[Array, "12"]
    width: int = eqx.field(static=True)
    height: int = eqx.field(static=True)

    def __init__(self, fx, fy, cx, cy, distortion: Float[ArrayLike, " L"] = (0.0, 0.0, 0.0, 0.0), *, width: int,
                 height: int, dtype=None):
        dtype = resolve_dtype(dtype, fx)
        self.fx = jnp.asarray(fx, dtype=dtype)
        self.fy = jnp.asarray(fy, dtype=dtype)
        self.cx = jnp.asarray(cx, dtype=dtype)
        self.cy = jnp.asarray(cy, dtype=dtype)
        self.distortion = as_distortion(distortion, 12, OPENCV_DISTORTION_LENGTHS, dtype, "OpenCVPinhole")
        self.width, self.height = check_image_size(width, height, "OpenCVPinhole")

    def domain_problem(self) -> str | None:
        """Why the parameters lie outside the model's domain (focal lengths positive), or None."""
        return focal_problem(self.fx, self.fy)

    @property
    def principal_point(self) -> Float[Array, "2"]:
        """``(cx, cy)`` in pixel-centre coordinates."""
        return jnp.stack([self.cx, self.cy], axis=-1)

    @property
    def intrinsic_matrix(self) -> Float[Array, "3 3"]:
        """OpenCV's K (no skew), for ``cv2.projectPoints`` with ``distCoeffs = distortion``."""
        z = jnp.zeros_like(self.fx)
        return jnp.stack([jnp.stack([self.fx, z, self.cx]), jnp.stack([z, self.fy, self.cy]),
                          jnp.stack([z, z, jnp.ones_like(self.fx)])])

    def r_max(self, dtype=None) -> Float[Array, ""]:
        """Largest undistorted normalised radius ``|(X/Z, Y/Z)|`` of the domain (class docstring)."""
        dtype = resolve_dtype(dtype, self.distortion)
        return radtan_r_max(self.distortion.astype(dtype))

    def theta_max(self, dtype=None) -> Float[Array, ""]:
        """Largest valid incidence angle (radians): ``atan(r_max)``, below pi/2."""
        return jnp.arctan(self.r_max(dtype))

    def _domain(self, c, x, y, dtype) -> Bool[Array, "*batch"]:
        r_max = self.r_max(dtype)
        r2 = x * x + y * y
        return (r2 <= r_max * r_max * edge_slack(dtype)) & (unfolded(radtan_distort, c, x, y))

    @eqx.filter_jit
    def project(
        self, points: Float[ArrayLike, "*batch 3"]
    ) -> tuple[Float[Array, "*batch 2"], Bool[Array, "*batch"]]:
        """Pixels ``(..., 2)`` of camera-frame points ``(..., 3)`` and their validity."""
        p, dtype = as_coordinates(points, 3, "OpenCVPinhole.project: points")
        c = self.distortion.astype(dtype)
        x, y, z, finite = point_direction(p)  # exactly rescaled: huge and tiny points keep their direction
        front = finite & clear_of_rim(z, x, y, z)
        inv_z = 1.0 / jnp.where(front, z, 1.0)
        x, y = x * inv_z, y * inv_z
        bound = jax.lax.stop_gradient(self.r_max(dtype))
        inside = front & (x * x + y * y <= bound * bound * edge_slack(dtype))
        x, y = jnp.where(inside, x, 0.0), jnp.where(inside, y, 0.0)  # no overflow beyond the domain
        xd, yd = radtan_distort(c, x, y)
        u = self.fx.astype(dtype) * xd + self.cx.astype(dtype)
        v = self.fy.astype(dtype) * yd + self.cy.astype(dtype)
        near = (jnp.abs(xd) <= MAX_DISTORTED_RADIUS) & (jnp.abs(yd) <= MAX_DISTORTED_RADIUS)
        valid = inside & near & self._domain(c, x, y, dtype)
        return finite_or_invalid(jnp.stack([u, v], axis=-1), valid)

    @eqx.filter_jit
    def unproject(
        self, uv: Float[ArrayLike, "*batch 2"]
    ) -> tuple[Float[Array, "*batch 3"], Bool[Array, "*batch"]]:
        """Unit rays ``(..., 3)`` of pixels ``(..., 2)`` and their validity."""
        uv, dtype = as_coordinates(uv, 2, "OpenCVPinhole.unproject: uv")
        uv, finite = finite_pixels(uv)
        c = self.distortion.astype(dtype)
        xd = (uv[..., 0] - self.cx.astype(dtype)) / self.fx.astype(dtype)
        yd = (uv[..., 1] - self.cy.astype(dtype)) / self.fy.astype(dtype)
        measurable = (jnp.abs(xd) <= MAX_DISTORTED_RADIUS) & (jnp.abs(yd) <= MAX_DISTORTED_RADIUS)
        xd, yd = jnp.where(measurable, xd, 0.0), jnp.where(measurable, yd, 0.0)
        r_max = jax.lax.stop_gradient(self.r_max(dtype))
        x, y, converged = undistort(radtan_distort, c, xd, yd, radial_guess(c, xd, yd, r_max))
        ray = jnp.stack([x, y, jnp.ones_like(x)], axis=-1)
        ray = ray / safe_norm(ray, keepdims=True)
        valid = finite & measurable & converged & self._domain(c, x, y, dtype)
        return finite_or_invalid(ray, valid)

