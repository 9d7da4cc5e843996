"""OCamCalib's ``calib_results.txt`` (Scaramuzza's toolbox): read and write."""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np

from .._errors import CalibrationError
from ..cameras import MAX_IMAGE_SIDE, OCAM_INVPOL_LENGTH, OCAM_POL_LENGTH, OCamCalib
from ._atomic import atomic_write_text
from ._json import regular_file

_MAX_FILE_BYTES = 1 << 20
"""A ``calib_results.txt`` is a few hundred bytes: larger files are refused before reading."""


class _Tokens:
    """The numbers of the file in reading order (comment lines starting with ``#`` skipped), as
    OCamCalib's ``get_ocam_model`` reads them with ``fscanf``."""

    def __init__(self, text: str, source: str):
        self.source = source
        self.items: list[tuple[int, str]] = []
        for number, line in enumerate(text.splitlines(), start=1):
            if line.lstrip().startswith("#"):
                continue
            self.items.extend((number, tok) for tok in line.split())
        self.pos = 0

    def fail(self, field: str, message: str) -> CalibrationError:
        return CalibrationError(f"{self.source}: field '{field}': {message}")

    def more(self) -> bool:
        return self.pos < len(self.items)

    def number(self, field: str) -> float:
        if not self.more():
            raise self.fail(field, "missing (the file ends before it)")
        line, tok = self.items[self.pos]
        self.pos += 1
        try:
            value = float(tok)
        except ValueError:
            raise self.fail(field, f"expected a number, got {tok!r} (line {line})") from None
        if not math.isfinite(value):
            raise self.fail(field, f"expected a finite number, got {tok!r} (line {line})")
        return value

    def count(self, field: str, largest: int) -> int:
        value = self.number(field)
        if value != int(value) or not 1 <= value <= 64:
            raise self.fail(field, f"expected a whole number of coefficients from 1 to 64, got {value!r}")
        return int(value)


def _coefficients(tokens: _Tokens, name: str, largest: int) -> list[float]:
    n = tokens.count(f"{name} length", largest)
    values = [tokens.number(f"{name}[{i}]") for i in range(n)]
    while len(values) > largest and values[-1] == 0:
        values.pop()
    if len(values) > largest:
        raise tokens.fail(f"{name} length", f"{n} coefficients, at most {largest} are supported")
    return values


def ocamcalib_from_text(text: str, *, width: int | None = None, height: int | None = None,
                        source: str = "<calib_results.txt>", dtype=None) -> OCamCalib:
    """An `OCamCalib` camera from the text of a ``calib_results.txt``; see `load_ocamcalib`."""
    tokens = _Tokens(text, source)
    pol = _coefficients(tokens, "pol", OCAM_POL_LENGTH)
    invpol = _coefficients(tokens, "invpol", OCAM_INVPOL_LENGTH)
    xc = tokens.number("center xc (row)")
    yc = tokens.number("center yc (column)")
    c = tokens.number("affine c")
    d = tokens.number("affine d")
    e = tokens.number("affine e")
    size = {}
    if tokens.more():
        for key in ("height", "width"):
            value = tokens.number(f"image size {key}")
            if value != int(value) or not 1 <= value <= MAX_IMAGE_SIDE:
                raise tokens.fail(f"image size {key}", f"expected a whole number of pixels from 1 to {MAX_IMAGE_SIDE}, "
                                  f"got {value!r}")
            size[key] = int(value)
    if tokens.more():
        line, tok = tokens.items[tokens.pos]
        raise tokens.fail("image size", f"unexpected text {tok!r} after the image size (line {line})")
    for key, given in (("width", width), ("height", height)):
        if given is None and key not in size:
            raise tokens.fail(f"image size {key}", "missing (older files have no image size: pass width and height)")
        if given is not None and key in size and int(given) != size[key]:
            raise tokens.fail(f"image size {key}", f"the file says {size[key]}, the caller {given}")
        if given is not None:
            size[key] = int(given)
    if not pol[0] < 0:
        raise tokens.fail("pol[0]", f"OCamCalib's a0 must be negative (the optical axis is -z), got {pol[0]!r}")
    if c - d * e == 0:
        raise tokens.fail("affine c", f"the affine matrix [[c, d], [e, 1]] is singular (c = {c!r}, d = {d!r}, e = {e!r})")
    for name, values in (("pol", pol), ("invpol", invpol)):
        for i, v in enumerate(values):
            if abs(v) > 1e30:
                raise tokens.fail(f"{name}[{i}]", f"expected a magnitude at most 1e30, got {v!r}")
    try:
        return OCamCalib(np.asarray(pol), np.asarray(invpol), xc=xc, yc=yc, c=c, d=d, e=e,
                         width=size["width"], height=size["height"], dtype=dtype)
    except ValueError as err:
        raise tokens.fail("image size", str(err)) from None


def load_ocamcalib(path: str | os.PathLike, width: int | None = None, height: int | None = None, *,
                   dtype=None) -> OCamCalib:
    """Read OCamCalib's ``calib_results.txt`` (the file its Matlab toolbox exports and its C
    ``get_ocam_model`` reads): the direct polynomial (length, then ``a0 a1 ...``), the inverse
    polynomial (length, then coefficients), the centre ``xc yc`` (row, column, 0-based), the affine
    ``c d e`` and, in recent files, the image size ``height width``. Lines starting with ``#`` are
    comments. ``width`` / ``height`` give the image size of files without one (and must agree with
    a file that has one). Polynomials longer than `OCAM_POL_LENGTH` / `OCAM_INVPOL_LENGTH` are
    refused unless the extra coefficients are zeros.

    Raises `FileNotFoundError` for a missing file and `CalibrationError` naming the file and the
    field (``pol[2]``, ``affine c``, ``image size width``, ...) for anything malformed."""
    path = regular_file(path, CalibrationError, "OCamCalib calibration file")
    if path.stat().st_size > _MAX_FILE_BYTES:
        raise CalibrationError(f"{path}: larger than {_MAX_FILE_BYTES} bytes: not an OCamCalib calib_results.txt")
    try:
        text = path.read_bytes().decode("utf-8")
    except UnicodeDecodeError as e:
        raise CalibrationError(f"{path}: not a UTF-8 text file ({e})") from None
    return ocamcalib_from_text(text, width=width, height=height, source=str(path), dtype=dtype)


def ocamcalib_to_text(camera: OCamCalib) -> str:
    """The ``calib_results.txt`` text of a camera (OCamCalib's layout and comments; trailing zero
    coefficients dropped; the image size line included)."""

    def trimmed(values) -> list[float]:
        out = [float(v) for v in np.asarray(values, dtype=np.float64)]
        while len(out) > 1 and out[-1] == 0:
            out.pop()
        return out

    pol, invpol = trimmed(camera.pol), trimmed(camera.invpol)
    lines = [
        "#polynomial coefficients for the DIRECT mapping function (ocam_model.ss in MATLAB). These are used by cam2world",
        "", f"{len(pol)} " + " ".join(repr(v) for v in pol), "",
        "#polynomial coefficients for the inverse mapping function (ocam_model.invpol in MATLAB). "
        "These are used by world2cam", "", f"{len(invpol)} " + " ".join(repr(v) for v in invpol), "",
        '#center: "row" and "column", starting from 0 (C convention)', "",
        f"{float(camera.xc)!r} {float(camera.yc)!r}", "",
        '#affine parameters "c", "d", "e"', "", f"{float(camera.c)!r} {float(camera.d)!r} {float(camera.e)!r}", "",
        '#image size: "height" and "width"', "", f"{camera.height} {camera.width}", "",
    ]
    return "\n".join(lines)


def save_ocamcalib(camera: OCamCalib, path: str | os.PathLike) -> Path:
    """Write a camera as OCamCalib's ``calib_results.txt``, atomically."""
    path = Path(path)
    atomic_write_text(path, ocamcalib_to_text(camera))
    return path
