"""The intrinsic parameters of every jaxfish lens model: names, vectors, and plain-dict form."""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Float

from ..cameras import (
    MAX_IMAGE_SIDE,
    AbstractCamera,
    FieldOfView,
    Fisheye624,
    MeiCamera,
    OpenCVPinhole,
    WoodScapeFisheye,
)
from ..cameras._double_sphere import DoubleSphere
from ..cameras._kannala_brandt import KannalaBrandt
from ..cameras._unified import ExtendedUnifiedCamera, UnifiedCamera

MODEL_CLASSES: dict[str, type[AbstractCamera]] = {
    "radial_poly": WoodScapeFisheye,
    "kannala_brandt": KannalaBrandt,
    "unified": UnifiedCamera,
    "extended_unified": ExtendedUnifiedCamera,
    "double_sphere": DoubleSphere,
    "mei": MeiCamera,
    "opencv": OpenCVPinhole,
    "fov": FieldOfView,
    "fisheye624": Fisheye624,
}
"""Model names (the ``intrinsic.model`` value of a calibration JSON) and their camera classes."""

PARAMETER_NAMES: dict[str, tuple[str, ...]] = {
    "radial_poly": ("k1", "k2", "k3", "k4", "cx_offset", "cy_offset", "aspect_ratio"),
    "kannala_brandt": ("fx", "fy", "cx", "cy", "k1", "k2", "k3", "k4"),
    "unified": ("fx", "fy", "cx", "cy", "alpha"),
    "extended_unified": ("fx", "fy", "cx", "cy", "alpha", "beta"),
    "double_sphere": ("fx", "fy", "cx", "cy", "xi", "alpha"),
    "mei": ("fx", "fy", "cx", "cy", "xi", "k1", "k2", "p1", "p2"),
    "opencv": ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6", "s1", "s2", "s3", "s4"),
    "fov": ("fx", "fy", "cx", "cy", "w"),
    "fisheye624": ("fx", "fy", "cx", "cy", "k0", "k1", "k2", "k3", "k4", "k5", "p0", "p1", "s0", "s1", "s2", "s3"),
}
"""Intrinsic parameter names of each model, in vector order (pixels for k of radial_poly,
fx, fy, cx, cy, cx_offset, cy_offset; radians for w of fov; dimensionless otherwise)."""

FIELD_LAYOUTS: dict[str, tuple[tuple[str, int], ...]] = {
    "mei": (("fx", 0), ("fy", 0), ("cx", 0), ("cy", 0), ("xi", 0), ("distortion", 4)),
    "opencv": (("fx", 0), ("fy", 0), ("cx", 0), ("cy", 0), ("distortion", 12)),
    "fov": (("fx", 0), ("fy", 0), ("cx", 0), ("cy", 0), ("w", 0)),
    "fisheye624": (("fx", 0), ("fy", 0), ("cx", 0), ("cy", 0), ("k", 6), ("p", 2), ("s", 4)),
}
"""How a model's parameter vector (`PARAMETER_NAMES` order) lies in its camera's fields, in order:
``(field, n)``, ``n = 0`` for a scalar field, else a field of ``n`` coefficients; the camera's
constructor takes the fields positionally in this order."""


def _layout_split(name: str, vector) -> list:
    parts, i = [], 0
    for _, n in FIELD_LAYOUTS[name]:
        parts.append(vector[i] if n == 0 else vector[i:i + n])
        i += max(n, 1)
    return parts

MAX_INTRINSIC = 1e7
"""Largest magnitude of an intrinsic parameter read from a calibration file (pixels, pixels per
radian^n, or dimensionless): beyond any real lens (a 2000 mm lens on 1 µm pixels has a focal length
of 2e6 pixels), and small enough that projections stay finite in float32."""
MIN_FOCAL_PX = 1e-3
"""Smallest focal length (``fx``, ``fy``; radial_poly's ``k1``), pixels per radian: below it every
ray lands on the principal point and unprojection divides by ~0."""
ASPECT_RATIO_RANGE = (1e-3, 1e3)
"""The ``aspect_ratio`` (fy / fx) of a radial_poly calibration lies in this range."""


def intrinsic_range_problem(model: str, key: str, value: float) -> str | None:
    """Why the finite intrinsic ``value`` of parameter ``key`` of lens ``model`` makes the camera
    useless (beyond `MAX_INTRINSIC`, a focal length below `MIN_FOCAL_PX`, an aspect ratio outside
    `ASPECT_RATIO_RANGE`), or None when it is sensible."""
    if key in ("width", "height", "poly_order"):
        return None
    if abs(value) > MAX_INTRINSIC:
        return f"expected a magnitude at most {MAX_INTRINSIC:g}, got {value!r}"
    focal = key in ("fx", "fy") or (model == "radial_poly" and key == "k1")
    if focal and value < MIN_FOCAL_PX:
        return f"a focal length must be at least {MIN_FOCAL_PX:g} pixels per radian, got {value!r}"
    if model == "fov" and key == "w" and not abs(value) < math.pi:
        return f"expected |w| below pi radians (the field of view of the ideal fisheye lens), got {value!r}"
    if model == "mei" and key == "xi" and not value > -1:
        return f"expected xi above -1 (at or below it the unified model sees nothing), got {value!r}"
    if model == "radial_poly" and key == "aspect_ratio":
        lo, hi = ASPECT_RATIO_RANGE
        if not lo <= value <= hi:
            return f"expected an aspect ratio (fy / fx) from {lo:g} to {hi:g}, got {value!r}"
    return None


MODEL_ALIASES: dict[str, str] = {
    "woodscape": "radial_poly",
    "kb": "kannala_brandt",
    "opencv_fisheye": "kannala_brandt",
    "ucm": "unified",
    "eucm": "extended_unified",
    "ds": "double_sphere",
}
"""Aliases accepted wherever a model name is expected."""


def canonical_model_name(model: str | type | AbstractCamera) -> str:
    """The canonical model name of a name, alias, camera class or camera instance."""
    if isinstance(model, AbstractCamera):
        model = type(model)
    if isinstance(model, type):
        for name, cls in MODEL_CLASSES.items():
            if model is cls:
                return name
        raise ValueError(f"no lens model is registered for camera class {model.__name__}")
    key = str(model).strip().lower().replace("-", "_")
    key = MODEL_ALIASES.get(key, key)
    if key not in MODEL_CLASSES:
        known = ", ".join(sorted(set(MODEL_CLASSES) | set(MODEL_ALIASES)))
        raise ValueError(f"unknown lens model {model!r} (known: {known})")
    return key


def parameter_names(camera: AbstractCamera | str) -> tuple[str, ...]:
    """Names of the intrinsic parameters of a camera (or model name), in `intrinsics_vector` order."""
    return PARAMETER_NAMES[canonical_model_name(camera)]


def intrinsics_vector(camera: AbstractCamera) -> Float[Array, " P"]:
    """The intrinsic parameters of ``camera`` as one vector (order: `parameter_names`)."""
    name = canonical_model_name(camera)
    c: Any = camera
    if name in FIELD_LAYOUTS:
        return jnp.concatenate([getattr(c, f)[None] if n == 0 else getattr(c, f) for f, n in FIELD_LAYOUTS[name]])
    if name == "radial_poly":
        parts = [c.k, c.cx_offset[None], c.cy_offset[None], c.aspect_ratio[None]]
    elif name == "kannala_brandt":
        parts = [jnp.stack([c.fx, c.fy, c.cx, c.cy]), c.k]
    elif name == "unified":
        parts = [jnp.stack([c.fx, c.fy, c.cx, c.cy, c.alpha])]
    elif name == "extended_unified":
        parts = [jnp.stack([c.fx, c.fy, c.cx, c.cy, c.alpha, c.beta])]
    else:
        parts = [jnp.stack([c.fx, c.fy, c.cx, c.cy, c.xi, c.alpha])]
    return jnp.concatenate(parts)


def with_intrinsics(camera: AbstractCamera, vector: Float[Array, " P"]) -> AbstractCamera:
    """A copy of ``camera`` whose intrinsic parameters are ``vector`` (differentiable, jit-safe)."""
    name = canonical_model_name(camera)
    n = len(PARAMETER_NAMES[name])
    if vector.shape != (n,):
        raise ValueError(f"with_intrinsics: a {name} camera has {n} parameters, got a vector of shape {vector.shape}")
    if name in FIELD_LAYOUTS:
        fields = [f for f, _ in FIELD_LAYOUTS[name]]
        return eqx.tree_at(lambda c: tuple(getattr(c, f) for f in fields), camera, tuple(_layout_split(name, vector)))
    if name == "radial_poly":
        return eqx.tree_at(lambda c: (c.k, c.cx_offset, c.cy_offset, c.aspect_ratio), camera,
                           (vector[0:4], vector[4], vector[5], vector[6]))
    if name == "kannala_brandt":
        return eqx.tree_at(lambda c: (c.fx, c.fy, c.cx, c.cy, c.k), camera,
                           (vector[0], vector[1], vector[2], vector[3], vector[4:8]))
    if name == "unified":
        return eqx.tree_at(lambda c: (c.fx, c.fy, c.cx, c.cy, c.alpha), camera, tuple(vector[i] for i in range(5)))
    if name == "extended_unified":
        return eqx.tree_at(lambda c: (c.fx, c.fy, c.cx, c.cy, c.alpha, c.beta), camera,
                           tuple(vector[i] for i in range(6)))
    return eqx.tree_at(lambda c: (c.fx, c.fy, c.cx, c.cy, c.xi, c.alpha), camera, tuple(vector[i] for i in range(6)))


def camera_from_intrinsics(model: str, vector, *, width: int, height: int, dtype=None) -> AbstractCamera:
    """A new camera of ``model`` from an intrinsics vector (order: `parameter_names`)."""
    name = canonical_model_name(model)
    v = jnp.asarray(vector, dtype=dtype)
    if v.shape != (len(PARAMETER_NAMES[name]),):
        raise ValueError(f"camera_from_intrinsics: {name} needs {len(PARAMETER_NAMES[name])} parameters, got {v.shape}")
    if name in FIELD_LAYOUTS:
        return MODEL_CLASSES[name](*_layout_split(name, v), width=width, height=height, dtype=v.dtype)
    if name == "radial_poly":
        return WoodScapeFisheye(v[0:4], width=width, height=height, cx_offset=v[4], cy_offset=v[5],
                                aspect_ratio=v[6], dtype=v.dtype)
    if name == "kannala_brandt":
        return KannalaBrandt(v[0], v[1], v[2], v[3], v[4:8], width=width, height=height, dtype=v.dtype)
    return MODEL_CLASSES[name](*[v[i] for i in range(v.shape[0])], width=width, height=height, dtype=v.dtype)


def intrinsics_to_dict(camera: AbstractCamera) -> dict[str, Any]:
    """The ``"intrinsic"`` object of a calibration JSON for any model.

    ``{"model": name, "width": W, "height": H, <parameter>: value, ...}``; for ``radial_poly``
    exactly WoodScape's keys (plus ``"poly_order": 4``), so WoodScape tools read it.
    """
    name = canonical_model_name(camera)
    values = [float(x) for x in jnp.asarray(intrinsics_vector(camera))]
    out: dict[str, Any] = {"model": name, "width": float(camera.width), "height": float(camera.height)}
    out.update(zip(PARAMETER_NAMES[name], values, strict=True))
    if name == "radial_poly":
        out["poly_order"] = 4
    return dict(sorted(out.items()))


def intrinsics_from_dict(data: Mapping[str, Any], *, source: str = "<intrinsic>", dtype=None) -> AbstractCamera:
    """Inverse of `intrinsics_to_dict`; every problem raises `ValueError` naming ``source`` and the field."""
    if not isinstance(data, Mapping):
        raise ValueError(f"{source}: field 'intrinsic': expected an object, got {type(data).__name__}")
    if "model" not in data:
        raise ValueError(f"{source}: field 'intrinsic.model': missing")
    try:
        name = canonical_model_name(data["model"])
    except ValueError as e:
        raise ValueError(f"{source}: field 'intrinsic.model': {e}") from None
    keys = set(PARAMETER_NAMES[name]) | {"model", "width", "height"}
    if name == "radial_poly":
        keys.add("poly_order")
    for key in sorted(keys - {"poly_order"}):
        if key not in data:
            raise ValueError(f"{source}: field 'intrinsic.{key}': missing (model {name})")
    extra = sorted(set(data) - keys)
    if extra:
        raise ValueError(f"{source}: field 'intrinsic.{extra[0]}': unexpected key for model {name}")
    values = {}
    for key in keys - {"model"}:
        if key not in data:
            continue
        val = data[key]
        try:
            number = math.nan if isinstance(val, bool) or not isinstance(val, (int, float)) else float(val)
        except OverflowError:  # an integer beyond ~1.8e308
            number = math.inf
        if not math.isfinite(number):
            shown = f"an integer of {len(str(val))} digits" if isinstance(val, int) and len(str(val)) > 40 else repr(val)
            raise ValueError(f"{source}: field 'intrinsic.{key}': expected a finite number, got {shown}")
        if key in ("fx", "fy") and number <= 0:
            raise ValueError(f"{source}: field 'intrinsic.{key}': a focal length must be positive, got {val!r}")
        values[key] = number
    for key, number in sorted(values.items()):
        problem = intrinsic_range_problem(name, key, number)
        if problem is not None:
            raise ValueError(f"{source}: field 'intrinsic.{key}': {problem}")
    for key in ("width", "height"):
        if values[key] <= 0 or values[key] != int(values[key]):
            raise ValueError(f"{source}: field 'intrinsic.{key}': expected a positive whole number, got {data[key]!r}")
        if values[key] > MAX_IMAGE_SIDE:
            raise ValueError(f"{source}: field 'intrinsic.{key}': expected at most {MAX_IMAGE_SIDE} pixels, got {data[key]!r}")
    if name == "radial_poly" and values.get("poly_order", 4) != 4:
        raise ValueError(f"{source}: field 'intrinsic.poly_order': only 4 is supported, got {data['poly_order']!r}")
    vec = [values[k] for k in PARAMETER_NAMES[name]]
    return camera_from_intrinsics(name, vec, width=int(values["width"]), height=int(values["height"]), dtype=dtype)
