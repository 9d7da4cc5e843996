"""Orthographic (top-view / bird's-eye-view) camera."""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Bool, Float

from .._numerics import float_dtype, resolve_dtype
from ._base import AbstractCamera, as_coordinates, check_image_size, finite_or_invalid, interval_problem


class Orthographic(AbstractCamera):
    """A parallel-projection camera looking along its +z axis (OpenCV camera frame).

    ``u = X / metres_per_pixel + cx``, ``v = Y / metres_per_pixel + cy``: every pixel's ray starts
    on the camera's z = 0 plane at ``((u - cx) m, (v - cy) m, 0)`` and points along +z. With the
    camera above the ground looking down, image right is camera +x and image down is camera +y.
    ``(cx, cy)`` defaults to the image centre ``((W-1)/2, (H-1)/2)``, i.e. the camera axis passes
    through the middle of the image. Points with ``Z <= 0`` (above/behind the image plane) are
    invalid. Not central: use `ray_origins` with `unproject`.
    """

    metres_per_pixel: Float[Array, ""]
    cx: Float[Array, ""]
    cy: Float[Array, ""]
    width: int = eqx.field(static=True)
    height: int = eqx.field(static=True)

    def __init__(
        self,
        metres_per_pixel,
        *,
        width: int,
        height: int,
        cx=None,
        cy=None,
        dtype=None,
    ):
        dtype = resolve_dtype(dtype, metres_per_pixel)
        width, height = check_image_size(width, height, "Orthographic")
        self.metres_per_pixel = jnp.asarray(metres_per_pixel, dtype=dtype)
        self.cx = jnp.asarray((width - 1) / 2.0 if cx is None else cx, dtype=dtype)
        self.cy = jnp.asarray((height - 1) / 2.0 if cy is None else cy, dtype=dtype)
        self.width = width
        self.height = height

    def domain_problem(self) -> str | None:
        """Why the parameters lie outside the model's domain (``metres_per_pixel > 0``), or None."""
        return interval_problem("metres_per_pixel", self.metres_per_pixel, 0.0, open_low=True)

    @property
    def is_central(self) -> bool:
        """False: rays are parallel, with per-pixel origins (`ray_origins`)."""
        return False

    def project(
        self, points: Float[ArrayLike, "*batch 3"]
    ) -> tuple[Float[Array, "*batch 2"], Bool[Array, "*batch"]]:
        """Pixels of camera-frame points; valid where the point is finite, ``Z > 0`` and the pixel finite."""
        p, dtype = as_coordinates(points, 3, "Orthographic.project: points")
        finite = jnp.all(jnp.isfinite(p), axis=-1)
        p = jnp.where(finite[..., None], p, jnp.zeros_like(p))  # no NaN into the gradients either
        m = self.metres_per_pixel.astype(dtype)
        u = p[..., 0] / m + self.cx.astype(dtype)
        v = p[..., 1] / m + self.cy.astype(dtype)
        return finite_or_invalid(jnp.stack([u, v], axis=-1), finite & (p[..., 2] > 0))

    def unproject(
        self, uv: Float[ArrayLike, "*batch 2"]
    ) -> tuple[Float[Array, "*batch 3"], Bool[Array, "*batch"]]:
        """Ray directions: +z for every pixel (valid for every finite pixel); origins from `ray_origins`."""
        uv, dtype = as_coordinates(uv, 2, "Orthographic.unproject: uv")
        shape = uv.shape[:-1]
        ray = jnp.broadcast_to(jnp.asarray([0.0, 0.0, 1.0], dtype), shape + (3,))
        return ray, jnp.all(jnp.isfinite(uv), axis=-1)

    def ray_origins(self, uv: Float[ArrayLike, "*batch 2"]) -> Float[Array, "*batch 3"]:
        """Camera-frame ray origins ``((u - cx) m, (v - cy) m, 0)`` in metres."""
        uv = jnp.asarray(uv)
        dtype = float_dtype(uv)
        uv = uv.astype(dtype)
        m = self.metres_per_pixel.astype(dtype)
        x = (uv[..., 0] - self.cx.astype(dtype)) * m
        y = (uv[..., 1] - self.cy.astype(dtype)) * m
        return jnp.stack([x, y, jnp.zeros_like(x)], axis=-1)
