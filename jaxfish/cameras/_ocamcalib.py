"""Scaramuzza's omnidirectional model as the OCamCalib toolbox writes it (``calib_results.txt``)."""

from __future__ import annotations

import math
import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float

from .._numerics import eps_for, incidence_angle, radial_ratio, resolve_dtype, safe_hypot, stack_last
from ._base import (
    AbstractCamera,
    affine_problem,
    as_coordinates,
    check_image_size,
    finite_or_invalid,
    finite_pixels,
    point_direction,
)
from ._domain import bisection_guess, invert_increasing
from ._pixel_radius import affine_solve, first_stationary_radius, polyder, polyval

OCAM_POL_LENGTH = 8
"""Coefficients ``a0 .. a7`` of the direct polynomial (``ocam_model.ss``; OCamCalib's default degree
is 4): shorter polynomials are padded with zeros, longer ones are refused by the readers."""
OCAM_INVPOL_LENGTH = 24
"""Coefficients of the inverse polynomial (``ocam_model.invpol``), padded with zeros likewise."""
_MAX_NEWTON_STEPS = 32
_GUESS_STEPS = 3
_GUESS_ANGLE_RAD = 1e-3
"""An inverse-polynomial start farther than this from the solution is replaced by a bisection."""


def alpha_of_rho(pol: Float[Array, " n"], rho: Float[Array, "*batch"]) -> Float[Array, "*batch"]:
    """Angle (radians) between the optical axis and the ray of image radius ``rho`` (pixels, in
    the sensor plane after the affine correction): ``atan2(rho, -pol(rho))``."""
    return incidence_angle(rho, -polyval(pol, rho))


def _dalpha_numerator(pol: Float[Array, " n"], rho: Float[Array, "*batch"]) -> Float[Array, "*batch"]:
    """``rho pol'(rho) - pol(rho)``: the sign of ``d alpha / d rho`` (whose denominator
    ``rho² + pol²`` is positive)."""
    return rho * polyval(polyder(pol), rho) - polyval(pol, rho)


def _residual(rho, args):
    pol, alpha = args
    return alpha_of_rho(pol, rho) - alpha  # radians


def _solve_rho(pol, alpha, rho_max, rho0):
    """``rho`` with ``alpha_of_rho(pol, rho) = alpha`` on ``[0, rho_max]``: optimistix Newton (with its
    bisection fallback, `invert_increasing`) on stopped-gradient inputs, then the implicit-function
    derivative attached by one Newton step whose residual is differentiated and whose slope is
    not (``rho - (R(rho) - sg R(rho)) / sg R'(rho)``: first derivatives exact by the implicit
    function theorem). The linear solve of optimistix's own implicit adjoint is avoided here: it
    received non-finite tangents inside `refit`'s Levenberg-Marquardt linearisation (the primal
    and ``jax.jacfwd`` / ``jax.grad`` were finite)."""
    tol = 1e-11 if alpha.dtype == jnp.float64 else 4e-6
    pol_sg, alpha_sg = jax.lax.stop_gradient(pol), jax.lax.stop_gradient(alpha)
    rho, converged = invert_increasing(alpha_of_rho, _residual, pol_sg, alpha_sg, rho_max, rho0, rtol=tol, atol=tol,
                                       max_steps=_MAX_NEWTON_STEPS)
    p = polyval(pol_sg, rho)
    slope = _dalpha_numerator(pol_sg, rho) / jnp.maximum(rho * rho + p * p, eps_for(alpha.dtype))
    residual = alpha_of_rho(pol, rho) - alpha
    correction = (residual - jax.lax.stop_gradient(residual)) / jnp.maximum(slope, eps_for(alpha.dtype))
    return rho - correction, converged


class OCamCalib(AbstractCamera):
    """Scaramuzza's omnidirectional camera model, exactly as the OCamCalib toolbox's C functions
    ``cam2world`` / ``world2cam`` (``ocam_functions.cpp``) and its ``calib_results.txt``.

    **OCamCalib's conventions** (followed here field for field): image points are ``(row,
    column)``, so ``xc`` is the *row* (vertical) and ``yc`` the *column* (horizontal) coordinate
    of the centre, 0-based with integer coordinates at pixel centres (the C convention of
    ``calib_results.txt``: jaxfish's ``(u, v) = (column, row)``). Its camera frame is ``x`` down
    the rows, ``y`` along the columns and ``z`` *backwards* (the optical axis is ``-z``); a jaxfish
    (OpenCV) point ``(X, Y, Z)`` is OCamCalib's ``(Y, X, -Z)``.

    Unprojection (``cam2world``) of a pixel ``(u, v)``::

        [v - xc, u - yc] = [[c, d], [e, 1]] [x', y']            # affine sensor correction
        rho = sqrt(x'² + y'²)
        ray_ocam ∝ (x', y', a0 + a1 rho + a2 rho² + ... )        # pol; a0 < 0, a1 = 0 in OCamCalib
        ray = (y', x', -pol(rho)) / norm                        # jaxfish frame

    Projection (``world2cam``) is its exact inverse: the incidence angle ``alpha`` of a point
    fixes ``rho`` through ``alpha = atan2(rho, -pol(rho))``, solved by optimistix Newton (with
    implicit gradients) from the file's inverse polynomial ``invpol`` (``rho ≈ invpol(alpha -
    pi/2)``, only an approximation: used as the initial guess), then ``(x', y') = rho (Y, X) /
    sqrt(X² + Y²)`` and ``[v - xc, u - yc] = [[c, d], [e, 1]] [x', y']``.

    **Domain**: radii ``rho`` in ``[0, rho_max]`` where ``alpha(rho)`` increases: ``rho_max`` is
    the image diagonal ``sqrt(W² + H²)`` (the calibration says nothing farther out), or the first
    stationary point of ``alpha(rho)`` before it minus ``1e-3 sqrt(W² + H²) / pi`` pixels.
    `theta_max` is ``alpha(rho_max)``; points beyond it, the camera centre, the ray straight
    behind the axis, and pixels with ``rho > rho_max`` are invalid; a polynomial with ``a0 >= 0``
    has no valid ray. Values and gradients are finite everywhere.

    Fields: `xc` (row), `yc` (column), pixels; `c`, `d`, `e` (dimensionless); `pol`
    ``(OCAM_POL_LENGTH,)`` (``a_i`` in pixels^(1-i)); `invpol` ``(OCAM_INVPOL_LENGTH,)`` (pixels
    per radian^i); `width`, `height` (static).
    """

    xc: Float[Array, ""]
    yc: Float[Array, ""]
    c: Float[Array, ""]
    d: Float[Array, ""]
    e: Float[Array, ""]
    pol: Float[Array, " 8"]
    invpol: Float[Array, " 24"]
    width: int = eqx.field(static=True)
    height: int = eqx.field(static=True)

    def __init__(self, pol: Float[ArrayLike, " n"], invpol: Float[ArrayLike, " m"] = (), *, xc, yc, c=1.0, d=0.0,
                 e=0.0, width: int, height: int, dtype=None):
        dtype = resolve_dtype(dtype, pol, xc)
        self.pol = _padded(pol, OCAM_POL_LENGTH, "pol", dtype)
        self.invpol = _padded(invpol, OCAM_INVPOL_LENGTH, "invpol", dtype)
        self.xc = jnp.asarray(xc, dtype=dtype)
        self.yc = jnp.asarray(yc, dtype=dtype)
        self.c = jnp.asarray(c, dtype=dtype)
        self.d = jnp.asarray(d, dtype=dtype)
        self.e = jnp.asarray(e, dtype=dtype)
        self.width, self.height = check_image_size(width, height, "OCamCalib")

    def domain_problem(self) -> str | None:
        """Why the parameters lie outside the model's domain (an invertible affine matrix
        ``[[c, d], [e, 1]]``: ``c - d e != 0``), or None."""
        return affine_problem(self.c, self.d, self.e)

    @property
    def principal_point(self) -> Float[Array, " 2"]:
        """``(u, v) = (yc, xc)`` in jaxfish's pixel-centre convention."""
        return jnp.stack([self.yc, self.xc], axis=-1)

    def _rho_bound(self, dtype) -> Array:
        return jnp.asarray(math.hypot(self.width, self.height), dtype)

    def rho_max(self, dtype=None) -> Float[Array, ""]:
        """Largest valid radius (pixels, sensor plane) of the domain; see the class docstring."""
        dtype = resolve_dtype(dtype, self.pol)
        pol = jax.lax.stop_gradient(self.pol.astype(dtype))
        return first_stationary_radius(_dalpha_numerator, pol, self._rho_bound(dtype), dtype)

    def theta_max(self, dtype=None) -> Float[Array, ""]:
        """Largest valid incidence angle (radians): ``alpha(rho_max)``."""
        dtype = resolve_dtype(dtype, self.pol)
        pol = jax.lax.stop_gradient(self.pol.astype(dtype))
        return alpha_of_rho(pol, self.rho_max(dtype))

    def with_fitted_inverse(self, *, max_error_px: float = 0.01) -> OCamCalib:
        """A copy whose ``invpol`` is fitted again to the exact model (as OCamCalib's
        ``findinvpoly``: the shortest polynomial in ``alpha - pi/2`` whose largest radius error
        over the domain is below ``max_error_px``, else the longest, `OCAM_INVPOL_LENGTH`). Only
        the Newton start of `project` depends on it; NumPy, not traceable."""
        pol = np.asarray(self.pol, dtype=np.float64)
        rho_max = float(self.rho_max(np.float64 if jax.config.jax_enable_x64 else np.float32))
        rho = np.linspace(0.0, rho_max, 1024)
        p = np.polynomial.polynomial.polyval(rho, pol)
        t = np.arctan2(rho, -p) - math.pi / 2
        best = np.zeros(OCAM_INVPOL_LENGTH)
        for n in range(2, OCAM_INVPOL_LENGTH + 1):
            with warnings.catch_warnings():  # high degrees are poorly conditioned: the error test decides
                warnings.simplefilter("ignore", np.exceptions.RankWarning)
                coef = np.polynomial.polynomial.polyfit(t, rho, n - 1)
            best = np.pad(coef, (0, OCAM_INVPOL_LENGTH - n))
            if np.max(np.abs(np.polynomial.polynomial.polyval(t, coef) - rho)) < max_error_px:
                break
        return eqx.tree_at(lambda c: c.invpol, self, jnp.asarray(best, self.invpol.dtype))

    @eqx.filter_jit
    def project(
        self, points: Float[ArrayLike, "*batch 3"]
    ) -> tuple[Float[Array, "*batch 2"], Bool[Array, "*batch"]]:
        """Pixels ``(..., 2)`` of camera-frame points ``(..., 3)`` (``world2cam``, made exact)."""
        p, dtype = as_coordinates(points, 3, "OCamCalib.project: points")
        pol = self.pol.astype(dtype)
        lens = pol[0] < 0
        pol = jnp.where(lens, pol, jnp.zeros_like(pol).at[0].set(-1.0))  # no lens: solve a harmless one
        x, y, z, finite = point_direction(p)
        chi = safe_hypot(x, y)
        r = safe_hypot(x, y, z)
        nonzero = r > 0
        alpha = incidence_angle(jnp.where(nonzero, chi, 0.0), jnp.where(nonzero, z, 1.0))
        alpha_over_chi, defined = radial_ratio(alpha, chi, r, z)
        rho_max = self.rho_max(dtype)
        pol_sg = jax.lax.stop_gradient(pol)
        alpha_max = alpha_of_rho(pol_sg, rho_max)
        inside = alpha <= alpha_max
        target = jnp.minimum(alpha, alpha_max)
        rho0 = self._initial_rho(pol_sg, jax.lax.stop_gradient(target), rho_max, dtype)
        rho, converged = _solve_rho(pol, target, rho_max, rho0)
        # rho / alpha, with its Taylor expansion at the axis (-a0 + a0 a1 alpha).
        tiny = jnp.asarray(math.sqrt(eps_for(dtype)), dtype)
        small = target < tiny
        rho_over_alpha = jnp.where(small, -pol[0] + pol[0] * pol[1] * target,
                                   rho / jnp.where(small, jnp.ones_like(target), target))
        ratio = rho_over_alpha * alpha_over_chi  # rho / sqrt(X² + Y²)
        xo = y * ratio  # OCamCalib's x (rows) is jaxfish's Y
        yo = x * ratio
        row = self.c.astype(dtype) * xo + self.d.astype(dtype) * yo + self.xc.astype(dtype)
        col = self.e.astype(dtype) * xo + yo + self.yc.astype(dtype)
        invertible = self.c.astype(dtype) - self.d.astype(dtype) * self.e.astype(dtype) != 0  # else one line of pixels
        valid = finite & defined & inside & converged & lens & invertible
        return finite_or_invalid(jnp.stack([col, row], axis=-1), valid)

    def _initial_rho(self, pol, alpha, rho_max, dtype) -> Array:
        """The inverse polynomial's radius (clipped to the domain), refined by a few fused Newton
        steps: only a starting point for the optimistix solve."""
        invpol = jax.lax.stop_gradient(self.invpol.astype(dtype))
        rho = jnp.clip(polyval(invpol, alpha - math.pi / 2), 0.0, rho_max)
        # Where invpol is far off (absent, or a polynomial being fitted), a bisection instead: the
        # Newton solve must converge on its first try (its fallback would still be differentiated).
        far = jnp.abs(alpha_of_rho(pol, rho) - alpha) > _GUESS_ANGLE_RAD
        rho = jnp.where(far, bisection_guess(alpha_of_rho, pol, alpha, rho_max), rho)
        for _ in range(_GUESS_STEPS):
            p = polyval(pol, rho)
            slope = _dalpha_numerator(pol, rho) / jnp.maximum(rho * rho + p * p, eps_for(dtype))
            step = (alpha_of_rho(pol, rho) - alpha) / jnp.maximum(slope, eps_for(dtype))
            rho = jnp.clip(rho - step, 0.0, rho_max)
        return rho

    @eqx.filter_jit
    def unproject(
        self, uv: Float[ArrayLike, "*batch 2"]
    ) -> tuple[Float[Array, "*batch 3"], Bool[Array, "*batch"]]:
        """Unit rays ``(..., 3)`` of pixels ``(..., 2)`` (``cam2world``); invalid beyond `rho_max`."""
        uv, dtype = as_coordinates(uv, 2, "OCamCalib.unproject: uv")
        uv, finite = finite_pixels(uv)
        pol = self.pol.astype(dtype)
        lens = pol[0] < 0
        c, d, e = self.c.astype(dtype), self.d.astype(dtype), self.e.astype(dtype)
        invertible = c - d * e != 0
        xp, yp = affine_solve(c, d, e, uv[..., 1] - self.xc.astype(dtype), uv[..., 0] - self.yc.astype(dtype))
        rho = safe_hypot(xp, yp)
        measurable = jnp.isfinite(rho)
        rho = jnp.where(measurable, rho, 0.0)
        xp, yp = jnp.where(measurable, xp, 0.0), jnp.where(measurable, yp, 0.0)
        rho_max = self.rho_max(dtype)
        inside = rho <= rho_max * (1 + 4 * eps_for(dtype))
        zp = polyval(pol, jnp.minimum(rho, rho_max))
        zp = jnp.where(lens, zp, -1.0)
        norm = safe_hypot(xp, yp, zp)
        inv = 1.0 / jnp.where(norm > 0, norm, 1.0)
        ray = stack_last([yp * inv, xp * inv, -zp * inv])
        return finite_or_invalid(ray, inside & measurable & finite & lens & invertible & (norm > 0))


def _padded(values, n: int, name: str, dtype) -> Array:
    a = jnp.asarray(values, dtype=dtype)
    if a.ndim == 0:
        raise ValueError(f"OCamCalib: {name} must be a sequence of coefficients, got a scalar")
    if a.shape[-1] > n:
        extra = a[..., n:]
        if not isinstance(extra, jax.core.Tracer) and bool(jnp.any(extra != 0)):
            raise ValueError(f"OCamCalib: {name} has {a.shape[-1]} coefficients, at most {n} are supported")
        a = a[..., :n]
    pad = [(0, 0)] * (a.ndim - 1) + [(0, n - a.shape[-1])]
    return jnp.pad(a, pad)
