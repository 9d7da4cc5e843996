"""The WoodScape 4th-order polynomial fisheye model (``"radial_poly"``)."""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import TypeVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float

from .._numerics import eps_for, float_dtype, incidence_angle, radial_ratio, resolve_dtype, safe_hypot
from ._base import (
    AbstractCamera,
    as_coordinates,
    check_image_size,
    finite_or_invalid,
    interval_problem,
    point_direction,
)
from ._domain import all_of_batch, bisection_bracket, first_increasing_limit

T = TypeVar("T")

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


_SEED_DEGREE = {jnp.dtype(jnp.float32): 12, jnp.dtype(jnp.float64): 12}
"""Degree of the per-lens Chebyshev interpolant of theta(rho) that seeds the per-pixel Newton steps
(3e-5 rad on SynWoodScape lenses; 1e-4 at degree 10, 1e-3 at degree 8)."""
_NEWTON_STEPS = {jnp.dtype(jnp.float32): 1, jnp.dtype(jnp.float64): 2}
"""Newton steps from the seed; the error squares with each (about 0.5 e**2 rad on SynWoodScape
lenses): 3e-5 -> 1e-9 rad, below float32's resolution, in one step; -> 1e-18 in float64's second."""
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
    lo, hi = bisection_bracket(lambda theta: rho_of_theta(k, theta), nodes, theta_max, _NODE_BISECTIONS)
    transform = 2.0 / n * np.cos(np.outer(np.arange(n), angles))
    transform[0] /= 2
    return jnp.asarray(transform, dtype) @ (0.5 * (lo + hi))


def _monomial(coeffs: Float[Array, " n"]) -> Float[Array, " n"]:
    """The power-series coefficients of ``sum_j coeffs[j] T_j(x)`` (a fixed linear map; on
    ``[-1, 1]`` and at degree 12 its rounding stays far below the seed's own error, also in
    float32)."""
    n = coeffs.shape[0]
    basis = np.zeros((n, n))
    for j in range(n):
        basis[: j + 1, j] = np.polynomial.chebyshev.cheb2poly(np.eye(n)[j])[: j + 1]
    return jnp.asarray(basis, coeffs.dtype) @ coeffs


def _estrin(a: Float[Array, " n"], x: Float[Array, "*batch"]) -> Float[Array, "*batch"]:
    """``sum_j a[j] x**j`` by Estrin's scheme: pairs, then pairs of pairs, so the dependency chain
    is ``log2(n)`` multiply-adds deep instead of Horner's ``n`` (the per-pixel solve is bound by
    that latency, not by the arithmetic)."""
    terms = [a[j] for j in range(a.shape[0])]
    power = x
    while len(terms) > 1:
        if len(terms) % 2:
            terms.append(None)
        terms = [lo if hi is None else lo + hi * power for lo, hi in zip(terms[::2], terms[1::2], strict=True)]
        power = power * power
    return terms[0] + jnp.zeros_like(x)


def _checked(k, rho, theta) -> Array:
    """``theta`` where it passes the residual check ``|rho(theta) - rho| <= 64 eps max(rho, 1)``
    pixels, else -1 (thetas are never negative): one array, so XLA keeps the solve in a single
    vectorised loop instead of recomputing it for a second output."""
    error = jnp.abs(rho_of_theta(k, theta) - rho)
    ok = error <= 64 * eps_for(rho.dtype) * jnp.maximum(jnp.abs(rho), 1.0)  # False for NaN
    return jnp.where(ok, theta, -1.0)


def _fast_theta(k, rho, theta_max) -> Array:
    """The root of ``rho(theta) = min(rho, rho(theta_max))`` from the per-lens Chebyshev seed
    (`_chebyshev_seed`, evaluated as a power series by `_estrin`) and `_NEWTON_STEPS` clipped
    Newton steps: one fused, vectorised elementwise pass, no sine or cosine; -1 where the result
    fails the residual check (`_checked`)."""
    dtype = rho.dtype
    rho_max = rho_of_theta(k, theta_max)
    coeffs = _monomial(_chebyshev_seed(k, rho_max, theta_max))
    scale = 2.0 / jnp.maximum(rho_max, jnp.finfo(dtype).tiny)
    target = jnp.minimum(rho, rho_max)
    theta = jnp.clip(_estrin(coeffs, target * scale - 1.0), 0.0, theta_max)
    tiny = jnp.asarray(eps_for(dtype), dtype) * k[0]
    for _ in range(_NEWTON_STEPS[jnp.dtype(dtype)]):
        step = (rho_of_theta(k, theta) - target) / jnp.maximum(drho_dtheta(k, theta), tiny)
        theta = jnp.clip(theta - step, 0.0, theta_max)
    return _checked(k, target, theta)


def _bisect(k, target, theta_max) -> Array:
    """Element-wise bisection of ``rho(theta) = target`` on ``[0, theta_max]`` (where rho
    increases), down to the last float: certain, slow (`_RETRY_BISECTIONS` passes), for the lenses
    whose Newton steps the seed cannot start (`solve_theta`). The bracket is the midpoint alone,
    moved by ``theta_max / 2**(i + 2)`` towards the root at step ``i``: one plane of state, so the
    retry adds few buffers to the program (on CPU, temporaries above glibc's 32 MiB mmap limit
    are page-faulted afresh on every call, the fast path's too)."""

    def bisect(i, theta):
        half = jnp.ldexp(theta_max, -(i + 2))
        return theta + jnp.where(rho_of_theta(k, theta) < target, half, -half)

    return jax.lax.fori_loop(0, _RETRY_BISECTIONS[jnp.dtype(target.dtype)], bisect, jnp.full_like(target, 0.5) * theta_max)


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

    Values from `_fast_theta` (a per-lens Chebyshev seed, `_NEWTON_STEPS` Newton steps: one in
    float32, two in float64, and the residual check); should the check fail anywhere (a lens whose
    rho flattens near ``theta_max``, where the seed is poor), the whole batch is solved again by
    bisection (`_bisect`), under a ``lax.cond`` on `all_of_batch`: the retry runs only when needed
    and stays a branch under ``vmap`` over cameras.
    Values are computed on stopped-gradient inputs; gradients with respect to ``rho`` and ``k``
    are implicit (exact): `_implicit_theta`. Returns ``(theta, converged)``; `converged` is a
    per-element residual check, never a silent default.
    """
    return _solve_then(k, lambda: rho, theta_max, lambda theta, converged: (theta, converged))


def _solve_then(k: Array, rho_of: Callable[[], Array], theta_max: Array, then: Callable[[Array, Array], T]) -> T:
    """`solve_theta`, continued by ``then(theta, converged)`` inside both branches of the retry's
    cond: a caller's outputs are written once (a cond that returned ``theta`` would copy it), and
    ``rho_of()`` recomputes the radii where they are needed (the solve itself, the retry) instead
    of storing them as an operand of the cond."""
    k_sg, theta_max = jax.lax.stop_gradient(k), jax.lax.stop_gradient(theta_max)
    rho_max = rho_of_theta(k_sg, theta_max)

    def finish(checked):
        target = jnp.minimum(rho_of(), rho_max)
        return then(_implicit_theta(jnp.maximum(checked, 0.0), k, target), checked >= 0)

    def retry(checked):
        bounded = jnp.minimum(jax.lax.stop_gradient(rho_of()), rho_max)
        return finish(_checked(k_sg, bounded, _bisect(k_sg, bounded, theta_max)))

    checked = _fast_theta(k_sg, jax.lax.stop_gradient(rho_of()), theta_max)
    # One reduction (the minimum) rather than a boolean plane and its reduction: -1 marks a failure.
    return jax.lax.cond(all_of_batch(jnp.min(checked, initial=0.0) >= 0), finish, retry, checked)


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

    def domain_problem(self) -> str | None:
        """Why the parameters lie outside the model's domain (``aspect_ratio > 0``), or None."""
        return interval_problem("aspect_ratio", self.aspect_ratio, 0.0, open_low=True)

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
        theta_max = self.theta_max(dtype)
        rho_max = rho_of_theta(jax.lax.stop_gradient(k), theta_max)
        rho_limit = rho_max * (1 + 4 * eps_for(dtype))  # the pixel of theta_max itself, after rounding

        def centred(uv):
            # Per coordinate plane throughout: XLA on CPU does not vectorise reductions or
            # concatenations over a minor axis of size 2 or 3 (`finite_pixels`, `finite_or_invalid`).
            u, v = uv[..., 0], uv[..., 1]
            finite = jnp.isfinite(u) & jnp.isfinite(v)  # a non-finite pixel becomes (0, 0): no NaN in gradients
            x = jnp.where(finite, u, 0.0) - cx
            y = (jnp.where(finite, v, 0.0) - cy) / a
            r2 = x * x + y * y
            measurable = jnp.isfinite(r2)  # squares overflow beyond ~1e19 px (float32): invalid, not NaN
            return x, y, jnp.where(measurable, r2, 0.0), finite & measurable

        def ray_of(theta, converged):
            # The pixel's coordinates again, from `uv` itself: recomputing them costs less than
            # storing them as operands of the retry's cond and reading them back.
            x, y, r2, finite = centred(uv)
            inside = r2 <= rho_limit * rho_limit
            # sin(θ)/rho = sinc(θ) / (rho(θ)/θ) at the root: smooth through the principal point, and
            # no per-pixel sine, cosine or division by rho (both series are exact to rounding on [0, pi]).
            s = _sinc(theta) / _rho_over_theta(k, theta)
            ok = jnp.isfinite(x * s) & jnp.isfinite(y * s)  # False only for a degenerate lens
            s = jnp.where(ok, jnp.maximum(s, 0.0), 0.0)
            # The validity rides in the sign bit of s (+0 or more here) and the ray takes |s|: one
            # plane feeds both outputs, and the ray stays one branch-free, vectorised loop.
            s = jnp.where(inside & converged & finite & lens & ok, s, -s)
            valid = ~jnp.signbit(s)
            s = jnp.abs(s)
            c = _cos(theta)
            # The ray as one elementwise loop over (..., 3), selecting its component by index: no
            # minor-axis concatenation (which XLA on CPU neither vectorises nor writes in place).
            j = jax.lax.broadcasted_iota(jnp.int32, (*s.shape, 3), s.ndim)
            ray = jnp.where(j == 2, c[..., None], jnp.where(j == 0, x[..., None], y[..., None]) * s[..., None])
            return ray, valid

        return _solve_then(k, lambda: _radius(centred(uv)[2]), theta_max, ray_of)


def _radius(r2: Array) -> Array:
    """``sqrt(r2)``, with a finite gradient (0) at ``r2 = 0``."""
    return jnp.where(r2 > 0, jnp.sqrt(jnp.where(r2 > 0, r2, 1.0)), 0.0)


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
