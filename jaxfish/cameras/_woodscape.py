"""The WoodScape 4th-order polynomial fisheye model (``"radial_poly"``)."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float

from .._numerics import eps_for, float_dtype, incidence_angle, radial_ratio, resolve_dtype, safe_hypot, stack_last
from ._base import AbstractCamera, as_coordinates, check_image_size, finite_or_invalid, finite_pixels, point_direction
from ._domain import first_increasing_limit, invert_increasing

THETA_MAX_MARGIN_RAD = 1e-3
"""When rho(theta) has a stationary point theta_s <= pi, the valid domain is [0, theta_s - margin]:
at theta_s itself the inverse has infinite slope and is not a usable ray."""
_MAX_NEWTON_STEPS = 32
"""Newton iterations at most when inverting rho (4-6 are used on real calibrations)."""


def _newton_tolerances(dtype) -> tuple[float, float]:
    """(rtol, atol) in radians for the theta solve (CONVENTIONS §8: solve in radians)."""
    if jnp.dtype(dtype) == jnp.float64:
        return 1e-11, 1e-11
    return 4e-6, 4e-6


def rho_of_theta(k: Float[Array, 4], theta: Float[Array, "*batch"]) -> Float[Array, "*batch"]:
    """rho(theta) = k1 θ + k2 θ² + k3 θ³ + k4 θ⁴ (pixels), Horner form."""
    return theta * (k[0] + theta * (k[1] + theta * (k[2] + theta * k[3])))


def _rho_over_theta(k: Float[Array, 4], theta: Float[Array, "*batch"]) -> Float[Array, "*batch"]:
    return k[0] + theta * (k[1] + theta * (k[2] + theta * k[3]))


def drho_dtheta(k: Float[Array, 4], theta: Float[Array, "*batch"]) -> Float[Array, "*batch"]:
    """d rho / d theta (pixels per radian)."""
    return k[0] + theta * (2 * k[1] + theta * (3 * k[2] + theta * (4 * k[3])))


def theta_max_of(k: Float[Array, "4"]) -> Float[Array, ""]:
    """Upper end of the valid incidence-angle domain of a radial_poly lens (radians).

    ``pi`` when rho is strictly increasing on [0, pi]; otherwise the first stationary point of rho
    minus `THETA_MAX_MARGIN_RAD`; 0 when rho does not increase at 0 (k1 <= 0: no valid ray).
    Not differentiated (the domain boundary is a mask, not a value).
    """
    return first_increasing_limit(drho_dtheta, k, k.dtype, margin=THETA_MAX_MARGIN_RAD)


def _theta_residual(theta, args):
    k, rho = args
    # Residual in radians (divide by k1): a pixel residual can never meet a float32 tolerance.
    return (rho_of_theta(k, theta) - rho) / k[0]


_GUESS_STEPS = 3
"""Plain Newton steps fused into one elementwise pass that give optimistix its starting point."""


def _initial_guess(k: Float[Array, "4"], rho: Float[Array, "*batch"], theta_max: Float[Array, ""]) -> Float[Array, "*batch"]:
    """A starting point for the optimistix solve: `_GUESS_STEPS` unrolled, clipped Newton steps
    from ``rho / k1``. XLA fuses them into a single elementwise loop (no while loop, no gather),
    so optimistix then needs one or two steps to confirm convergence. The guess only saves
    iterations: the returned theta is always a converged, residual-checked optimistix root.
    """
    k = jax.lax.stop_gradient(k)
    tiny = jnp.asarray(eps_for(rho.dtype), rho.dtype) * k[0]
    theta = jnp.clip(rho / k[0], 0.0, theta_max)
    for _ in range(_GUESS_STEPS):
        step = (rho_of_theta(k, theta) - rho) / jnp.maximum(drho_dtheta(k, theta), tiny)
        theta = jnp.clip(theta - step, 0.0, theta_max)
    return theta


def solve_theta(
    k: Float[Array, "4"], rho: Float[Array, "*batch"], theta_max: Float[Array, ""]
) -> tuple[Float[Array, "*batch"], Bool[Array, "*batch"]]:
    """Invert rho(theta) = rho on [0, theta_max] with optimistix Newton (element-wise).

    The whole batch is one root-finding problem with a *diagonal* Jacobian, so every Newton step
    is one vectorised polynomial evaluation; it starts from `_initial_guess`. Gradients with
    respect to ``rho`` and ``k`` are implicit (exact). Should Newton fail anywhere (it can cycle
    near a stationary point of rho, on lenses whose domain ends before pi), the solve is repeated
    from a bisection (`invert_increasing`). Returns ``(theta, converged)``; `converged` is a
    per-element residual check, never a silent default.
    """
    rtol, atol = _newton_tolerances(rho.dtype)
    return invert_increasing(rho_of_theta, _theta_residual, k, rho, theta_max,
                             _initial_guess(k, jax.lax.stop_gradient(rho), theta_max), rtol=rtol, atol=atol,
                             max_steps=_MAX_NEWTON_STEPS)


class WoodScapeFisheye(AbstractCamera):
    """The WoodScape fisheye model, exactly as ``scripts/calibration/projection.py``.

    Projection of a camera-frame point ``(X, Y, Z)`` (OpenCV frame)::

        chi = sqrt(X² + Y²),  theta = atan2(chi, Z)          # theta in [0, pi]
        rho = k1 θ + k2 θ² + k3 θ³ + k4 θ⁴                    # pixels
        u = rho X / chi + cx,  v = rho Y / chi * aspect_ratio + cy
        cx = W/2 + cx_offset - 0.5,  cy = H/2 + cy_offset - 0.5   # pixel-centre convention

    Unprojection inverts rho by optimistix Newton on the valid domain ``[0, theta_max]`` (see
    `theta_max`); pixels with ``rho > rho(theta_max)`` are reported invalid, never mapped to
    theta = 0. Values and gradients are finite everywhere, including the principal point.

    Fields: `k` ``(4,)`` = (k1, k2, k3, k4) in pixels; `cx_offset`, `cy_offset` in pixels;
    `aspect_ratio` (scales v only); `width`, `height` in pixels (static).
    """

    k: Float[Array, 4]
    cx_offset: Float[Array, ""]
    cy_offset: Float[Array, ""]
    aspect_ratio: Float[Array, ""]
    width: int = eqx.field(static=True)
    height: int = eqx.field(static=True)

    def __init__(
        self,
        k: Float[ArrayLike, 4],
        *,
        width: int,
        height: int,
        cx_offset: float | ArrayLike = 0.0,
        cy_offset: float | ArrayLike = 0.0,
        aspect_ratio: float | ArrayLike = 1.0,
        dtype=None,
    ):
        dtype = resolve_dtype(dtype, k)
        k = jnp.asarray(k, dtype=dtype)
        if k.shape[-1:] != (4,):
            raise ValueError(f"WoodScapeFisheye: k must have shape (..., 4), got {k.shape}")
        self.k = k
        self.cx_offset = jnp.asarray(cx_offset, dtype=dtype)
        self.cy_offset = jnp.asarray(cy_offset, dtype=dtype)
        self.aspect_ratio = jnp.asarray(aspect_ratio, dtype=dtype)
        width, height = check_image_size(width, height, "WoodScapeFisheye")
        self.width = width
        self.height = height

    # ----------------------------------------------------------------------------- parameters
    @property
    def principal_point(self) -> Float[Array, 2]:
        """``(cx, cy)`` in pixel-centre coordinates: ``(W/2 + cx_offset - 0.5, H/2 + cy_offset - 0.5)``."""
        return jnp.stack(self._principal_point(self.k.dtype), axis=-1)

    def _principal_point(self, dtype) -> tuple[Array, Array]:
        cx = self.cx_offset.astype(dtype) + jnp.asarray(self.width / 2 - 0.5, dtype)
        cy = self.cy_offset.astype(dtype) + jnp.asarray(self.height / 2 - 0.5, dtype)
        return cx, cy

    def rho(self, theta: Float[ArrayLike, "*batch"]) -> Float[Array, "*batch"]:
        """Image radius (pixels) of the incidence angle ``theta`` (radians)."""
        theta = jnp.asarray(theta)
        dtype = float_dtype(theta)
        return rho_of_theta(self.k.astype(dtype), theta.astype(dtype))

    def theta_max(self, dtype=None) -> Float[Array, ""]:
        """Largest valid incidence angle (radians): pi, or the first stationary point of rho
        minus `THETA_MAX_MARGIN_RAD` when rho stops increasing before pi."""
        dtype = resolve_dtype(dtype, self.k)
        return theta_max_of(self.k.astype(dtype))

    def rho_max(self, dtype=None) -> Float[Array, ""]:
        """Image radius (pixels) of `theta_max`: pixels farther from the principal point have no ray."""
        dtype = resolve_dtype(dtype, self.k)
        k = jax.lax.stop_gradient(self.k.astype(dtype))
        return rho_of_theta(k, theta_max_of(k))

    # ----------------------------------------------------------------------------- model
    # Both methods are `eqx.filter_jit`-compiled: eager calls hit a compilation cache instead of
    # re-tracing the root finder op by op; inside a user's jit they simply inline.
    @eqx.filter_jit
    def project(
        self, points: Float[ArrayLike, "*batch 3"]
    ) -> tuple[Float[Array, "*batch 2"], Bool[Array, "*batch"]]:
        """Pixels ``(..., 2)`` of camera-frame points ``(..., 3)``, and their validity.

        Invalid: the camera centre, points with theta > `theta_max`, and the ray exactly behind
        the optical axis (theta = pi, where the azimuth is undefined).
        """
        p, dtype = as_coordinates(points, 3, "WoodScapeFisheye.project: points")
        k = self.k.astype(dtype)
        cx, cy = self._principal_point(dtype)
        a = self.aspect_ratio.astype(dtype)
        x, y, z, finite = point_direction(p)  # exactly rescaled: huge and tiny points keep their direction
        chi = safe_hypot(x, y)
        r = safe_hypot(x, y, z)
        nonzero = r > 0
        theta = incidence_angle(jnp.where(nonzero, chi, 0.0), jnp.where(nonzero, z, 1.0))
        # rho(θ)/chi = (rho(θ)/θ) · (θ/chi): smooth at chi = 0, exact near the back axis.
        theta_over_chi, defined = radial_ratio(theta, chi, r, z)
        ratio = _rho_over_theta(k, theta) * theta_over_chi
        u = x * ratio + cx
        v = y * ratio * a + cy
        valid = finite & defined & (theta <= self.theta_max(dtype)) & (k[..., 0] > 0)
        return finite_or_invalid(jnp.stack([u, v], axis=-1), valid)

    @eqx.filter_jit
    def unproject(
        self, uv: Float[ArrayLike, "*batch 2"]
    ) -> tuple[Float[Array, "*batch 3"], Bool[Array, "*batch"]]:
        """Unit rays ``(..., 3)`` (camera frame) of pixels ``(..., 2)``, and their validity.

        Invalid: pixels beyond `rho_max` (outside the lens domain) and, never in practice, a
        Newton solve that did not converge. Invalid rays are finite placeholders.
        """
        uv, dtype = as_coordinates(uv, 2, "WoodScapeFisheye.unproject: uv")
        uv, finite = finite_pixels(uv)
        k = self.k.astype(dtype)
        lens = k[..., 0] > 0  # k1 <= 0: no valid ray (solve a harmless lens instead of dividing by k1)
        k = jnp.where(lens, k, jnp.asarray([1.0, 0.0, 0.0, 0.0], dtype))
        cx, cy = self._principal_point(dtype)
        a = self.aspect_ratio.astype(dtype)
        x = uv[..., 0] - cx
        y = (uv[..., 1] - cy) / a
        r2 = x * x + y * y
        measurable = jnp.isfinite(r2)  # squares overflow beyond ~1e19 px (float32): invalid, not NaN
        r2 = jnp.where(measurable, r2, 0.0)
        rho = jnp.where(r2 > 0, jnp.sqrt(jnp.where(r2 > 0, r2, 1.0)), 0.0)
        # Materialise rho once: otherwise XLA re-fuses it (strided reads of uv) into every consumer.
        rho = jax.lax.optimization_barrier(rho)
        theta_max = self.theta_max(dtype)
        rho_max = rho_of_theta(jax.lax.stop_gradient(k), theta_max)
        inside = rho <= rho_max * (1 + 4 * eps_for(dtype))  # the pixel of theta_max itself, after rounding
        theta, converged = solve_theta(k, jnp.minimum(rho, rho_max), theta_max)
        # sin(θ)/rho, with its first-order Taylor expansion near the principal point.
        tau = jnp.asarray(np.sqrt(eps_for(dtype)) * 100, dtype)
        small = rho < tau
        safe_rho = jnp.where(small, jnp.ones_like(rho), rho)
        taylor = 1.0 / k[0] - k[1] * rho / k[0] ** 3
        s = jnp.where(small, taylor, jnp.sin(theta) / safe_rho)
        ray = stack_last([x * s, y * s, jnp.cos(theta)])
        return finite_or_invalid(ray, inside & converged & measurable & finite & lens)
