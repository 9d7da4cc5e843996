"""One JSON reader for every input file: each way a file can fail names the file."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any


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
