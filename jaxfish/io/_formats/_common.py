"""What every interop format shares: the model mapping tables (data keyed by jaxfish model key
and parameter names), number checks that name the file and field, and the calibration dicts the
readers produce (`camera_calibration_from_dict`'s JSON form)."""

from __future__ import annotations

import dataclasses
import math
import reprlib
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np

from ..._errors import CalibrationError
from ...refit._parameters import MODEL_CLASSES, PARAMETER_NAMES

_REPR = reprlib.Repr()
_REPR.maxlevel, _REPR.maxlist, _REPR.maxdict, _REPR.maxstring, _REPR.maxother = 2, 6, 4, 60, 60


def short(value: Any) -> str:
    """A bounded ``repr`` for messages: a hostile file's value may be huge (YAML aliases nest a
    small text into billions of items); reprlib never walks more than a few of them."""
    return _REPR.repr(value)


def fail(source: str, field: str, message: str) -> CalibrationError:
    """``CalibrationError("{source}: field '{field}': {message}")``."""
    return CalibrationError(f"{source}: field '{field}': {message}")


def number(value: Any, source: str, field: str) -> float:
    """A finite number (int or float, not bool; a numeric string from a text format too)."""
    if isinstance(value, str):
        try:
            value = float(value)
        except ValueError:
            raise fail(source, field, f"expected a number, got {short(value)}") from None
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise fail(source, field, f"expected a number, got {type(value).__name__} {short(value)}")
    try:
        out = float(value)
    except OverflowError:
        out = math.inf
    if not math.isfinite(out):
        raise fail(source, field, f"expected a finite number, got {short(value)}" if isinstance(value, float)
                   else "expected a finite number")
    return out


def numbers(value: Any, source: str, field: str, n: int | Sequence[int] | None = None) -> list[float]:
    """A list of finite numbers, of length ``n`` (or one of several lengths) when given."""
    if not isinstance(value, (list, tuple)):
        raise fail(source, field, f"expected a list of numbers, got {type(value).__name__}")
    if n is not None:
        allowed = (n,) if isinstance(n, int) else tuple(n)
        if len(value) not in allowed:
            want = " or ".join(str(a) for a in allowed)
            raise fail(source, field, f"expected {want} numbers, got {len(value)}")
    return [number(x, source, f"{field}[{i}]") for i, x in enumerate(value)]


def whole(value: Any, source: str, field: str) -> int:
    """A positive whole number (image sides)."""
    x = number(value, source, field)
    if x <= 0 or x != int(x):
        raise fail(source, field, f"expected a positive whole number, got {short(value)}")
    return int(x)


def mapping(value: Any, source: str, field: str) -> Mapping[str, Any]:
    if not isinstance(value, Mapping):
        raise fail(source, field, f"expected a mapping, got {type(value).__name__}")
    return value


def require(obj: Mapping[str, Any], key: str, source: str, where: str) -> Any:
    if key not in obj:
        raise fail(source, f"{where}.{key}" if where else key, "missing")
    return obj[key]


@dataclasses.dataclass(frozen=True)
class ModelMapping:
    """One lens model of a tool and the jaxfish model it is.

    - `tool`: the tool's name of the model (``"OPENCV_FISHEYE"``, ``"kb4"``, ``("pinhole", "radtan")``);
    - `model`: the jaxfish model key (`jaxfish.refit.MODEL_CLASSES`);
    - `params`: the tool's parameters in its order, each a jaxfish parameter name of `model`;
      ``"fx|fy"`` is one value for both (COLMAP's single focal length), which a camera is written
      with only when ``fx == fy``. jaxfish parameters the tool lacks are 0 on reading and must be 0
      (exactly) for a camera to be written with this mapping;
    - `decode` / `encode`: optional maps between the tool's parameter values (keyed by the names
      in `params`) and jaxfish's, for a tool whose parameterisation differs (kalibr's omni without
      distortion is the unified model with ``alpha = xi / (1 + xi)``); `encode` returns None when
      the camera has no exact equivalent.
    """

    tool: Any
    model: str
    params: tuple[str, ...]
    decode: Callable[[dict[str, float]], dict[str, float]] | None = None
    encode: Callable[[dict[str, float]], dict[str, float] | None] | None = None

    @property
    def available(self) -> bool:
        """Whether this jaxfish has the model (models are added over time)."""
        return self.model in MODEL_CLASSES

    def read(self, values: Sequence[float], source: str, field: str) -> dict[str, float]:
        """The jaxfish parameters (every name of the model) from the tool's values."""
        if not self.available:
            raise fail(source, field, f"{_tool_name(self.tool)} is jaxfish's lens model {short(self.model)}, which this "
                       f"version of jaxfish does not have (models: {', '.join(sorted(MODEL_CLASSES))})")
        if len(values) != len(self.params):
            raise fail(source, field, f"{_tool_name(self.tool)} has {len(self.params)} parameters "
                       f"({', '.join(self.params)}), got {len(values)}")
        tool_values = dict(zip(self.params, (float(v) for v in values), strict=True))
        if self.decode is not None:
            tool_values = self.decode(tool_values)
        out = {n: 0.0 for n in PARAMETER_NAMES[self.model]}
        for spec, v in tool_values.items():
            for n in spec.split("|"):
                out[n] = v
        return out

    def write(self, params: Mapping[str, float]) -> list[float] | None:
        """The tool's values of a camera with jaxfish parameters ``params``, or None when this
        mapping cannot hold it exactly (another model, a parameter the tool lacks not 0, ``fx != fy``
        for a single focal length)."""
        if not self.available or set(params) != set(PARAMETER_NAMES[self.model]):
            return None
        p = dict(params)
        if self.encode is not None:
            enc = self.encode(p)
            if enc is None:
                return None
            return [float(enc[s]) for s in self.params]
        used = {n for spec in self.params for n in spec.split("|")}
        if any(p[n] != 0.0 for n in p if n not in used):
            return None
        out = []
        for spec in self.params:
            names = spec.split("|")
            if any(p[n] != p[names[0]] for n in names):
                return None
            out.append(p[names[0]])
        return out


def _tool_name(tool: Any) -> str:
    return "-".join(tool) if isinstance(tool, tuple) else str(tool)


def find_reader(table: Sequence[ModelMapping], tool: Any) -> ModelMapping | None:
    """The mapping that reads ``tool``'s model: the first available one, else the first one (whose
    `read` then names the missing jaxfish model); None for a model the table lacks."""
    rows = [m for m in table if m.tool == tool]
    for m in rows:
        if m.available:
            return m
    return rows[0] if rows else None


def find_writer(table: Sequence[ModelMapping], model: str, params: Mapping[str, float]
                ) -> tuple[ModelMapping, list[float]] | None:
    """The first mapping that writes a jaxfish camera of ``model`` exactly, with its values."""
    for m in table:
        if m.model == model:
            values = m.write(params)
            if values is not None:
                return m, values
    return None


def writable_models(table: Sequence[ModelMapping]) -> tuple[str, ...]:
    """jaxfish models (available in this version) that a table writes, in its order."""
    out: list[str] = []
    for m in table:
        if m.available and m.model not in out:
            out.append(m.model)
    return tuple(out)


@dataclasses.dataclass
class CameraRecord:
    """One camera as every format reader returns it and every writer takes it: jaxfish model key
    and parameters (`PARAMETER_NAMES` order, jaxfish's pixel-centre convention), image size, the
    4x4 OpenCV camera -> vehicle matrix, and `where` (the file's field of this camera, for errors)."""

    name: str
    model: str
    params: dict[str, float]
    width: int
    height: int
    camera_to_vehicle: np.ndarray
    where: str = ""
    strings: dict[str, str] = dataclasses.field(default_factory=dict)
    """The model's non-numeric intrinsic fields (`jaxfish.refit` ``STRING_PARAMETERS``: CARLA's
    ``camera_model``)."""

    def to_dict(self) -> dict[str, Any]:
        """The jaxfish calibration JSON object of this camera."""
        out = calibration_dict(self.name, self.model, self.params, self.width, self.height, self.camera_to_vehicle)
        out["intrinsic"].update(self.strings)
        return out


def calibration_dict(name: str, model: str, params: Mapping[str, float], width: int, height: int,
                     camera_to_vehicle: np.ndarray) -> dict[str, Any]:
    """The jaxfish calibration JSON object (read by `camera_calibration_from_dict`) of one camera;
    ``camera_to_vehicle`` is a 4x4 matrix (OpenCV camera -> vehicle)."""
    m = np.asarray(camera_to_vehicle, dtype=np.float64)
    rot = m[:3, :3]
    u, _, vt = np.linalg.svd(rot)  # the nearest rotation: files hold rounded matrices
    rot = u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt
    q = quaternion_xyzw(rot)
    intr: dict[str, Any] = {"model": model, "width": float(width), "height": float(height)}
    intr.update({k: float(v) for k, v in params.items()})
    return {"name": name, "extrinsic": {"quaternion": [float(x) for x in q], "translation": [float(x) for x in m[:3, 3]]},
            "intrinsic": intr}


def rigid_matrix(value: Any, source: str, field: str) -> np.ndarray:
    """A 4x4 rigid transform given as 4 rows of 4 numbers (the last row 0 0 0 1) or 16 numbers."""
    if isinstance(value, (list, tuple)) and len(value) == 4 and all(isinstance(r, (list, tuple)) for r in value):
        rows = [numbers(r, source, f"{field}[{i}]", 4) for i, r in enumerate(value)]
        m = np.asarray(rows)
    else:
        m = np.asarray(numbers(value, source, field, 16)).reshape(4, 4)
    if not np.allclose(m[3], [0, 0, 0, 1], atol=1e-9):
        raise fail(source, field, f"expected a rigid transform whose last row is [0, 0, 0, 1], got {m[3].tolist()}")
    rot = m[:3, :3]
    err = float(np.abs(rot @ rot.T - np.eye(3)).max())
    if err > 1e-4 or np.linalg.det(rot) < 0:
        raise fail(source, field, f"expected a rotation in the upper-left 3x3 block (R Rᵀ = I, det +1), off by {err:.3g}")
    return m




def rodrigues(omega: np.ndarray) -> np.ndarray:
    """The rotation matrix of a rotation vector (radians), in float64 NumPy."""
    omega = np.asarray(omega, dtype=np.float64)
    theta = float(np.linalg.norm(omega))
    k = np.array([[0.0, -omega[2], omega[1]], [omega[2], 0.0, -omega[0]], [-omega[1], omega[0], 0.0]])
    if theta < 1e-12:
        return np.eye(3) + k
    return np.eye(3) + math.sin(theta) / theta * k + (1 - math.cos(theta)) / theta**2 * (k @ k)


def file_stem(name: str, what: str) -> str:
    """A camera name used as a file name (``NAME.yaml``, ``NAME.json``): refused when it holds a
    path separator, NUL or a line break, or is ``.`` / ``..`` (it would write outside the folder)."""
    if not name or name in (".", "..") or any(ch in name for ch in "/\\\0\n\r"):
        raise CalibrationError(f"{what}: camera name {short(name)} cannot be a file name (no '/', '\\', NUL, line breaks, "
                               "'.' or '..')")
    return name


def string_parameters(model: str) -> tuple[str, ...]:
    """The non-numeric intrinsic fields of a model (none for most)."""
    from ...refit import _parameters

    return tuple(getattr(_parameters, "STRING_PARAMETERS", {}).get(model, {}))


def quaternion_xyzw(rot: np.ndarray) -> np.ndarray:
    """The unit quaternion ``(x, y, z, w)``, ``w >= 0``, of a rotation matrix, in float64 NumPy
    (Shepperd's method: the largest of the four squared components is taken first)."""
    r = np.asarray(rot, dtype=np.float64)
    tr = r[0, 0] + r[1, 1] + r[2, 2]
    cand = np.array([tr, r[0, 0], r[1, 1], r[2, 2]])
    k = int(np.argmax(cand))
    if k == 0:
        w = math.sqrt(max(1.0 + tr, 0.0)) / 2
        q = np.array([(r[2, 1] - r[1, 2]) / (4 * w), (r[0, 2] - r[2, 0]) / (4 * w), (r[1, 0] - r[0, 1]) / (4 * w), w])
    elif k == 1:
        x = math.sqrt(max(1.0 + r[0, 0] - r[1, 1] - r[2, 2], 0.0)) / 2
        q = np.array([x, (r[0, 1] + r[1, 0]) / (4 * x), (r[0, 2] + r[2, 0]) / (4 * x), (r[2, 1] - r[1, 2]) / (4 * x)])
    elif k == 2:
        y = math.sqrt(max(1.0 - r[0, 0] + r[1, 1] - r[2, 2], 0.0)) / 2
        q = np.array([(r[0, 1] + r[1, 0]) / (4 * y), y, (r[1, 2] + r[2, 1]) / (4 * y), (r[0, 2] - r[2, 0]) / (4 * y)])
    else:
        z = math.sqrt(max(1.0 - r[0, 0] - r[1, 1] + r[2, 2], 0.0)) / 2
        q = np.array([(r[0, 2] + r[2, 0]) / (4 * z), (r[1, 2] + r[2, 1]) / (4 * z), z, (r[1, 0] - r[0, 1]) / (4 * z)])
    q = q / np.linalg.norm(q)
    return -q if q[3] < 0 else q


def quaternion_matrix(q_xyzw) -> np.ndarray:
    """The rotation matrix of a quaternion ``(x, y, z, w)`` (normalised first), float64 NumPy."""
    x, y, z, w = np.asarray(q_xyzw, dtype=np.float64) / np.linalg.norm(np.asarray(q_xyzw, dtype=np.float64))
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def rigid_inverse(m: np.ndarray) -> np.ndarray:
    """The inverse of a 4x4 rigid transform (``Rᵀ``, ``-Rᵀ t``)."""
    m = np.asarray(m, dtype=np.float64)
    out = np.eye(4)
    out[:3, :3] = m[:3, :3].T
    out[:3, 3] = -m[:3, :3].T @ m[:3, 3]
    return out
