"""The WoodScape 4th-order polynomial fisheye model (``"radial_poly"``)."""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float

from .._numerics import eps_for, float_dtype, incidence_angle, radial_ratio, resolve_dtype, safe_hypot
from ._base import AbstractCamera, as_coordinates, check_image_size, finite_or_invalid, point_direction
from ._domain import all_of_batch, first_increasing_limit

THETA_MAX_MARGIN_RAD = 1e-3
"""When rho(theta) has a stationary point theta_s <= pi, the valid domain is [0, theta_s - margin]:
at theta_s itself the inverse has infinite slope and is not a usable ray."""
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


_SEED_DEGREE = {jnp.dtype(jnp.float32): 8, jnp.dtype(jnp.float64): 12}
"""Degree of the per-lens Chebyshev interpolant of theta(rho) that seeds the per-pixel Newton steps
(1e-3 rad on SynWoodScape lenses at degree 8, 3e-5 at degree 12)."""
_FAST_NEWTON_STEPS = 2
"""Newton steps from the seed: the error squares with each (1e-3 -> 1e-7 -> 1e-14 rad)."""
_NODE_BISECTIONS = 64
"""Bisection steps that place the interpolation nodes (exact to the last bit in float64)."""
_RETRY_BISECTIONS = {jnp.dtype(jnp.float32): 40, jnp.dtype(jnp.float64): 72}
"""Bisection steps of the retry: the bracket ``[0, pi]`` shrinks to adjacent floats down to
``theta`` ~ 1e-4 (float32) and 1e-6 (float64) rad; smaller roots meet the residual check earlier."""


def _chebyshev_seed(k: Float[Array, "4"], rho_max: Float[Array, ""], theta_max: Float[Array, ""]
                    ) -> Float[Array, " n"]:
    """Chebyshev coefficients of theta(rho) on ``[0, rho_max]`` (argument ``2 rho / rho_max - 1``),
    interpolated at the first-kind nodes, whose thetas come from a bisection on ``[0, theta_max]``.
    Computed once per lens (a few dozen scalars); not differentiated (it is only a starting point)."""
    dtype = k.dtype
    n = _SEED_DEGREE[jnp.dtype(dtype)] + 1
    angles = np.pi * (np.arange(n) + 0.5) / n
    nodes = jnp.asarray((np.cos(angles) + 1) / 2, dtype) * rho_max

    def bisect(_, bracket):
        a, b = bracket
        m = 0.5 * (a + b)
        low = rho_of_theta(k, m) < nodes
        return jnp.where(low, m, a), jnp.where(low, b, m)

    zero = jnp.zeros_like(nodes)
    lo, hi = jax.lax.fori_loop(0, _NODE_BISECTIONS, bisect, (zero, zero + theta_max))
    transform = 2.0 / n * np.cos(np.outer(np.arange(n), angles))
    transform[0] /= 2
    return jnp.asarray(transform, dtype) @ (0.5 * (lo + hi))


def _clenshaw(coeffs: Float[Array, " n"], x: Float[Array, "*batch"]) -> Float[Array, "*batch"]:
    """``sum_j coeffs[j] T_j(x)`` (Clenshaw's recurrence, unrolled)."""
    b1 = jnp.zeros_like(x)
    b2 = jnp.zeros_like(x)
    two_x = x + x
    for j in range(coeffs.shape[0] - 1, 0, -1):
        b1, b2 = coeffs[j] + two_x * b1 - b2, b1
    return coeffs[0] + x * b1 - b2


def _checked(k, rho, theta) -> Array:
    """``theta`` where it passes the residual check ``|rho(theta) - rho| <= 64 eps max(rho, 1)``
    pixels, else -1 (thetas are never negative): one array, so XLA keeps the solve in a single
    vectorised loop instead of recomputing it for a second output."""
    error = jnp.abs(rho_of_theta(k, theta) - rho)
    ok = error <= 64 * eps_for(rho.dtype) * jnp.maximum(jnp.abs(rho), 1.0)  # False for NaN
    return jnp.where(ok, theta, -1.0)


def _fast_theta(k, rho, theta_max) -> Array:
    """The root of ``rho(theta) = min(rho, rho(theta_max))`` from the per-lens Chebyshev seed
    (`_chebyshev_seed`) and `_FAST_NEWTON_STEPS` clipped Newton steps: one fused, vectorised
    elementwise pass, no sine or cosine; -1 where the result fails the residual check (`_checked`)."""
    dtype = rho.dtype
    rho_max = rho_of_theta(k, theta_max)
    coeffs = _chebyshev_seed(k, rho_max, theta_max)
    scale = 2.0 / jnp.maximum(rho_max, jnp.finfo(dtype).tiny)
    target = jnp.minimum(rho, rho_max)
    theta = jnp.clip(_clenshaw(coeffs, target * scale - 1.0), 0.0, theta_max)
    tiny = jnp.asarray(eps_for(dtype), dtype) * k[0]
    for _ in range(_FAST_NEWTON_STEPS):
        step = (rho_of_theta(k, theta) - target) / jnp.maximum(drho_dtheta(k, theta), tiny)
        theta = jnp.clip(theta - step, 0.0, theta_max)
    return _checked(k, target, theta)


def _solve_theta_values(k, rho, theta_max) -> Array:
    """The root of ``rho(theta) = min(rho, rho(theta_max))`` on ``[0, theta_max]`` (values only, no
    derivative), -1 where no root passed the residual check.

    `_fast_theta` for every pixel; should any pixel fail its residual check (a lens whose rho
    flattens near ``theta_max``, where the seed is poor), the whole batch is solved again by
    bisection (`_bisect`), under a ``lax.cond`` on `all_of_batch`: the retry runs only when needed
    and stays a branch under ``vmap`` over cameras. The cond also keeps the thetas in one buffer
    (XLA would otherwise fuse the solve into each of its consumers). The retry is a plain
    bisection rather than an iterative solver library: its few buffers keep the program's
    temporaries small (on CPU, allocations above glibc's 32 MiB mmap limit are page-faulted
    afresh on every call)."""
    rho_max = rho_of_theta(k, theta_max)
    theta = _fast_theta(k, rho, theta_max)

    def retry():
        target = jnp.minimum(rho, rho_max)
        return _checked(k, target, _bisect(k, target, theta_max))

    return jax.lax.cond(all_of_batch(theta >= 0), lambda: theta, retry)


def _bisect(k, target, theta_max) -> Array:
    """Element-wise bisection of ``rho(theta) = target`` on ``[0, theta_max]`` (where rho
    increases) until the bracket is two adjacent floats: certain, slow (`_RETRY_BISECTIONS`
    passes), for the lenses whose Newton steps the seed cannot start (`_solve_theta_values`)."""

    def bisect(_, bracket):
        lo, hi = bracket
        m = 0.5 * (lo + hi)
        low = rho_of_theta(k, m) < target
        return jnp.where(low, m, lo), jnp.where(low, hi, m)

    zero = jnp.zeros_like(target)
    lo, hi = jax.lax.fori_loop(0, _RETRY_BISECTIONS[jnp.dtype(target.dtype)], bisect, (zero, zero + theta_max))
    return 0.5 * (lo + hi)


@jax.custom_jvp
def _implicit_theta(theta: Array, k: Array, rho: Array) -> Array:
    """``theta`` (a root of ``rho_of_theta(k, theta) = rho``) with the implicit-function derivative
    ``d theta = (d rho - sum_j theta^(j+1) d k_j) / rho'(theta)`` attached (exact at the root, to
    every order: the rule differentiates through itself)."""
    return theta


@_implicit_theta.defjvp
def _implicit_theta_jvp(primals, tangents):
    theta, k, rho = primals
    _, dk, drho = tangents
    out = _implicit_theta(theta, k, rho)
    dpoly = out * (dk[..., 0] + out * (dk[..., 1] + out * (dk[..., 2] + out * dk[..., 3])))
    return out, (drho - dpoly) / drho_dtheta(k, out)


def solve_theta(
    k: Float[Array, "4"], rho: Float[Array, "*batch"], theta_max: Float[Array, ""]
) -> tuple[Float[Array, "*batch"], Bool[Array, "*batch"]]:
    """Invert rho(theta) = rho on [0, theta_max] (element-wise; ``k1 > 0``); ``rho`` beyond
    ``rho(theta_max)`` gives ``theta_max``.

    Values from `_solve_theta_values` (a per-lens Chebyshev seed, two Newton steps, the residual
    check, and a bisection retry should the check fail anywhere), computed
    on stopped-gradient inputs; gradients with respect to ``rho`` and ``k`` are implicit (exact):
    `_implicit_theta`. Returns ``(theta, converged)``; `converged` is a per-element residual check,
    never a silent default.
    """
    k_sg, theta_max = jax.lax.stop_gradient(k), jax.lax.stop_gradient(theta_max)
    checked = _solve_theta_values(k_sg, jax.lax.stop_gradient(rho), theta_max)
    return _implicit_theta(jnp.maximum(checked, 0.0), k, jnp.minimum(rho, rho_of_theta(k_sg, theta_max))), checked >= 0


class WoodScapeFisheye(AbstractCamera):
    """The WoodScape fisheye model, exactly as ``scripts/calibration/projection.py``.

    Projection of a camera-frame point ``(X, Y, Z)`` (OpenCV frame)::

        chi = sqrt(X² + Y²),  theta = atan2(chi, Z)          # theta in [0, pi]
        rho = k1 θ + k2 θ² + k3 θ³ + k4 θ⁴                    # pixels
        u = rho X / chi + cx,  v = rho Y / chi * aspect_ratio + cy
        cx = W/2 + cx_offset - 0.5,  cy = H/2 + cy_offset - 0.5   # pixel-centre convention

    Unprojection inverts rho by Newton steps from a per-lens fitted seed (a bisection where they
    fall short) on the valid domain ``[0, theta_max]`` (see
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
        k = self.k.astype(dtype)
        lens = k[..., 0] > 0  # k1 <= 0: no valid ray (solve a harmless lens instead of dividing by k1)
        k = jnp.where(lens, k, jnp.asarray([1.0, 0.0, 0.0, 0.0], dtype))
        cx, cy = self._principal_point(dtype)
        a = self.aspect_ratio.astype(dtype)
        # Per coordinate plane throughout: XLA on CPU does not vectorise reductions or
        # concatenations over a minor axis of size 2 or 3 (`finite_pixels`, `finite_or_invalid`).
        u, v = uv[..., 0], uv[..., 1]
        finite = jnp.isfinite(u) & jnp.isfinite(v)  # a non-finite pixel becomes (0, 0): no NaN in gradients
        x = jnp.where(finite, u, 0.0) - cx
        y = (jnp.where(finite, v, 0.0) - cy) / a
        r2 = x * x + y * y
        measurable = jnp.isfinite(r2)  # squares overflow beyond ~1e19 px (float32): invalid, not NaN
        r2 = jnp.where(measurable, r2, 0.0)
        rho = jnp.where(r2 > 0, jnp.sqrt(jnp.where(r2 > 0, r2, 1.0)), 0.0)
        theta_max = self.theta_max(dtype)
        rho_max = rho_of_theta(jax.lax.stop_gradient(k), theta_max)
        inside = rho <= rho_max * (1 + 4 * eps_for(dtype))  # the pixel of theta_max itself, after rounding
        theta, converged = solve_theta(k, rho, theta_max)
        # sin(θ)/rho = sinc(θ) / (rho(θ)/θ) at the root: smooth through the principal point, and no
        # per-pixel sine, cosine or division by rho (both series are exact to rounding on [0, pi]).
        s = _sinc(theta) / _rho_over_theta(k, theta)
        # A ray that is not finite (a degenerate lens) is invalid; the flag rides in the sign of
        # s (never negative otherwise), so the ray below stays one branch-free, vectorised loop.
        s = jnp.where(jnp.isfinite(x * s) & jnp.isfinite(y * s), s, -1.0)
        ok = s >= 0
        s = jnp.maximum(s, 0.0)
        c = jnp.where(ok, _cos(theta), 0.0)
        # The ray as one elementwise loop over (..., 3), selecting its component by index: no
        # minor-axis concatenation (which XLA on CPU neither vectorises nor writes in place).
        j = jax.lax.broadcasted_iota(jnp.int32, (*rho.shape, 3), rho.ndim)
        ray = jnp.where(j == 2, c[..., None], jnp.where(j == 0, x[..., None], y[..., None]) * s[..., None])
        return ray, inside & converged & measurable & finite & lens & ok


def _series(coefficients: tuple[float, ...], t2: Array) -> Array:
    out = jnp.full_like(t2, coefficients[-1])
    for c in coefficients[-2::-1]:
        out = c + t2 * out
    return out


def _taylor(first: int, dtype) -> tuple[float, ...]:
    """Coefficients in ``t²`` of the Taylor series of ``sin(t)/t`` (``first = 1``) or ``cos(t)``
    (``first = 0``), to the last term that still matters at ``t = pi`` in ``dtype``."""
    terms, n = [], first
    while True:
        c = (-1) ** (n // 2) / math.factorial(n)
        terms.append(c)
        if math.pi ** n * abs(c) < eps_for(dtype) / 64:
            return tuple(terms)
        n += 2


def _sinc(theta: Array) -> Array:
    """``sin(θ)/θ`` for ``θ`` in ``[0, pi]`` (a polynomial in ``θ²``, vectorised; 1 at 0)."""
    return _series(_taylor(1, theta.dtype), theta * theta)


def _cos(theta: Array) -> Array:
    """``cos(θ)`` for ``θ`` in ``[0, pi]`` (a polynomial in ``θ²``, vectorised)."""
    return _series(_taylor(0, theta.dtype), theta * theta)
