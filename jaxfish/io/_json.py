"""One JSON reader for every input file (each way a file can fail names the file) and one strict
JSON writer (no NaN or infinity ever reaches a file)."""

from __future__ import annotations

import errno
import json
import math
import os
import re
import stat
import sys
from pathlib import Path
from typing import Any

from .._errors import JaxfishError

_FLOAT_MAX = sys.float_info.max
_KINDS = ((stat.S_ISFIFO, "a FIFO (named pipe)"), (stat.S_ISSOCK, "a socket"), (stat.S_ISCHR, "a character device"),
          (stat.S_ISBLK, "a block device"))


def regular_file(path: str | os.PathLike, error: type[Exception], what: str = "file") -> Path:
    """``path`` as a `Path` when it is a regular file (or a symbolic link to one), checked without
    opening it: a FIFO or a device would block or never end a read. A missing path (or a broken
    symbolic link) raises `FileNotFoundError` naming it; a directory, a FIFO, a socket, a device, a
    symbolic link loop or an unreadable parent raises ``error`` naming it and what it is."""
    path = Path(path)
    try:
        st = os.stat(path)
    except FileNotFoundError:
        broken = os.path.islink(path)
        raise FileNotFoundError(f"{path}: {what} not found" + (" (a broken symbolic link)" if broken else "")) from None
    except OSError as e:  # ELOOP (a symbolic link loop), EACCES, ENAMETOOLONG, ENOTDIR, ...
        if e.errno == errno.ENOTDIR:
            raise FileNotFoundError(f"{path}: {what} not found (a parent is not a directory)") from None
        raise error(f"{path}: cannot read the {what} ({e.strerror})") from None
    if stat.S_ISDIR(st.st_mode):
        raise error(f"{path}: is a directory, expected a {what}")
    if not stat.S_ISREG(st.st_mode):
        kind = next((name for test, name in _KINDS if test(st.st_mode)), "not a regular file")
        raise error(f"{path}: is {kind}, expected a regular {what}")
    return path


class _HugeInt:
    """An integer literal too long for Python's int-string conversion limit (4300 digits)."""

    def __init__(self, text: str):
        self.digits = len(text.lstrip("-"))


def _parse_int(text: str) -> int | _HugeInt:
    try:
        return int(text)
    except ValueError:  # "Exceeds the limit (4300 digits) for integer string conversion"
        return _HugeInt(text)


def _parse_float(text: str) -> float:
    value = float(text)
    return _OutOfRange(text) if math.isinf(value) else value  # type: ignore[return-value]


class _OutOfRange:
    """A number literal whose magnitude exceeds the largest float (e.g. ``1e400``)."""

    def __init__(self, text: str):
        self.text = text


def _field(keys: list[Any]) -> str:
    out = ""
    for k in keys:
        out += f"[{k}]" if isinstance(k, int) else (f".{k}" if out else str(k))
    return out or "<root>"


def _out_of_range(data: Any) -> tuple[list[Any], str] | None:
    """The field path and a description of the first number beyond the float range, if any."""
    stack: list[tuple[list[Any], Any]] = [([], data)]
    while stack:
        keys, value = stack.pop()
        if isinstance(value, dict):
            stack.extend((keys + [k], v) for k, v in reversed(list(value.items())))
        elif isinstance(value, list):
            stack.extend((keys + [i], v) for i, v in reversed(list(enumerate(value))))
        elif isinstance(value, _HugeInt):
            return keys, f"an integer of {value.digits} digits"
        elif isinstance(value, _OutOfRange):
            return keys, f"{value.text[:40]}{'...' if len(value.text) > 40 else ''}"
        elif isinstance(value, int) and not isinstance(value, bool) and abs(value) > _FLOAT_MAX:
            text = str(value)
            return keys, f"an integer of {len(text.lstrip('-'))} digits"
    return None


def read_json(path: Path, error: type[Exception], *, obj: bool = False) -> Any:
    """The parsed JSON of ``path``; ``error(message naming the file)`` for a file that is not UTF-8,
    not JSON, nested too deeply to parse, holding a number beyond the float range (an integer
    literal of more than 308 digits or a literal such as ``1e400``: the message names its field) or
    (``obj=True``) whose root is not an object. A missing file raises `FileNotFoundError` naming it;
    a path that is not a regular file (a directory, a FIFO, a symbolic link loop) raises ``error``
    naming it (see `regular_file`)."""
    path = regular_file(path, error)
    try:
        data = json.loads(path.read_bytes().decode("utf-8"), parse_int=_parse_int, parse_float=_parse_float)
    except UnicodeDecodeError as e:
        raise error(f"{path}: not a UTF-8 text file ({e})") from None
    except json.JSONDecodeError as e:
        raise error(f"{path}: invalid JSON at line {e.lineno} column {e.colno}: {e.msg}") from None
    except RecursionError:
        raise error(f"{path}: JSON nested too deeply to read") from None
    bad = _out_of_range(data)
    if bad is not None:
        keys, shown = bad
        raise error(f"{path}: field '{_field(keys)}': expected a finite number, got {shown} (beyond the float range)")
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
