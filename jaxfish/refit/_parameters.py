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
    CarlaWideAngle,
    FieldOfView,
    Fisheye624,
    MeiCamera,
    OpenCVPinhole,
    WoodScapeFisheye,
)
from ..cameras._double_sphere import DoubleSphere
from ..cameras._ftheta import FTHETA_POLY_LENGTH, FTheta
from ..cameras._kannala_brandt import KannalaBrandt
from ..cameras._ocamcalib import OCAM_INVPOL_LENGTH, OCAM_POL_LENGTH, OCamCalib
from ..cameras._pinhole import Pinhole
from ..cameras._unified import ExtendedUnifiedCamera, UnifiedCamera

MODEL_CLASSES: dict[str, type[AbstractCamera]] = {
    "radial_poly": WoodScapeFisheye,
    "kannala_brandt": KannalaBrandt,
    "unified": UnifiedCamera,
    "extended_unified": ExtendedUnifiedCamera,
    "double_sphere": DoubleSphere,
    "pinhole": Pinhole,
    "mei": MeiCamera,
    "opencv": OpenCVPinhole,
    "fov": FieldOfView,
    "fisheye624": Fisheye624,
    "ocamcalib": OCamCalib,
    "ftheta": FTheta,
    "carla_wide_angle": CarlaWideAngle,
}
"""Model names (the ``intrinsic.model`` value of a calibration JSON) and their camera classes."""

PARAMETER_NAMES: dict[str, tuple[str, ...]] = {
    "radial_poly": ("k1", "k2", "k3", "k4", "cx_offset", "cy_offset", "aspect_ratio"),
    "kannala_brandt": ("fx", "fy", "cx", "cy", "k1", "k2", "k3", "k4"),
    "unified": ("fx", "fy", "cx", "cy", "alpha"),
    "extended_unified": ("fx", "fy", "cx", "cy", "alpha", "beta"),
    "double_sphere": ("fx", "fy", "cx", "cy", "xi", "alpha"),
    "pinhole": ("fx", "fy", "cx", "cy"),
    "mei": ("fx", "fy", "cx", "cy", "xi", "k1", "k2", "p1", "p2"),
    "opencv": ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6", "s1", "s2", "s3", "s4"),
    "fov": ("fx", "fy", "cx", "cy", "w"),
    "fisheye624": ("fx", "fy", "cx", "cy", "k0", "k1", "k2", "k3", "k4", "k5", "p0", "p1", "s0", "s1", "s2", "s3"),
    "ocamcalib": ("xc", "yc", "c", "d", "e", *(f"a{i}" for i in range(OCAM_POL_LENGTH)),
                  *(f"invpol{i}" for i in range(OCAM_INVPOL_LENGTH))),
    "ftheta": ("cx", "cy", *(f"bw{i}" for i in range(1, FTHETA_POLY_LENGTH + 1)),
               *(f"fw{i}" for i in range(1, FTHETA_POLY_LENGTH + 1)), "max_angle", "c", "d", "e"),
    "carla_wide_angle": ("fov", "k0", "k1", "k2", "k3"),
}
"""Intrinsic parameter names of each model, in vector order (pixels for k of radial_poly,
fx, fy, cx, cy, cx_offset, cy_offset; radians for w of fov; dimensionless otherwise). ``ocamcalib``: OCamCalib's centre
``xc`` (row), ``yc`` (column), affine ``c, d, e``, direct polynomial ``a0 .. a7`` and inverse
polynomial ``invpol0 ..`` (zero-padded to fixed lengths); ``ftheta``: principal point, backward
polynomial ``bw1 .. bw5`` (radians per pixel^i), forward ``fw1 .. fw5``, ``max_angle`` (radians) and
the affine ``c, d, e``; ``carla_wide_angle``: the vertical ``fov`` (degrees) and ``k0 .. k3``, its
``camera_model`` being a string (`STRING_PARAMETERS`)."""

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


APPROXIMATION_PARAMETERS: dict[str, tuple[str, ...]] = {
    "ocamcalib": tuple(f"invpol{i}" for i in range(OCAM_INVPOL_LENGTH)),
    "ftheta": (*(f"fw{i}" for i in range(1, FTHETA_POLY_LENGTH + 1)), "max_angle"),
}
"""Parameters that move no projection (an approximate inverse polynomial, only the start of the exact
Newton inverse; a domain bound): `refit` and `convert_camera` hold them fixed unless a boolean mask
frees them, and conversions refill the inverse polynomials afterwards."""

STRING_PARAMETERS: dict[str, dict[str, tuple[str, ...]]] = {
    "carla_wide_angle": {"camera_model": ("perspective", "stereographic", "equidistant", "equisolid",
                                          "orthographic", "kannala-brandt")},
}
"""Non-numeric intrinsic fields of a model (static, not in the parameter vector) and their allowed
values: written beside the numbers in a calibration JSON's ``intrinsic`` object."""

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
    if model in ("mei", "double_sphere") and key == "xi" and not value > -1:
        return f"expected xi above -1 (at or below it the model sees nothing), got {value!r}"
    if model in ("unified", "extended_unified", "double_sphere") and key == "alpha" and not 0 <= value <= 1:
        return f"expected alpha in [0, 1] (outside it the model folds the image), got {value!r}"
    if model == "extended_unified" and key == "beta" and not value > 0:
        return f"expected beta above 0, got {value!r}"
    if model == "ocamcalib" and key == "a0" and value > -MIN_FOCAL_PX:
        return f"OCamCalib's a0 must be negative (at most {-MIN_FOCAL_PX:g} pixels), got {value!r}"
    if model == "ftheta" and key == "bw1" and not 0 < value <= 1 / MIN_FOCAL_PX:
        return f"the backward polynomial's slope bw1 must be in (0, {1 / MIN_FOCAL_PX:g}] radians per pixel, got {value!r}"
    if model == "ftheta" and key == "max_angle" and not 0 < value <= math.pi:
        return f"expected an angle in (0, pi] radians, got {value!r}"
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
    elif name == "pinhole":
        parts = [jnp.stack([c.fx, c.fy, c.cx, c.cy])]
    elif name == "ocamcalib":
        parts = [jnp.stack([c.xc, c.yc, c.c, c.d, c.e]), c.pol, c.invpol]
    elif name == "ftheta":
        parts = [jnp.stack([c.cx, c.cy]), c.bw, c.fw, jnp.stack([c.max_angle, c.c, c.d, c.e])]
    elif name == "carla_wide_angle":
        parts = [c.fov[None], c.k]
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
    if name == "pinhole":
        return eqx.tree_at(lambda c: (c.fx, c.fy, c.cx, c.cy), camera, tuple(vector[i] for i in range(4)))
    if name == "ocamcalib":
        n = 5 + OCAM_POL_LENGTH
        return eqx.tree_at(lambda c: (c.xc, c.yc, c.c, c.d, c.e, c.pol, c.invpol), camera,
                           (*(vector[i] for i in range(5)), vector[5:n], vector[n:]))
    if name == "ftheta":
        m = FTHETA_POLY_LENGTH
        return eqx.tree_at(lambda c: (c.cx, c.cy, c.bw, c.fw, c.max_angle, c.c, c.d, c.e), camera,
                           (vector[0], vector[1], vector[2:2 + m], vector[2 + m:2 + 2 * m],
                            *(vector[2 + 2 * m + i] for i in range(4))))
    if name == "carla_wide_angle":
        return eqx.tree_at(lambda c: (c.fov, c.k), camera, (vector[0], vector[1:5]))
    return eqx.tree_at(lambda c: (c.fx, c.fy, c.cx, c.cy, c.xi, c.alpha), camera, tuple(vector[i] for i in range(6)))


def camera_from_intrinsics(model: str, vector, *, width: int, height: int, dtype=None,
                           strings: Mapping[str, str] | None = None) -> AbstractCamera:
    """A new camera of ``model`` from an intrinsics vector (order: `parameter_names`); ``strings``
    holds its `STRING_PARAMETERS` (default: a ``carla_wide_angle`` lens is ``kannala-brandt``)."""
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
    if name == "ocamcalib":
        n = 5 + OCAM_POL_LENGTH
        return OCamCalib(v[5:n], v[n:], xc=v[0], yc=v[1], c=v[2], d=v[3], e=v[4], width=width, height=height,
                         dtype=v.dtype)
    if name == "ftheta":
        m = FTHETA_POLY_LENGTH
        return FTheta(v[0], v[1], v[2:2 + m], v[2 + m:2 + 2 * m], max_angle=v[2 + 2 * m], c=v[3 + 2 * m],
                      d=v[4 + 2 * m], e=v[5 + 2 * m], width=width, height=height, dtype=v.dtype)
    if name == "carla_wide_angle":
        lens = dict(strings or {}).get("camera_model", "kannala-brandt")
        return CarlaWideAngle(lens, v[0], v[1:5], width=width, height=height, dtype=v.dtype)
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
    for key in STRING_PARAMETERS.get(name, {}):
        out[key] = getattr(camera, key)
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
    strings = {}
    for key, allowed in STRING_PARAMETERS.get(name, {}).items():
        val = data.get(key)
        if not isinstance(val, str) or val.strip().lower().replace("_", "-") not in allowed:
            shown = "missing" if key not in data else f"expected one of {', '.join(allowed)}, got {val!r}"
            raise ValueError(f"{source}: field 'intrinsic.{key}': {shown} (model {name})")
        strings[key] = val.strip().lower().replace("_", "-")
        keys.add(key)
    keys_numeric = keys - set(strings)
    for key in sorted(keys - {"poly_order"}):
        if key not in data:
            raise ValueError(f"{source}: field 'intrinsic.{key}': missing (model {name})")
    extra = sorted(set(data) - keys)
    if extra:
        raise ValueError(f"{source}: field 'intrinsic.{extra[0]}': unexpected key for model {name}")
    values = {}
    for key in keys_numeric - {"model"}:
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
    try:
        camera = camera_from_intrinsics(name, vec, width=int(values["width"]), height=int(values["height"]),
                                        dtype=dtype, strings=strings)
    except ValueError as e:  # a domain rule of the model (`parameter_problem`) that the checks above do not name
        raise ValueError(f"{source}: field 'intrinsic': {e}") from None
    problem = getattr(camera, "fov_problem", lambda: None)()
    if problem is not None:
        raise ValueError(f"{source}: field 'intrinsic.fov': {problem}")
    return camera
