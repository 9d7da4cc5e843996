"""The camera contract shared by every jaxfish camera model."""

from __future__ import annotations

import abc
import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float

from .._numerics import float_dtype, resolve_dtype


class AbstractCamera(eqx.Module):
    """A camera model: an immutable pytree mapping camera-frame points to pixels and back.

    Conventions (stated once, in `docs/conventions.md`):

    - camera frame: OpenCV — x right, y down, z forward (optical axis), metres;
    - pixels: ``(u, v)`` = (column, row); integer coordinates are pixel **centres**, ``(0, 0)`` is
      the centre of the top-left pixel, the image spans ``[-0.5, W - 0.5] x [-0.5, H - 0.5]``.

    `project` and `unproject` accept any leading batch shape and return ``(value, valid)``; invalid
    entries hold finite placeholder values (never NaN) and must be masked by the caller. Both are
    pure and safe under `jax.jit`, `jax.vmap` and `jax.grad`. A *batch of cameras* is a camera whose
    array fields have leading axes; map over it with `jax.vmap` (or `eqx.filter_vmap`).

    Computations run in the floating dtype of the coordinates passed in (the camera's parameters
    are cast to it), so a float64 camera projects float32 points in float32.
    """

    width: eqx.AbstractVar[int]
    height: eqx.AbstractVar[int]

    def __check_init__(self) -> None:
        """Refuses (``ValueError`` naming the model and the field) a camera built from concrete
        parameters that `parameter_problem` rejects. Parameters traced by `jax.jit`, `jax.vmap` or
        `jax.grad` are not inspected here; where a traced value would fold the image, the model
        masks every pixel instead (the unified models' α outside [0, 1] or β <= 0, the double
        sphere's α, a singular f-theta or OCamCalib affine matrix)."""
        problem = parameter_problem(self)
        if problem is not None:
            raise ValueError(f"{type(self).__name__}: {problem}")

    def domain_problem(self) -> str | None:
        """Why this camera's (concrete, finite) parameters lie outside its model's domain, or None.
        Models with restricted parameters (focal lengths, α, β, ξ, ...) override it."""
        return None

    @abc.abstractmethod
    def project(
        self, points: Float[ArrayLike, "*batch 3"]
    ) -> tuple[Float[Array, "*batch 2"], Bool[Array, "*batch"]]:
        """Project camera-frame points (metres) to pixels.

        `valid` is False where the model has no image of the point (behind a pinhole, beyond a
        fisheye's ``theta_max``, the camera centre itself). It does **not** test the image bounds:
        combine with `contains` for that.
        """

    @abc.abstractmethod
    def unproject(
        self, uv: Float[ArrayLike, "*batch 2"]
    ) -> tuple[Float[Array, "*batch 3"], Bool[Array, "*batch"]]:
        """Unit ray directions (camera frame) of pixels; `valid` is False where a pixel has no ray."""

    def ray_origins(self, uv: Float[ArrayLike, "*batch 2"]) -> Float[Array, "*batch 3"]:
        """Camera-frame origins of the pixel rays (zeros for central cameras)."""
        uv = jnp.asarray(uv)
        dtype = float_dtype(uv)
        return jnp.zeros(uv.shape[:-1] + (3,), dtype)

    @property
    def is_central(self) -> bool:
        """True when every ray starts at the camera centre (all models but `Orthographic`)."""
        return True

    @property
    def image_size(self) -> tuple[int, int]:
        """``(width, height)`` in pixels."""
        return (self.width, self.height)

    def contains(self, uv: Float[ArrayLike, "*batch 2"]) -> Bool[Array, "*batch"]:
        """True for pixel coordinates inside the image ``[-0.5, W-0.5] x [-0.5, H-0.5]``."""
        uv = jnp.asarray(uv)
        u, v = uv[..., 0], uv[..., 1]
        return (u >= -0.5) & (u <= self.width - 0.5) & (v >= -0.5) & (v <= self.height - 0.5)

    def pixel_grid(self, dtype=None) -> Float[Array, "H W 2"]:
        """Pixel-centre coordinates ``(u, v)`` of the whole image, shape ``(H, W, 2)``."""
        dtype = resolve_dtype(dtype, )
        u = jnp.arange(self.width, dtype=dtype)
        v = jnp.arange(self.height, dtype=dtype)
        uu, vv = jnp.meshgrid(u, v, indexing="xy")
        return jnp.stack([uu, vv], axis=-1)

    def astype(self, dtype) -> AbstractCamera:
        """A copy whose floating parameters have the given dtype."""
        dtype = resolve_dtype(dtype)

        def cast(x):
            if eqx.is_array(x) and jnp.issubdtype(x.dtype, jnp.floating):
                return x.astype(dtype)
            return x

        return jax.tree_util.tree_map(cast, self)


def parameter_problem(camera: AbstractCamera) -> str | None:
    """Why ``camera`` cannot image anything correctly, or None: a non-finite floating parameter, or
    a parameter outside its model's domain (``camera.domain_problem()``: a focal length that is not
    positive, a unified-model α outside [0, 1], ...). Cameras holding traced parameters (inside
    `jax.jit`, `jax.vmap`, `jax.grad`) give None: there is nothing concrete to inspect. Batched
    cameras are checked element by element."""
    leaves = jax.tree_util.tree_leaves(camera)
    if any(isinstance(x, jax.core.Tracer) for x in leaves):
        return None
    for field in dataclasses.fields(camera):
        value = getattr(camera, field.name, None)
        if eqx.is_array(value) and jnp.issubdtype(value.dtype, jnp.inexact) and not np.all(np.isfinite(np.asarray(value))):
            return f"{field.name} must be finite, got {_shown(value)}"
    return camera.domain_problem()


def _shown(value) -> str:
    a = np.asarray(value)
    return repr(a.item()) if a.ndim == 0 else np.array2string(a, threshold=8)


def focal_problem(fx, fy) -> str | None:
    """Why focal lengths ``fx``, ``fy`` (pixels, concrete) are not both positive, or None."""
    for name, value in (("fx", fx), ("fy", fy)):
        if not np.all(np.asarray(value) > 0):
            return f"the focal length {name} must be positive, got {_shown(value)}"
    return None


def affine_problem(c, d, e) -> str | None:
    """Why the concrete sensor affine matrix ``[[c, d], [e, 1]]`` (OCamCalib, f-theta) is singular
    (``c - d e == 0``: every ray would land on one line of pixels), or None."""
    det = np.asarray(c) - np.asarray(d) * np.asarray(e)
    if np.all(det != 0):
        return None
    return f"the affine matrix [[c, d], [e, 1]] must be invertible (c - d e != 0), got c={_shown(c)}, d={_shown(d)}, e={_shown(e)}"


def interval_problem(name: str, value, low: float | None = None, high: float | None = None, *,
                     open_low: bool = False, open_high: bool = False) -> str | None:
    """Why the concrete ``value`` of parameter ``name`` lies outside the interval from ``low`` to
    ``high`` (None: unbounded; ``open_*``: the end itself excluded), or None."""
    a = np.asarray(value)
    ok = np.ones(a.shape, bool)
    if low is not None:
        ok &= (a > low) if open_low else (a >= low)
    if high is not None:
        ok &= (a < high) if open_high else (a <= high)
    if np.all(ok):
        return None
    left = "(" if open_low or low is None else "["
    right = ")" if open_high or high is None else "]"
    lo = "-inf" if low is None else f"{low:g}"
    hi = "inf" if high is None else f"{high:g}"
    return f"{name} must lie in {left}{lo}, {hi}{right}, got {_shown(value)}"


MAX_IMAGE_SIDE = 65536
"""Largest width or height (pixels) of a camera image: every camera model refuses a larger one (one
float32 image channel of 65536 x 65536 pixels is already 16 GiB; a typo such as ``1e12`` would
otherwise reach an allocation)."""


def _split_last(x: Array, n: int) -> tuple[Array, ...]:
    if x.shape[-1:] != (n,):
        raise ValueError(f"expected a trailing axis of size {n}, got shape {x.shape}")
    return tuple(x[..., i] for i in range(n))


def as_coordinates(x: ArrayLike, n: int, where: str) -> tuple[Array, jnp.dtype]:
    """``x`` as an array with a trailing axis of size ``n``, cast to its computation dtype
    (`float_dtype`); a wrong shape raises ``ValueError`` naming ``where`` (e.g. ``"Pinhole.project: points"``)."""
    a = jnp.asarray(x)
    if a.shape[-1:] != (n,):
        raise ValueError(f"{where} must have shape (..., {n}), got {a.shape}")
    dtype = float_dtype(a)
    return a.astype(dtype), dtype


def check_image_size(width: int, height: int, where: str) -> tuple[int, int]:
    """``(int(width), int(height))``, raising ``ValueError`` naming ``where`` unless both are
    positive and at most `MAX_IMAGE_SIDE`."""
    width, height = int(width), int(height)
    if width <= 0 or height <= 0:
        raise ValueError(f"{where}: image size must be positive, got {width}x{height}")
    if width > MAX_IMAGE_SIDE or height > MAX_IMAGE_SIDE:
        raise ValueError(f"{where}: image size {width}x{height} exceeds {MAX_IMAGE_SIDE} pixels per side")
    return width, height


def finite_or_invalid(values: Float[Array, "*batch n"], valid: Bool[Array, "*batch"]
                      ) -> tuple[Float[Array, "*batch n"], Bool[Array, "*batch"]]:
    """``values`` with non-finite entries replaced by 0 and their elements marked invalid: inputs
    whose squares overflow (beyond ~1e19 in float32) are masked, never returned as NaN or as a
    wrong pixel marked valid."""
    finite = jnp.isfinite(values)
    return jnp.where(finite, values, jnp.zeros_like(values)), valid & jnp.all(finite, axis=-1)


_EXPONENT_BITS = {jnp.dtype(jnp.float32): (jnp.int32, 23, 0xFF, 127), jnp.dtype(jnp.float64): (jnp.int64, 52, 0x7FF, 1023)}


def _power_of_two(k: Array, dtype) -> Array:
    """``2**k`` (integer ``k`` within the normal exponent range) built from its bits: exact."""
    itype, mant, _, bias = _EXPONENT_BITS[jnp.dtype(dtype)]
    return jax.lax.bitcast_convert_type((k.astype(itype) + bias) << mant, dtype)


def point_direction(p: Float[Array, "*batch 3"]) -> tuple[Array, Array, Array, Bool[Array, "*batch"]]:
    """The coordinate planes ``(x, y, z)`` of points, each scaled by a power of two (exactly: no
    rounding) so that its largest component lies in ``[1, 2)``, and whether the point was finite.

    A central camera's projection only depends on the direction of a point, so the scaled point
    projects to the same pixel, with the same gradient; but neither a huge point (squares
    overflowing beyond ~1e19 in float32) nor a tiny one (squares underflowing) loses its
    direction on the way. A non-finite point becomes ``(0, 0, 1)``, flagged False, so nothing
    non-finite reaches the values or the gradients of the camera parameters."""
    x, y, z = p[..., 0], p[..., 1], p[..., 2]
    finite = jnp.isfinite(x) & jnp.isfinite(y) & jnp.isfinite(z)
    x, y, z = jnp.where(finite, x, 0.0), jnp.where(finite, y, 0.0), jnp.where(finite, z, 1.0)
    if jnp.dtype(p.dtype) not in _EXPONENT_BITS:
        return x, y, z, finite
    itype, mant, mask, bias = _EXPONENT_BITS[jnp.dtype(p.dtype)]
    m = jax.lax.stop_gradient(jnp.maximum(jnp.maximum(jnp.abs(x), jnp.abs(y)), jnp.abs(z)))
    e = (jax.lax.bitcast_convert_type(m, itype) >> mant) & mask  # biased exponent: m in [2**(e-bias), 2**(e-bias+1))
    k = bias - e  # scale by 2**k, in two normal factors (2**k alone may not be representable)
    a = k >> 1
    extreme = (e > 0) & ((k > bias // 4) | (k < -(bias // 4)))  # only where squares (or cubes) could leave the range
    s1 = jnp.where(extreme, _power_of_two(a, p.dtype), 1.0)
    s2 = jnp.where(extreme, _power_of_two(k - a, p.dtype), 1.0)
    return x * s1 * s2, y * s1 * s2, z * s1 * s2, finite


def clear_of_rim(denominator: Float[Array, "*batch"], x: Array, y: Array, z: Array) -> Bool[Array, "*batch"]:
    """Whether a projection's denominator (``z`` of a pinhole, ``alpha d + (1 - alpha) z`` of the
    unified model, ...) exceeds the dtype's machine epsilon times the point's largest component
    ``(x, y, z)`` (as `point_direction` returns them). Points closer to the model's rim project
    beyond ``1 / eps`` focal lengths from the principal point, far outside any image, and the
    derivative of their pixel (``~ 1 / denominator²``) could overflow: they are invalid, so no
    masked point sends an infinite gradient back."""
    m = jax.lax.stop_gradient(jnp.maximum(jnp.maximum(jnp.abs(x), jnp.abs(y)), jnp.abs(z)))
    return denominator > jnp.finfo(denominator.dtype).eps * m


def finite_pixels(uv: Float[Array, "*batch 2"]) -> tuple[Float[Array, "*batch 2"], Bool[Array, "*batch"]]:
    """Pixels with non-finite rows replaced by ``(0, 0)`` and whether each was finite: unprojecting
    the placeholder keeps NaN out of the values and of the gradients of the camera parameters."""
    finite = jnp.all(jnp.isfinite(uv), axis=-1)
    return jnp.where(finite[..., None], uv, jnp.zeros_like(uv)), finite


def measurable_radius(mx: Float[Array, "*batch"], my: Float[Array, "*batch"]) -> Bool[Array, "*batch"]:
    """Whether a pixel's offset from the principal point in focal units, ``(mx, my)``, is small
    enough that the closed-form unprojections (which square it, then square terms of its size
    again) stay finite: ``mx² + my² <= sqrt(max float)`` (1.8e19 in float32, ~4e9 focal lengths
    away, beyond any lens). Farther pixels are invalid, never NaN."""
    r2 = mx * mx + my * my
    bound = jnp.sqrt(jnp.asarray(jnp.finfo(r2.dtype).max, r2.dtype))
    return jnp.isfinite(r2) & (r2 <= bound)
