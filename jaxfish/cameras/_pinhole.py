"""The pinhole (perspective) camera, with CARLA's field-of-view convention."""

from __future__ import annotations

import math

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Bool, Float

from .._numerics import resolve_dtype
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


class Pinhole(AbstractCamera):
    """An ideal pinhole camera: ``u = fx X/Z + cx``, ``v = fy Y/Z + cy`` (OpenCV camera frame).

    Pixel-centre convention as every jaxfish camera: ``(cx, cy)`` is the pixel coordinate of the
    optical axis, with integer coordinates at pixel centres. Use `Pinhole.from_fov` for a CARLA
    ``sensor.camera.*``: CARLA's optical axis is the image centre ``((W-1)/2, (H-1)/2)`` in these
    coordinates (CARLA tutorials write ``W/2`` with a pixel-corner origin: the same point).
    Points with ``Z <= 0`` are invalid.
    """

    fx: Float[Array, ""]
    fy: Float[Array, ""]
    cx: Float[Array, ""]
    cy: Float[Array, ""]
    width: int = eqx.field(static=True)
    height: int = eqx.field(static=True)

    def __init__(self, fx, fy, cx, cy, *, width: int, height: int, dtype=None):
        dtype = resolve_dtype(dtype, fx)
        self.fx = jnp.asarray(fx, dtype=dtype)
        self.fy = jnp.asarray(fy, dtype=dtype)
        self.cx = jnp.asarray(cx, dtype=dtype)
        self.cy = jnp.asarray(cy, dtype=dtype)
        width, height = check_image_size(width, height, "Pinhole")
        self.width = width
        self.height = height

    def domain_problem(self) -> str | None:
        """Why the parameters lie outside the model's domain (focal lengths positive), or None."""
        return focal_problem(self.fx, self.fy)

    @classmethod
    def from_fov(cls, width: int, height: int, fov_deg: float = 90.0, *, dtype=None) -> Pinhole:
        """CARLA's camera: ``f = W / (2 tan(fov/2))`` (fov horizontal, degrees), square pixels,
        optical axis at the image centre ``((W-1)/2, (H-1)/2)``."""
        if not 0.0 < float(fov_deg) < 180.0:
            raise ValueError(f"Pinhole.from_fov: fov_deg must be in (0, 180), got {fov_deg}")
        f = width / (2.0 * math.tan(math.radians(fov_deg) / 2.0))
        return cls(f, f, (width - 1) / 2.0, (height - 1) / 2.0, width=width, height=height, dtype=dtype)

    @property
    def intrinsic_matrix(self) -> Float[Array, "3 3"]:
        """The 3x3 matrix K (pixel-centre convention)."""
        z = jnp.zeros_like(self.fx)
        o = jnp.ones_like(self.fx)
        return jnp.stack(
            [jnp.stack([self.fx, z, self.cx]), jnp.stack([z, self.fy, self.cy]), jnp.stack([z, z, o])]
        )

    def project(
        self, points: Float[ArrayLike, "*batch 3"]
    ) -> tuple[Float[Array, "*batch 2"], Bool[Array, "*batch"]]:
        """Pixels of camera-frame points; valid where ``Z > 0``."""
        p, dtype = as_coordinates(points, 3, "Pinhole.project: points")
        x, y, z, finite = point_direction(p)  # exactly rescaled: huge and tiny points keep their direction
        valid = finite & clear_of_rim(z, x, y, z)  # z > 0, not within eps of the image plane
        inv_z = 1.0 / jnp.where(valid, z, 1.0)
        u = self.fx.astype(dtype) * x * inv_z + self.cx.astype(dtype)
        v = self.fy.astype(dtype) * y * inv_z + self.cy.astype(dtype)
        return finite_or_invalid(jnp.stack([u, v], axis=-1), valid)  # u overflows for z -> 0+

    def unproject(
        self, uv: Float[ArrayLike, "*batch 2"]
    ) -> tuple[Float[Array, "*batch 3"], Bool[Array, "*batch"]]:
        """Unit rays of pixels (valid unless the coordinates are too large to square)."""
        uv, dtype = as_coordinates(uv, 2, "Pinhole.unproject: uv")
        uv, finite = finite_pixels(uv)
        x = (uv[..., 0] - self.cx.astype(dtype)) / self.fx.astype(dtype)
        y = (uv[..., 1] - self.cy.astype(dtype)) / self.fy.astype(dtype)
        ok = jnp.isfinite(x * x + y * y)  # squares overflow for huge pixels: invalid, not NaN
        x, y = jnp.where(ok, x, 0.0), jnp.where(ok, y, 0.0)
        d = jnp.stack([x, y, jnp.ones_like(x)], axis=-1)
        return d / jnp.linalg.norm(d, axis=-1, keepdims=True), ok & finite
