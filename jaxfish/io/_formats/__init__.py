"""Calibration files of other tools: kalibr camchain YAML, COLMAP ``cameras.txt`` +
``images.txt``, OpenCV FileStorage YAML, basalt calibration JSON and CARLA sensor blueprints
(edge I/O, not jitted).

Every format goes through jaxfish's calibration JSON form (`camera_calibration_from_dict`), and
each format's models are a table (`ModelMapping`: the tool's model and parameter order <-> a
jaxfish model key and parameter names), so a lens model added to `jaxfish.refit.MODEL_CLASSES`
is read and written as soon as a table names it. See ``docs/interop.md``.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ..._errors import CalibrationError
from ...calibration import Calibration
from ...refit._parameters import PARAMETER_NAMES, canonical_model_name, intrinsics_to_dict
from .._atomic import atomic_write_text
from .._calibration_json import load_calibration as load_woodscape_calibration
from .._correspondences import camera_calibration_from_dict
from .._json import read_json, regular_file, to_json_text
from . import _basalt, _carla, _colmap, _kalibr, _opencv
from ._common import CameraRecord, ModelMapping, file_stem, short, string_parameters, writable_models

CALIBRATION_FORMATS: tuple[str, ...] = ("jaxfish", "kalibr", "colmap", "opencv", "basalt", "carla")
"""Calibration file formats jaxfish reads (``jaxfish`` is its own calibration JSON)."""
EXPORT_FORMATS: tuple[str, ...] = ("kalibr", "colmap", "opencv", "basalt", "carla")
"""Formats `export_calibrations` writes."""

MODEL_TABLES: dict[str, tuple[ModelMapping, ...]] = {
    "kalibr": _kalibr.KALIBR_MODELS, "colmap": _colmap.COLMAP_MODELS, "opencv": _opencv.OPENCV_MODELS,
    "basalt": _basalt.BASALT_MODELS,
}
"""Each format's model table (CARLA's two cameras are in its module)."""

MAX_FILE_BYTES = 64 * 1024 * 1024
"""Largest calibration file read (a calibration is a few kB; a YAML or text parse of more is a mistake)."""

__all__ = ["CALIBRATION_FORMATS", "EXPORT_FORMATS", "MODEL_TABLES", "CameraRecord", "ModelMapping",
           "detect_calibration_format", "export_calibrations", "format_models", "read_calibration_file"]


def format_models(fmt: str) -> tuple[str, ...]:
    """The jaxfish lens models (of this version) that format ``fmt`` holds exactly."""
    if fmt == "carla":
        return tuple(m for m in ("pinhole", "carla_wide_angle") if m in PARAMETER_NAMES)
    return writable_models(MODEL_TABLES[fmt])


def _text(path: Path) -> str:
    path = regular_file(path, CalibrationError)
    size = path.stat().st_size
    if size > MAX_FILE_BYTES:
        raise CalibrationError(f"{path}: {size} bytes, more than a calibration file holds ({MAX_FILE_BYTES} at most)")
    try:
        return path.read_bytes().decode("utf-8")
    except UnicodeDecodeError as e:
        raise CalibrationError(f"{path}: not a UTF-8 text file ({e})") from None


def _yaml(path: Path, text: str) -> Any:
    import yaml

    class Loader(yaml.SafeLoader):
        pass

    def matrix(loader, node):
        return loader.construct_mapping(node, deep=True)

    for tag in ("tag:yaml.org,2002:opencv-matrix", "tag:yaml.org,2002:opencv-nd-matrix"):
        Loader.add_constructor(tag, matrix)
    lines = text.splitlines()
    if lines and lines[0].startswith("%YAML:"):  # OpenCV's directive (not YAML's "%YAML 1.x")
        lines[0] = ""
    try:
        return yaml.load("\n".join(lines), Loader=Loader)  # noqa: S506 (a SafeLoader subclass)
    except yaml.MarkedYAMLError as e:
        mark = e.problem_mark
        where = f" at line {mark.line + 1} column {mark.column + 1}" if mark is not None else ""
        raise CalibrationError(f"{path}: field '<yaml>': malformed YAML{where}: {e.problem or e}") from None
    except (yaml.YAMLError, RecursionError) as e:
        raise CalibrationError(f"{path}: field '<yaml>': malformed YAML: {e}") from None


def detect_calibration_format(path: str | os.PathLike) -> str:
    """The format of a calibration file (one of `CALIBRATION_FORMATS`), from its name and content:
    a folder holding ``cameras.txt`` or a ``.txt`` file is COLMAP; YAML with ``cam0`` is kalibr,
    other YAML OpenCV; JSON with ``value0`` is basalt, with ``sensors`` or ``attributes`` CARLA,
    other JSON (and anything else) jaxfish's own."""
    path = Path(path)
    if path.is_dir():
        return "colmap" if (path / "cameras.txt").exists() else "jaxfish"  # jaxfish's reader names the folder
    if not path.is_file():
        return "jaxfish"  # jaxfish's reader names a missing path or one that is not a regular file
    suffix = path.suffix.lower()
    if suffix == ".txt":
        return "colmap"
    if suffix == ".json":
        data = read_json(path, CalibrationError)
        return _json_format(data)
    text = _text(path)
    if suffix not in (".yaml", ".yml") and text.lstrip().startswith("{"):
        return _json_format(read_json(path, CalibrationError))
    data = _yaml(path, text)
    return "kalibr" if isinstance(data, dict) and "cam0" in data else "opencv"


def _json_format(data: Any) -> str:
    if isinstance(data, dict):
        if "value0" in data:
            return "basalt"
        if "sensors" in data or "attributes" in data or "blueprint" in data:
            return "carla"
    return "jaxfish"


def read_calibration_file(path: str | os.PathLike, *, dtype=None, fmt: str | None = None) -> list[Calibration]:
    """Every camera of a calibration file of any format (`detect_calibration_format`), in file
    order, as `Calibration` objects of jaxfish lens models. Problems raise `CalibrationError`
    naming the file and field (a model this jaxfish does not have included)."""
    path = Path(path)
    fmt = detect_calibration_format(path) if fmt is None else fmt
    if fmt == "jaxfish":
        return [camera_calibration_from_dict(read_json(path, CalibrationError), source=str(path), dtype=dtype)]
    records = _read_records(path, fmt)
    out = []
    for r in records:
        source = f"{path} ({r.where})" if len(records) > 1 or r.where not in ("", "<root>") else str(path)
        out.append(camera_calibration_from_dict(r.to_dict(), source=source, dtype=dtype))
    return out


def read_calibration_paths(paths: Sequence[str | os.PathLike], *, dtype=None) -> list[Calibration]:
    """Every camera of several calibration paths, in order: files of any format (all their
    cameras; ``PATH::NAME`` one of them), COLMAP folders, and folders of jaxfish calibration JSON
    files (a rig folder: its ``*.json`` in name order). Camera names must differ."""
    out: list[Calibration] = []
    for p in paths:
        path = Path(p)
        if "::" in os.fspath(p) and not path.exists():
            out.append(load_camera_calibration(p, dtype=dtype))
        elif path.is_dir() and not (path / "cameras.txt").exists():
            files = sorted(f for f in path.iterdir() if f.suffix.lower() == ".json")
            if not files:
                raise CalibrationError(f"{path}: a folder with neither calibration JSON files nor cameras.txt")
            for f in files:
                out.extend(read_calibration_file(f, dtype=dtype))
        else:
            out.extend(read_calibration_file(path, dtype=dtype))
    names = [c.name for c in out]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise CalibrationError(f"two cameras are named {short(dup[0])} (in {', '.join(os.fspath(p) for p in paths)}): "
                               "camera names must differ")
    return out


def load_camera_calibration(path: str | os.PathLike, *, dtype=None, camera: str | None = None) -> Calibration:
    """Read a calibration of any lens model: jaxfish's calibration JSON (WoodScape ``radial_poly``
    files included) or another tool's file (kalibr camchain YAML, COLMAP ``cameras.txt`` or its
    folder, OpenCV FileStorage YAML, basalt JSON, CARLA sensor JSON: ``docs/interop.md``), told
    apart by name and content. A file of several cameras needs ``camera`` (a name, or an index
    such as ``"0"``) unless it holds one; ``PATH::NAME`` (a path that does not exist as written)
    names it too, so that every command-line calibration argument can pick a camera."""
    text = os.fspath(path)
    if camera is None and "::" in text and not Path(text).exists():
        text, camera = text.rsplit("::", 1)
    path = Path(text)
    fmt = detect_calibration_format(path)
    if fmt == "jaxfish":  # one camera: ``camera`` must name it (its name or index 0) when given
        calib = camera_calibration_from_dict(read_json(path, CalibrationError), source=str(path), dtype=dtype)
        return select_camera([calib], path, camera)
    return select_camera(read_calibration_file(path, dtype=dtype, fmt=fmt), path, camera)


def load_calibration(path: str | os.PathLike, *, apply_errata: bool = False, dtype=None) -> Calibration:
    """Load a WoodScape or SynWoodScape calibration JSON file.

    - WoodScape files (key ``"translation"``) are in the ISO 8855 vehicle frame.
    - SynWoodScape files (key ``"translation used in CARLA (CARLA reference)"``) store the
      translation in CARLA's frame (y right); it is converted to ISO 8855 (y flipped) so that
      `Calibration.camera_to_vehicle` is consistent; the quaternion is used as is.
    - ``apply_errata=True`` (SynWoodScape files only) replaces the published translation with the
      dataset author's correction (`SYNWOODSCAPE_CORRECTED_TRANSLATIONS_CARLA`, WoodScape issue
      #113): the published MVL/MVR translations are wrong. Other fixes: `eqx.tree_at` on the result.

    Raises `FileNotFoundError` for a missing file and `CalibrationError` (a `ValueError`) naming
    the file and field for anything malformed, and naming the path when it is not a regular file
    (a directory, a FIFO, a symbolic link loop).

    Another tool's calibration file (kalibr, COLMAP, OpenCV, basalt, CARLA: ``docs/interop.md``)
    is read as `load_camera_calibration` reads it (its one camera, or ``PATH::NAME``'s, of any
    lens model).
    """
    if ("::" in os.fspath(path) and not Path(path).exists()) or detect_calibration_format(path) != "jaxfish":
        return load_camera_calibration(path, dtype=dtype)
    return load_woodscape_calibration(path, apply_errata=apply_errata, dtype=dtype)


def select_camera(calibs: list[Calibration], path: Path, camera: str | None) -> Calibration:
    """One calibration of a file's cameras: by name, by index, or the only one."""
    names = [c.name for c in calibs]
    if camera is None:
        if len(calibs) == 1:
            return calibs[0]
        raise CalibrationError(f"{path}: holds {len(calibs)} cameras ({', '.join(names)}); say which one "
                               f"({path}::NAME)")
    if camera in names:
        return calibs[names.index(camera)]
    if camera.isascii() and camera.isdigit() and int(camera) < len(calibs):
        return calibs[int(camera)]
    raise CalibrationError(f"{path}: no camera {camera!r} (cameras: {', '.join(names)})")

def _read_records(path: Path, fmt: str) -> list[CameraRecord]:
    if fmt == "colmap":
        cameras = path / "cameras.txt" if path.is_dir() else path
        images = cameras.with_name("images.txt")
        _text(cameras)  # the regular-file, size and UTF-8 checks
        if images.exists():
            _text(images)
        return _colmap.read(cameras, images if images != cameras else None)
    if fmt in ("basalt", "carla"):
        data = read_json(path, CalibrationError)
        return (_basalt if fmt == "basalt" else _carla).read(data, str(path))
    if fmt in ("kalibr", "opencv"):
        data = _yaml(path, _text(path))
        if fmt == "kalibr":
            return _kalibr.read(data, str(path))
        return _opencv.read(data, str(path), path.stem)
    raise ValueError(f"unknown calibration format {short(fmt)} (known: {', '.join(CALIBRATION_FORMATS)})")


def record_of(calib: Calibration) -> CameraRecord:
    """A `Calibration` as the formats' camera record (float64)."""
    intr = intrinsics_to_dict(calib.camera)
    model = canonical_model_name(calib.camera)
    params = {k: float(intr[k]) for k in PARAMETER_NAMES[model]}
    strings = {k: str(intr[k]) for k in string_parameters(model) if k in intr}
    m = np.asarray(calib.camera_to_vehicle.as_matrix(), dtype=np.float64)
    return CameraRecord(calib.name, model, params, int(calib.camera.width), int(calib.camera.height), m,
                        strings=strings)


def holds_exactly(fmt: str, calib: Calibration) -> bool:
    """Whether format ``fmt`` holds this calibration's camera exactly (same model and parameters)."""
    r = record_of(calib)
    if fmt == "carla":
        return _carla.writable(r)
    from ._common import find_writer

    return find_writer(MODEL_TABLES[fmt], r.model, r.params) is not None


def export_calibrations(calibs: Sequence[Calibration], fmt: str, out: str | os.PathLike) -> list[Path]:
    """Write calibrations in format ``fmt`` (`EXPORT_FORMATS`), atomically; every camera must be one
    the format holds exactly (`holds_exactly`; convert it first otherwise). ``out``: the file
    (kalibr YAML, basalt JSON, CARLA JSON; OpenCV YAML for one camera) or a folder (COLMAP's
    ``cameras.txt``, ``images.txt`` and an empty ``points3D.txt``; OpenCV: ``NAME.yaml`` per
    camera when there are several). Returns the paths written."""
    out = Path(out)
    check_export_names([c.name for c in calibs], fmt, out)
    records = [record_of(c) for c in calibs]
    for c in calibs:
        if not holds_exactly(fmt, c):
            raise ValueError(f"export: {fmt} cannot hold camera {short(c.name)} ({canonical_model_name(c.camera)}) exactly; "
                             "convert it first")
    if fmt == "kalibr":
        import yaml

        text = yaml.safe_dump(_kalibr.write(records), sort_keys=False, default_flow_style=None, width=1000)
        return [_write(out, text)]
    if fmt in ("basalt", "carla"):
        data = (_basalt if fmt == "basalt" else _carla).write(records)
        return [_write(out, to_json_text(out, data, indent=2, error=CalibrationError))]
    if fmt == "colmap":
        cams, imgs = _colmap.write(records)
        out.mkdir(parents=True, exist_ok=True)
        return [_write(out / "cameras.txt", cams), _write(out / "images.txt", imgs),
                _write(out / "points3D.txt", "# 3D point list (empty: jaxfish exports cameras and poses only)\n")]
    if fmt == "opencv":
        if len(records) == 1 and not out.is_dir():
            return [_write(out, _opencv.write(records[0]))]
        out.mkdir(parents=True, exist_ok=True)
        return [_write(out / f"{r.name}.yaml", _opencv.write(r)) for r in records]
    raise ValueError(f"unknown export format {short(fmt)} (known: {', '.join(EXPORT_FORMATS)})")


def check_export_names(names: Sequence[str], fmt: str, out: str | os.PathLike) -> None:
    """Refuse camera names a format cannot carry (`CalibrationError`): a COLMAP image name
    ``NAME.png`` with white space or ``/``, an OpenCV ``NAME.yaml`` of several cameras that would
    leave the folder (``/``, ``..``)."""
    for name in names:
        if fmt == "colmap" and (not name or any(ch.isspace() for ch in name) or "/" in name):
            raise CalibrationError(f"export to {out}: camera name {short(name)} cannot be a COLMAP image name "
                                   "(NAME.png: no spaces, line breaks or '/')")
        if fmt == "opencv" and len(names) > 1:
            file_stem(name, f"export to {out}")


def _write(path: Path, text: str) -> Path:
    atomic_write_text(path, text)
    return path




def format_free_parameters(fmt: str, model: str) -> tuple[str, ...] | None:
    """The parameters of jaxfish ``model`` that format ``fmt`` can hold (the others must be 0), or
    None when the format does not hold the model."""
    if fmt == "carla":
        return PARAMETER_NAMES[model] if model in format_models("carla") else None
    rows = [m for m in MODEL_TABLES[fmt] if m.model == model and m.available]
    if not rows:
        return None
    used = {n for m in rows for spec in (m.params if m.encode is None else PARAMETER_NAMES[model]) for n in spec.split("|")}
    return tuple(n for n in PARAMETER_NAMES[model] if n in used)
