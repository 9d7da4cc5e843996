"""One JSON reader for every input file (each way a file can fail names the file) and one strict
JSON writer (no NaN or infinity ever reaches a file)."""

from __future__ import annotations

import json
import math
import os
import re
from pathlib import Path
from typing import Any

from .._errors import JaxfishError


def read_json(path: Path, error: type[Exception], *, obj: bool = False) -> Any:
    """The parsed JSON of ``path``; ``error(message naming the file)`` for a file that is not UTF-8,
    not JSON, nested too deeply to parse, or (``obj=True``) whose root is not an object.
    A missing file raises `FileNotFoundError` naming it."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: file not found")
    try:
        data = json.loads(path.read_bytes().decode("utf-8"))
    except UnicodeDecodeError as e:
        raise error(f"{path}: not a UTF-8 text file ({e})") from None
    except json.JSONDecodeError as e:
        raise error(f"{path}: invalid JSON at line {e.lineno} column {e.colno}: {e.msg}") from None
    except RecursionError:
        raise error(f"{path}: JSON nested too deeply to read") from None
    if obj and not isinstance(data, dict):
        raise error(f"{path}: expected a JSON object at the top level, got {type(data).__name__}")
    return data


def non_finite_field(data: Any, where: str = "") -> str | None:
    """The dotted path (``a.b[2]``) of the first float in ``data`` (dicts, lists, tuples) that is
    NaN or infinite, ``<root>`` when ``data`` itself is; None when every number is finite."""
    if isinstance(data, float):
        return None if math.isfinite(data) else (where or "<root>")
    if isinstance(data, dict):
        for key, value in data.items():
            found = non_finite_field(value, f"{where}.{key}" if where else str(key))
            if found is not None:
                return found
    elif isinstance(data, (list, tuple)):
        for i, value in enumerate(data):
            found = non_finite_field(value, f"{where}[{i}]")
            if found is not None:
                return found
    return None


def to_json_text(path: str | os.PathLike, data: Any, *, indent: int | None = None, error: type[Exception] = JaxfishError,
              **options: Any) -> str:
    """The JSON text of ``data`` for the file ``path`` (strict JSON: ``allow_nan=False``, one
    trailing newline); a NaN or infinite number raises ``error`` naming the file and the field
    (JSON has no literal for them, and a reader would take ``NaN`` for a number)."""
    field = non_finite_field(data)
    if field is not None:
        raise error(f"{path}: not written: field '{field}' is not a finite number ({_value_at(data, field)!r})")
    return json.dumps(data, indent=indent, allow_nan=False, **options) + "\n"


def _value_at(data: Any, field: str) -> Any:
    for part in re.findall(r"[^.\[\]]+|\[\d+\]", field):
        if part == "<root>":
            return data
        data = data[int(part[1:-1])] if part.startswith("[") else data[part]
    return data


def write_json(path: str | os.PathLike, data: Any, *, indent: int | None = 2, error: type[Exception] = JaxfishError,
               **options: Any) -> Path:
    """Write ``data`` as strict JSON to ``path``, atomically (`to_json_text`): a NaN or infinite
    number raises ``error`` naming the file and the field, and nothing is written."""
    from ._atomic import atomic_write_text

    return atomic_write_text(path, to_json_text(path, data, indent=indent, error=error, **options))
