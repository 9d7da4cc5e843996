"""CARLA's wide-angle lens sensors (``sensor.camera.*_wide_angle_lens``, CARLA 0.9.16, PR #9229)."""

from __future__ import annotations

import math
from collections.abc import Mapping

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Bool, Float

from .._errors import CalibrationError
from .._numerics import eps_for, incidence_angle, radial_ratio, resolve_dtype, safe_hypot, stack_last
from ._base import AbstractCamera, as_coordinates, check_image_size, finite_or_invalid, finite_pixels, point_direction
from ._kannala_brandt import kb_theta_max, solve_theta_kb, theta_d_of_theta

CARLA_CAMERA_MODELS: tuple[str, ...] = (
    "perspective", "stereographic", "equidistant", "equisolid", "orthographic", "kannala-brandt")
"""The ``camera_model`` attribute values of CARLA's wide-angle sensors (``ECameraModel`` order)."""
CARLA_DEFAULT_KB: tuple[float, float, float, float] = (
    0.08309221636708493, 0.01112126630599195, 0.008587261043925865, 0.0008542188930970716)
"""CARLA's defaults of ``k0 .. k3`` (used when a kannala-brandt blueprint omits them)."""
CARLA_DEFAULT_FOV_DEG = 90.0
"""CARLA's default ``fov`` attribute (degrees, vertical)."""
_EDGE_MARGIN_RAD = 1e-6
"""Perspective and orthographic lenses end at 90 degrees: kept this far below it."""


def _sinc(x: Array) -> Array:
    """``sin(x) / x`` with its Taylor expansion at 0 (finite value and gradient)."""
    small = jnp.abs(x) < jnp.asarray(eps_for(x.dtype) ** 0.25, x.dtype)
    safe = jnp.where(small, jnp.ones_like(x), x)
    x2 = x * x
    return jnp.where(small, 1 - x2 / 6 + x2 * x2 / 120, jnp.sin(safe) / safe)


def normalized_radius(model: str, k: Array, theta: Array) -> Array:
    """CARLA's ``ComputeDistance``: image radius in focal units of the ray angle ``theta``."""
    return theta * radius_over_theta(model, k, theta)


def radius_over_theta(model: str, k: Array, theta: Array) -> Array:
    """``normalized_radius / theta``, smooth at ``theta = 0``; finite (a placeholder) where the
    lens has no image (perspective at and beyond 90 degrees)."""
    if model == "perspective":
        cos = jnp.cos(theta)
        return _sinc(theta) / jnp.where(cos > 0, cos, 1.0)
    if model == "stereographic":
        cos = jnp.cos(theta / 2)
        return _sinc(theta / 2) / jnp.where(cos > 0, cos, 1.0)
    if model == "equidistant":
        return jnp.ones_like(theta)
    if model == "equisolid":
        return _sinc(theta / 2)
    if model == "orthographic":
        return _sinc(theta)
    t2 = theta * theta
    return 1 + t2 * (k[0] + t2 * (k[1] + t2 * (k[2] + t2 * k[3])))


def _model_name(value) -> str:
    name = str(value).strip().lower()
    aliases = {"kannala_brandt": "kannala-brandt", "equidistance": "equidistant", "orthogonal": "orthographic"}
    name = aliases.get(name, name)
    if name not in CARLA_CAMERA_MODELS:
        raise ValueError(f"unknown CARLA camera_model {value!r} (known: {', '.join(CARLA_CAMERA_MODELS)})")
    return name


class CarlaWideAngle(AbstractCamera):
    """The lens of CARLA's wide-angle sensors, exactly as their compute shader maps pixels to rays.

    Source (carla-simulator/carla, 0.9.16, PR #9229): ``Unreal/CarlaUE4/Plugins/Carla/Shaders/
    CameraModelCommon.ush`` and ``WideAngleLens.usf`` (the shader), ``Source/Carla/Util/
    CameraModelUtil.cpp`` (``ComputeDistance``: the focal length; ``CreateDistortionParameters``:
    ``Center = Size / 2`` on integers) and ``Source/Carla/Actor/ActorBlueprintFunctionLibrary.cpp``
    (``SetCamera``: the blueprint attributes). The shader's pixel ``(i, j)`` (integer, its centre)
    looks along::

        uv = ((i, j) - (W // 2, H // 2)) / f,   theta = R⁻¹(|uv|),   ray = (sin θ uv / |uv|, cos θ)

    with ``R(θ)`` of `camera_model`: ``perspective`` tan θ, ``stereographic`` 2 tan(θ/2),
    ``equidistant`` θ, ``equisolid`` 2 sin(θ/2), ``orthographic`` sin θ, ``kannala-brandt``
    θ (1 + k0 θ² + k1 θ⁴ + k2 θ⁶ + k3 θ⁸) (the shader inverts it with 32 Newton steps; here an
    optimistix solve with implicit gradients). The focal length (pixels) comes from the
    **vertical** field of view ``fov`` (degrees) and the image height::

        f = (H / 2) / R(fov / 2)

    and the principal point is ``(W // 2, H // 2)`` in jaxfish's pixel-centre convention (CARLA's
    integer pixel index is the pixel centre). CARLA computes ``f`` in float32 (a relative
    difference of ~1e-7 from this float64 value: below 1e-4 px over a 2000-px image).

    **Domain**: ``perspective`` and ``orthographic`` up to 90 degrees (``1e-6`` rad below it);
    ``stereographic`` and ``equisolid`` up to pi (exclusive), ``equidistant`` up to pi;
    ``kannala-brandt`` up to `KannalaBrandt`'s ``theta_max`` (first stationary point minus 1e-3).
    Pixels at or beyond the rim (orthographic ``|uv| >= 1``, equisolid ``|uv| >= 2``) or beyond the
    lens (equidistant ``|uv| > pi``) have no ray.
    ``k`` is used by ``kannala-brandt`` only (CARLA ignores it otherwise).

    Fields: `fov` (degrees, vertical); `k` ``(4,)`` = ``(k0, k1, k2, k3)``; `camera_model`,
    `width`, `height` (static).
    """

    fov: Float[Array, ""]
    k: Float[Array, " 4"]
    camera_model: str = eqx.field(static=True)
    width: int = eqx.field(static=True)
    height: int = eqx.field(static=True)

    def __init__(self, camera_model: str = "kannala-brandt", fov=CARLA_DEFAULT_FOV_DEG,
                 k: Float[ArrayLike, " 4"] = CARLA_DEFAULT_KB, *, width: int, height: int, dtype=None):
        dtype = resolve_dtype(dtype, fov)
        self.camera_model = _model_name(camera_model)
        self.fov = jnp.asarray(fov, dtype=dtype)
        k = jnp.asarray(k, dtype=dtype)
        if k.shape[-1:] != (4,):
            raise ValueError(f"CarlaWideAngle: k must have shape (..., 4), got {k.shape}")
        self.k = k
        self.width, self.height = check_image_size(width, height, "CarlaWideAngle")

    # ----------------------------------------------------------------------------- blueprint
    @classmethod
    def from_blueprint(cls, attributes: Mapping[str, str], width: int | None = None, height: int | None = None,
                       *, dtype=None) -> CarlaWideAngle:
        """The lens of a CARLA wide-angle sensor from its blueprint attributes (strings, as
        ``carla.ActorBlueprint`` holds them: ``camera_model``, ``fov``, ``k0 .. k3``,
        ``image_size_x``, ``image_size_y``); CARLA's defaults for missing ones (``perspective``,
        90 degrees, `CARLA_DEFAULT_KB`, 800 x 600). ``width`` / ``height`` give the image size
        when the attributes do not (they must agree when both do). Other attributes (``role_name``,
        post-processing, ``fov_mask``, ...) do not change the geometry and are ignored; a non-zero
        ``focal_length`` (which overrides the fov-derived focal length), ``equirectangular`` or
        ``perspective`` re-rendering change it and raise `CalibrationError` (a ``ValueError``)
        naming the attribute, as does an unknown ``camera_model`` (CARLA silently falls back to
        perspective), a non-numeric value or a ``fov`` the lens cannot image."""
        try:
            return cls._from_blueprint(attributes, width, height, dtype)
        except CalibrationError:
            raise
        except ValueError as e:
            raise CalibrationError(str(e)) from None

    @classmethod
    def _from_blueprint(cls, attributes, width, height, dtype) -> CarlaWideAngle:
        if not isinstance(attributes, Mapping):
            raise ValueError(f"blueprint attributes: expected a mapping of names to strings, got {type(attributes).__name__}")

        def number(key: str, default: float) -> float:
            if key not in attributes:
                return default
            try:
                value = float(str(attributes[key]).strip())
            except ValueError:
                raise ValueError(f"blueprint attribute {key!r}: expected a number, got {attributes[key]!r}") from None
            if not math.isfinite(value):
                raise ValueError(f"blueprint attribute {key!r}: expected a finite number, got {attributes[key]!r}")
            return value

        def flag(key: str) -> bool:
            return str(attributes.get(key, "false")).strip().lower() in ("true", "1")

        try:
            model = _model_name(attributes.get("camera_model", "perspective"))
        except ValueError as e:
            raise ValueError(f"blueprint attribute 'camera_model': {e}") from None
        sizes = []
        for key, given, default in (("image_size_x", width, 800), ("image_size_y", height, 600)):
            value = number(key, float(default) if given is None else float(given))
            if value != int(value) or value <= 0:
                raise ValueError(f"blueprint attribute {key!r}: expected a positive whole number, "
                                 f"got {attributes.get(key, given)!r}")
            if given is not None and int(value) != int(given):
                raise ValueError(f"blueprint attribute {key!r}: {attributes[key]!r} disagrees with the image size {given}")
            sizes.append(int(value))
        if number("focal_length", 0.0) != 0.0:
            raise ValueError("blueprint attribute 'focal_length': a focal length overriding the fov is not supported")
        for key in ("equirectangular", "perspective"):
            if flag(key):
                raise ValueError(f"blueprint attribute {key!r}: the re-rendered {key} image is not this lens")
        fov = number("fov", CARLA_DEFAULT_FOV_DEG)
        k = tuple(number(f"k{i}", CARLA_DEFAULT_KB[i]) for i in range(4)) if model == "kannala-brandt" else (0.0,) * 4
        camera = cls(model, fov, k, width=sizes[0], height=sizes[1], dtype=dtype)
        problem = camera.fov_problem()
        if problem is not None:
            raise ValueError(f"blueprint attribute 'fov': {problem}")
        return camera

    def to_blueprint(self) -> dict[str, str]:
        """The blueprint attributes that make CARLA render this lens (``repr`` of each float: CARLA
        parses them as float32)."""
        out = {"camera_model": self.camera_model, "fov": repr(float(self.fov)),
               "image_size_x": str(self.width), "image_size_y": str(self.height)}
        if self.camera_model == "kannala-brandt":
            out.update({f"k{i}": repr(float(v)) for i, v in enumerate(jnp.asarray(self.k).tolist())})
        return out

    def fov_problem(self) -> str | None:
        """Why `fov` gives no usable focal length for this lens (None when it does)."""
        fov = float(self.fov)
        if not 0 < fov <= 360:
            return f"expected a field of view in (0, 360] degrees, got {fov!r}"
        half = math.radians(fov) / 2
        top = float(self.theta_max(jnp.float64 if jax.config.jax_enable_x64 else jnp.float32))
        if half > top + 1e-12:
            return (f"a {self.camera_model} lens images rays up to {math.degrees(top):.6g} degrees from the axis; "
                    f"a vertical fov of {fov!r} degrees exceeds it")
        f = float(self.focal_length())
        if not (math.isfinite(f) and f > 0):
            return f"a vertical fov of {fov!r} degrees gives no finite positive focal length for a {self.camera_model} lens"
        return None

    # ----------------------------------------------------------------------------- intrinsics
    @property
    def principal_point(self) -> tuple[int, int]:
        """``(W // 2, H // 2)``: integers, as CARLA's shader."""
        return (self.width // 2, self.height // 2)

    def focal_length(self, dtype=None) -> Float[Array, ""]:
        """``f = (H / 2) / R(fov / 2)`` in pixels (CARLA's ``ComputeDistance``)."""
        dtype = resolve_dtype(dtype, self.fov)
        half = jnp.deg2rad(self.fov.astype(dtype)) / 2
        return jnp.asarray(self.height / 2, dtype) / normalized_radius(self.camera_model, self.k.astype(dtype), half)

    def theta_max(self, dtype=None) -> Float[Array, ""]:
        """Largest valid ray angle (radians); see the class docstring."""
        dtype = resolve_dtype(dtype, self.fov)
        m = self.camera_model
        if m in ("perspective", "orthographic"):
            return jnp.asarray(math.pi / 2 - _EDGE_MARGIN_RAD, dtype)
        if m == "kannala-brandt":
            return kb_theta_max(self.k.astype(dtype))
        return jnp.asarray(math.pi, dtype)

    # ----------------------------------------------------------------------------- model
    @eqx.filter_jit
    def project(
        self, points: Float[ArrayLike, "*batch 3"]
    ) -> tuple[Float[Array, "*batch 2"], Bool[Array, "*batch"]]:
        """Pixels ``(..., 2)`` of camera-frame points ``(..., 3)`` and their validity. An
        orthographic or equisolid point is valid only where its rounded pixel lies strictly inside
        the rim that `unproject` excludes (in float32 the rays a few 1e-4 rad short of 90 degrees
        round onto the orthographic rim)."""
        p, dtype = as_coordinates(points, 3, "CarlaWideAngle.project: points")
        k = self.k.astype(dtype)
        f = self.focal_length(dtype)
        x, y, z, finite = point_direction(p)
        chi = safe_hypot(x, y)
        r = safe_hypot(x, y, z)
        nonzero = r > 0
        theta = incidence_angle(jnp.where(nonzero, chi, 0.0), jnp.where(nonzero, z, 1.0))
        theta_over_chi, defined = radial_ratio(theta, chi, r, z)
        top = self.theta_max(dtype)
        inside = (theta < top) if self.camera_model in ("stereographic", "equisolid") else (theta <= top)
        over_theta = radius_over_theta(self.camera_model, k, jnp.minimum(theta, top))
        ratio = f * over_theta * theta_over_chi
        cx, cy = self.principal_point
        u = x * ratio + cx
        v = y * ratio + cy
        if self.camera_model in ("orthographic", "equisolid"):  # the pixel, as `unproject` measures it, inside the rim
            pu, pv = jax.lax.optimization_barrier((u, v))  # the rounded pixel (XLA would fold (u - cx) back)
            mx, my = (pu - cx) / jnp.where(f > 0, f, 1.0), (pv - cy) / jnp.where(f > 0, f, 1.0)
            inside = inside & (mx * mx + my * my < (1.0 if self.camera_model == "orthographic" else 4.0))
        valid = finite & defined & inside & (f > 0)
        return finite_or_invalid(jnp.stack([u, v], axis=-1), valid)

    @eqx.filter_jit
    def unproject(
        self, uv: Float[ArrayLike, "*batch 2"]
    ) -> tuple[Float[Array, "*batch 3"], Bool[Array, "*batch"]]:
        """Unit rays ``(..., 3)`` of pixels ``(..., 2)`` (the shader's ray, exactly). The rim of the
        lens circle is exclusive: pixels at ``|uv| >= 1`` (orthographic) or ``|uv| >= 2``
        (equisolid), in focal lengths from the principal point, have no ray, since ``d theta / d |uv|``
        is infinite at the rim; every valid ray has finite derivatives."""
        uv, dtype = as_coordinates(uv, 2, "CarlaWideAngle.unproject: uv")
        uv, finite = finite_pixels(uv)
        k = self.k.astype(dtype)
        f = self.focal_length(dtype)
        cx, cy = self.principal_point
        safe_f = jnp.where(f > 0, f, 1.0)
        mx = (uv[..., 0] - cx) / safe_f
        my = (uv[..., 1] - cy) / safe_f
        d2 = mx * mx + my * my
        measurable = jnp.isfinite(d2)
        d2 = jnp.where(measurable, d2, 0.0)
        mx, my = jnp.where(measurable, mx, 0.0), jnp.where(measurable, my, 0.0)
        d = safe_hypot(mx, my)
        m = self.camera_model
        one = jnp.ones_like(d)
        if m == "perspective":
            s = 1 / jnp.sqrt(1 + d2)  # sin(atan d) / d
            cos = s
            inside = jnp.ones_like(d, bool)
        elif m == "stereographic":
            q = 1 + d2 / 4
            s, cos = 1 / q, (1 - d2 / 4) / q
            inside = jnp.ones_like(d, bool)
        elif m == "equidistant":
            dc = jnp.minimum(d, math.pi)
            s, cos = _sinc(dc), jnp.cos(dc)
            inside = d <= math.pi * (1 + 4 * eps_for(dtype))
        elif m == "equisolid":  # the rim |uv| = 2 (the ray straight back) is excluded: d ray / d uv is infinite there
            inside = d2 < 4
            dc2 = jnp.minimum(d2, 4.0)
            s, cos = jnp.sqrt(jnp.where(inside, 1 - dc2 / 4, 1.0)), 1 - dc2 / 2
        elif m == "orthographic":  # the rim |uv| = 1 (90 degrees) is excluded, as in project
            inside = d2 < 1
            s, cos = one, jnp.sqrt(jnp.where(inside, 1 - d2, 1.0))
        else:
            theta_max = self.theta_max(dtype)
            td_max = theta_d_of_theta(jax.lax.stop_gradient(k), theta_max)
            inside = d <= td_max * (1 + 4 * eps_for(dtype))
            theta, converged = solve_theta_kb(k, jnp.minimum(d, td_max), theta_max)
            inside = inside & converged
            tau = jnp.asarray(math.sqrt(eps_for(dtype)) * 100, dtype)
            small = d < tau
            s = jnp.where(small, 1 - (k[0] + 1.0 / 6.0) * d * d, jnp.sin(theta) / jnp.where(small, one, d))
            cos = jnp.cos(theta)
        ray = stack_last([mx * s, my * s, cos])
        return finite_or_invalid(ray, inside & measurable & finite & (f > 0))
