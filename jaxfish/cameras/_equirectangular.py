"""Equirectangular (longitude/latitude) and cylindrical panoramic cameras."""

from __future__ import annotations

import math

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Bool, Float

from .._numerics import resolve_dtype, safe_hypot
from ._base import (
    AbstractCamera,
    as_coordinates,
    check_image_size,
    clear_of_rim,
    finite_or_invalid,
    finite_pixels,
    interval_problem,
    point_direction,
)


def _longitude(x: Array, z: Array) -> tuple[Array, Array]:
    """Longitude atan2(X, Z) (radians, 0 on the optical axis, positive to the right) and the
    horizontal radius sqrt(X² + Z²), both with finite gradients on the vertical axis."""
    horiz = safe_hypot(x, z)
    ok = horiz > 0
    lon = jnp.arctan2(jnp.where(ok, x, 0.0), jnp.where(ok, z, 1.0))
    return lon, horiz


class Equirectangular(AbstractCamera):
    """Longitude/latitude image: ``u`` linear in longitude, ``v`` linear in latitude.

    Longitude ``atan2(X, Z)`` (0 on the optical axis, positive towards +x, image right); latitude
    ``atan2(Y, sqrt(X² + Z²))`` (positive towards +y, image down). The image spans
    ``[lon_min, lon_max] x [lat_min, lat_max]`` edge to edge (radians), so pixel ``u`` has its
    centre at ``lon_min + (u + 0.5) (lon_max - lon_min) / W``. Defaults: the full sphere.
    """

    lon_min: Float[Array, ""]
    lon_max: Float[Array, ""]
    lat_min: Float[Array, ""]
    lat_max: Float[Array, ""]
    width: int = eqx.field(static=True)
    height: int = eqx.field(static=True)

    def __init__(
        self,
        *,
        width: int,
        height: int,
        lon_range: tuple[float, float] = (-math.pi, math.pi),
        lat_range: tuple[float, float] = (-math.pi / 2, math.pi / 2),
        dtype=None,
    ):
        dtype = resolve_dtype(dtype, )
        width, height = check_image_size(width, height, "Equirectangular")
        if not (-math.pi <= lon_range[0] < lon_range[1] <= math.pi):
            raise ValueError(f"Equirectangular: lon_range must be increasing within [-pi, pi], got {lon_range}")
        if not (-math.pi / 2 <= lat_range[0] < lat_range[1] <= math.pi / 2):
            raise ValueError(f"Equirectangular: lat_range must be increasing within [-pi/2, pi/2], got {lat_range}")
        self.lon_min = jnp.asarray(lon_range[0], dtype)
        self.lon_max = jnp.asarray(lon_range[1], dtype)
        self.lat_min = jnp.asarray(lat_range[0], dtype)
        self.lat_max = jnp.asarray(lat_range[1], dtype)
        self.width = width
        self.height = height

    def project(
        self, points: Float[ArrayLike, "*batch 3"]
    ) -> tuple[Float[Array, "*batch 2"], Bool[Array, "*batch"]]:
        """Pixels of camera-frame points; valid inside the longitude/latitude ranges."""
        p, dtype = as_coordinates(points, 3, "Equirectangular.project: points")
        x, y, z, finite = point_direction(p)  # exactly rescaled: huge and tiny points keep their direction
        lon, horiz = _longitude(x, z)
        ok = finite & ((x != 0) | (y != 0) | (z != 0))
        lat = jnp.arctan2(jnp.where(ok, y, 0.0), jnp.where(ok, horiz, 1.0))
        lon0, lon1 = self.lon_min.astype(dtype), self.lon_max.astype(dtype)
        lat0, lat1 = self.lat_min.astype(dtype), self.lat_max.astype(dtype)
        u = (lon - lon0) / (lon1 - lon0) * self.width - 0.5
        v = (lat - lat0) / (lat1 - lat0) * self.height - 0.5
        valid = ok & (lon >= lon0) & (lon <= lon1) & (lat >= lat0) & (lat <= lat1)
        return jnp.stack([u, v], axis=-1), valid

    def unproject(
        self, uv: Float[ArrayLike, "*batch 2"]
    ) -> tuple[Float[Array, "*batch 3"], Bool[Array, "*batch"]]:
        """Unit rays of pixels; valid inside the image."""
        uv, dtype = as_coordinates(uv, 2, "Equirectangular.unproject: uv")
        uv, finite = finite_pixels(uv)
        lon0, lon1 = self.lon_min.astype(dtype), self.lon_max.astype(dtype)
        lat0, lat1 = self.lat_min.astype(dtype), self.lat_max.astype(dtype)
        lon = lon0 + (uv[..., 0] + 0.5) / self.width * (lon1 - lon0)
        lat = lat0 + (uv[..., 1] + 0.5) / self.height * (lat1 - lat0)
        c = jnp.cos(lat)
        ray = jnp.stack([c * jnp.sin(lon), jnp.sin(lat), c * jnp.cos(lon)], axis=-1)
        return ray, self.contains(uv) & finite


class Cylindrical(AbstractCamera):
    """Cylindrical panorama: ``u`` linear in longitude, ``v = f Y / sqrt(X² + Z²) + cy``.

    Longitude as `Equirectangular` over ``lon_range`` (edge to edge); vertically a pinhole of focal
    `f` pixels with ``cy`` (pixel-centre convention, default ``(H-1)/2``). Straight vertical lines stay
    straight, which makes it a common rectification target for side fisheye cameras.
    """

    lon_min: Float[Array, ""]
    lon_max: Float[Array, ""]
    f: Float[Array, ""]
    cy: Float[Array, ""]
    width: int = eqx.field(static=True)
    height: int = eqx.field(static=True)

    def __init__(
        self,
        *,
        width: int,
        height: int,
        lon_range: tuple[float, float] = (-math.pi / 2, math.pi / 2),
        f: float | None = None,
        cy: float | None = None,
        dtype=None,
    ):
        dtype = resolve_dtype(dtype, )
        width, height = check_image_size(width, height, "Cylindrical")
        if not (-math.pi <= lon_range[0] < lon_range[1] <= math.pi):
            raise ValueError(f"Cylindrical: lon_range must be increasing within [-pi, pi], got {lon_range}")
        if f is None:  # square pixels at the horizon
            f = width / (lon_range[1] - lon_range[0])
        self.lon_min = jnp.asarray(lon_range[0], dtype)
        self.lon_max = jnp.asarray(lon_range[1], dtype)
        self.f = jnp.asarray(f, dtype)
        self.cy = jnp.asarray((height - 1) / 2.0 if cy is None else cy, dtype)
        self.width = width
        self.height = height

    def domain_problem(self) -> str | None:
        """Why the parameters lie outside the model's domain (``f > 0``), or None."""
        return interval_problem("f", self.f, 0.0, open_low=True)

    def project(
        self, points: Float[ArrayLike, "*batch 3"]
    ) -> tuple[Float[Array, "*batch 2"], Bool[Array, "*batch"]]:
        """Pixels of camera-frame points; valid off the vertical axis and inside the longitude range."""
        p, dtype = as_coordinates(points, 3, "Cylindrical.project: points")
        x, y, z, finite = point_direction(p)  # exactly rescaled: huge and tiny points keep their direction
        # within eps of the vertical axis: v beyond f / eps, and d v / d point ~ 1 / horiz² could overflow
        ok = finite & clear_of_rim(safe_hypot(x, z), x, y, z)
        lon, horiz = _longitude(jnp.where(ok, x, 0.0), jnp.where(ok, z, 1.0))
        lon0, lon1 = self.lon_min.astype(dtype), self.lon_max.astype(dtype)
        u = (lon - lon0) / (lon1 - lon0) * self.width - 0.5
        v = self.f.astype(dtype) * y / jnp.where(ok, horiz, 1.0) + self.cy.astype(dtype)
        valid = ok & (lon >= lon0) & (lon <= lon1)
        return finite_or_invalid(jnp.stack([u, v], axis=-1), valid)  # v overflows near the vertical axis

    def unproject(
        self, uv: Float[ArrayLike, "*batch 2"]
    ) -> tuple[Float[Array, "*batch 3"], Bool[Array, "*batch"]]:
        """Unit rays of pixels; valid inside the longitude range."""
        uv, dtype = as_coordinates(uv, 2, "Cylindrical.unproject: uv")
        uv, finite = finite_pixels(uv)
        lon0, lon1 = self.lon_min.astype(dtype), self.lon_max.astype(dtype)
        lon = lon0 + (uv[..., 0] + 0.5) / self.width * (lon1 - lon0)
        y = (uv[..., 1] - self.cy.astype(dtype)) / self.f.astype(dtype)
        measurable = jnp.isfinite(y * y)  # squares overflow for huge pixels: invalid, not NaN
        y = jnp.where(measurable, y, 0.0)
        d = jnp.stack([jnp.sin(lon), y, jnp.cos(lon)], axis=-1)
        ray = d / jnp.linalg.norm(d, axis=-1, keepdims=True)
        valid = finite & measurable & (uv[..., 0] >= -0.5) & (uv[..., 0] <= self.width - 0.5)
        return ray, valid
