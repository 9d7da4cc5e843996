"""Small numerical helpers shared by the pure-JAX core.

Everything here follows one rule (jaxlie / equinox style): an unsafe value is replaced *before*
it reaches a division, sqrt or arc function, so that values **and gradients** stay finite at
singular points such as the fisheye principal point.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float


def float_dtype(*xs: ArrayLike) -> jnp.dtype:
    """The floating dtype computations should run in: that of the first floating input.

    Integer or Python inputs fall back to JAX's default float dtype (float64 under x64).
    """
    for x in xs:
        dt = getattr(x, "dtype", None)
        if dt is not None and jnp.issubdtype(dt, jnp.floating):
            return jnp.dtype(jax.dtypes.canonicalize_dtype(dt))
    return jnp.dtype(jax.dtypes.canonicalize_dtype(float))


def as_float(x: ArrayLike, dtype) -> Array:
    """``jnp.asarray(x, dtype)`` (explicit dtype: no silent float64 promotion under x64)."""
    return jnp.asarray(x, dtype=dtype)


def eps_for(dtype) -> float:
    """Machine epsilon of a floating dtype."""
    return float(np.finfo(np.dtype(dtype)).eps)


def safe_norm(x: Float[Array, "*batch n"], *, keepdims: bool = False) -> Float[Array, "*batch"]:
    """Euclidean norm over the last axis whose gradient is 0 (not NaN) at the zero vector."""
    sq = jnp.sum(x * x, axis=-1, keepdims=keepdims)
    positive = sq > 0
    safe_sq = jnp.where(positive, sq, jnp.ones_like(sq))
    return jnp.where(positive, jnp.sqrt(safe_sq), jnp.zeros_like(sq))


def safe_sqrt(x: Float[Array, "*batch"]) -> Float[Array, "*batch"]:
    """``sqrt(x)`` for ``x > 0``, else 0, with a finite value and gradient everywhere (the
    gradient is 0 for ``x <= 0``)."""
    positive = x > 0
    return jnp.where(positive, jnp.sqrt(jnp.where(positive, x, jnp.ones_like(x))), jnp.zeros_like(x))


def safe_hypot(*planes: Float[Array, "*batch"]) -> Float[Array, "*batch"]:
    """`safe_norm` of coordinates given as separate planes (no minor-axis stack to vectorise)."""
    sq = sum(c * c for c in planes)
    positive = sq > 0
    return jnp.where(positive, jnp.sqrt(jnp.where(positive, sq, 1.0)), 0.0)


def theta_over_sin(theta: Float[Array, "*batch"]) -> Float[Array, "*batch"]:
    """``theta / sin(theta)`` for theta in [0, pi), smooth at 0 (Taylor branch).

    At theta -> pi the value diverges; callers mask those points (they are invalid).
    """
    dtype = theta.dtype
    small = jnp.abs(theta) < jnp.asarray(np.sqrt(np.sqrt(eps_for(dtype))), dtype)
    t2 = theta * theta
    taylor = 1 + t2 / 6 + 7 * t2 * t2 / 360
    s = jnp.sin(theta)
    near_pi = s <= jnp.asarray(eps_for(dtype), dtype)
    safe_theta = jnp.where(small | near_pi, jnp.ones_like(theta), theta)
    safe_s = jnp.where(small | near_pi, jnp.sin(jnp.ones_like(theta)), s)
    big = safe_theta / safe_s
    return jnp.where(small, taylor, jnp.where(near_pi, jnp.zeros_like(theta), big))


def radial_ratio(theta: Float[Array, "*batch"], chi: Float[Array, "*batch"], r: Float[Array, "*batch"],
                 z: Float[Array, "*batch"]) -> tuple[Float[Array, "*batch"], Bool[Array, "*batch"]]:
    """``(theta / chi, defined)`` for a point with ``chi = |(x, y)|``, ``r = |p|`` and
    ``theta = atan2(chi, z)``: radial lens models project to ``f(theta)/theta * theta/chi * (x, y)``.

    In front (``z >= 0``) it is ``theta/sin(theta) / r``, smooth at the principal point; behind,
    ``theta / chi`` itself: ``sin`` of a rounded theta near pi would lose every digit (0.3 px at
    1e-12 rad from the back axis in float64), while ``chi`` is exact. ``defined`` is False for the
    camera centre, points within float precision of the back axis (no azimuth) and non-finite
    norms (coordinates beyond ~1e19 in float32 overflow their squares); the value is then a finite
    placeholder."""
    tiny = jnp.asarray(eps_for(theta.dtype), theta.dtype)
    back = z < 0
    finite = jnp.isfinite(r)
    front_ok = (r > 0) & finite
    back_ok = back & (chi > tiny * r) & finite
    front = theta_over_sin(jnp.where(back, jnp.zeros_like(theta), theta)) / jnp.where(front_ok, r, 1.0)
    behind = theta / jnp.where(back_ok, chi, 1.0)
    value = jnp.where(back, jnp.where(back_ok, behind, 0.0), jnp.where(front_ok, front, 0.0))
    return value, jnp.where(back, back_ok, front_ok)


def positive_integer(value, name: str) -> int:
    """``value`` as an int when it is an integer >= 1 (a Python or NumPy integer, not a bool);
    otherwise ``TypeError`` ("{name} must be an integer") or ``ValueError`` ("{name} must be >= 1 ...")."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
        raise TypeError(f"{name} must be an integer, got {value!r}")
    if value < 1:
        raise ValueError(f"{name} must be >= 1 (a positive integer), got {value}")
    return int(value)


COMPUTATION_DTYPES = (jnp.dtype(jnp.float32), jnp.dtype(jnp.float64))
"""The dtypes jaxfish computes in (a given ``dtype=`` argument must be one of them)."""


def resolve_dtype(dtype, *likes: ArrayLike) -> jnp.dtype:
    """``dtype`` if given, else `float_dtype` of ``likes``; canonicalised (float64 becomes float32
    when ``jax_enable_x64`` is off, without a warning). A given ``dtype`` other than float32 or
    float64 (an integer, boolean, complex or half-precision dtype) raises ``TypeError``."""
    if dtype is None:
        return float_dtype(*likes)
    try:
        given = jnp.dtype(dtype)
    except TypeError:
        raise TypeError(f"dtype must be float32 or float64, got {dtype!r}") from None
    if given not in COMPUTATION_DTYPES:
        raise TypeError(f"dtype must be float32 or float64, got {given}")
    return jnp.dtype(jax.dtypes.canonicalize_dtype(given))


def stack_last(arrays: list[Array]) -> Array:
    """``jnp.stack(arrays, axis=-1)`` for full-frame hot paths.

    XLA on CPU fuses the producers of a minor-axis concatenate into a per-element loop that does
    not vectorise; the components are materialised first (an optimisation barrier), stacked along
    a major axis and transposed (one extra copy of the result).
    """
    arrays = jax.lax.optimization_barrier(list(arrays))
    return jnp.moveaxis(jnp.stack(arrays, axis=0), 0, -1)


_ATANF = (8.05374449538e-2, -1.38776856032e-1, 1.99777106478e-1, -3.33329491539e-1)
"""Cephes ``atanf`` coefficients: ``atan(t) = t + t s P(s)``, ``s = t²``, for ``|t| <= tan(pi / 8)``."""


def arctan_unit(a: Float[Array, "*batch"]) -> Float[Array, "*batch"]:
    """``arctan(a)`` for ``a`` in ``[0, 1]``. In float32 a polynomial that vectorises (Cephes
    ``atanf``: within 3 ulp of the float64 value, where XLA's own ``arctan`` is within 5, and
    vectorised on CPU, where XLA calls the scalar libm function per element); other dtypes use
    ``jnp.arctan`` (float64 keeps full precision). Differentiable everywhere on ``[0, 1]``."""
    if a.dtype != jnp.float32:
        return jnp.arctan(a)
    f = jnp.float32
    big = a > f(math.tan(math.pi / 8))
    t = jnp.where(big, (a - 1) / (a + 1), a)
    s = t * t
    p0, p1, p2, p3 = (f(c) for c in _ATANF)
    p = (((p0 * s + p1) * s + p2) * s + p3) * s * t + t
    return jnp.where(big, f(math.pi / 4) + p, p)


def arctan2(y: Float[Array, "*batch"], x: Float[Array, "*batch"]) -> Float[Array, "*batch"]:
    """``jnp.arctan2(y, x)``; in float32 through `arctan_unit` of the smaller over the larger
    magnitude (the quadrant from the signs, signed zeros included, as IEEE ``atan2``), which
    vectorises on CPU. Other dtypes call ``jnp.arctan2`` itself."""
    if jnp.result_type(y, x) != jnp.float32:
        return jnp.arctan2(y, x)
    a = _first_quadrant_angle(jnp.abs(y), jnp.abs(x))
    a = jnp.where(jnp.signbit(x), math.pi - a, a)
    return jnp.where(jnp.signbit(y), -a, a)


def _first_quadrant_angle(ay: Float[Array, "*batch"], ax: Float[Array, "*batch"]) -> Float[Array, "*batch"]:
    """``atan2(ay, ax)`` for ``ay, ax >= 0`` (in ``[0, pi / 2]``): `arctan_unit` of the smaller over
    the larger, branched by `where` (not min/max: exact gradients where ``ay == ax``); 0 at the origin."""
    steep = ay > ax
    lo = jnp.where(steep, ax, ay)
    hi = jnp.where(steep, ay, ax)
    a = arctan_unit(lo / jnp.where(hi > 0, hi, 1.0))
    return jnp.where(steep, math.pi / 2 - a, a)


def incidence_angle(chi: Float[Array, "*batch"], z: Float[Array, "*batch"]) -> Float[Array, "*batch"]:
    """``atan2(chi, z)`` for ``chi >= 0`` (the angle from the optical axis, in ``[0, pi]``) through
    `arctan_unit` of the smaller over the larger magnitude: in float64 within one ulp of the
    float64 ``atan2``, in float32 within a few ulp and vectorised (XLA's ``atan2`` calls libm per
    element on CPU). ``chi = z = 0`` gives 0."""
    a = _first_quadrant_angle(chi, jnp.abs(z))
    return jnp.where(z < 0, math.pi - a, a)


@jax.custom_jvp
def materialize(tree, token: Array):
    """``tree`` unchanged, but computed once into buffers: on CPU, XLA drops optimization barriers
    and may duplicate an expensive producer (a fisheye projection) into every consumer fusion (the
    flow recomputed it several times). A while loop whose trip count XLA cannot know, and whose
    body is not an identity it could hoist, is a boundary it keeps; ``token`` (any floating scalar
    from the data) makes the count 1 at run time (0 if it is NaN: the same result). Derivatives
    pass straight through (an identity), so it is safe under `jax.grad`."""
    trips = jnp.where(token != token, 0, 1).astype(jnp.int32)

    def body(c):
        i, xs = c
        flip = i < 0  # never true; XLA cannot prove it
        return i + 1, jax.tree_util.tree_map(lambda x: jnp.where(flip, jnp.zeros_like(x), x), xs)

    _, out = jax.lax.while_loop(lambda c: c[0] < trips, body, (jnp.int32(0), tree))
    return out


@materialize.defjvp
def _materialize_jvp(primals, tangents):
    tree, token = primals
    return materialize(tree, token), tangents[0]
