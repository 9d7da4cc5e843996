"""Exception types raised by jaxfish for bad *inputs* (files, fields, sizes)."""

from __future__ import annotations


class JaxfishError(ValueError):
    """Base class of every error jaxfish raises for a bad input.

    It is a `ValueError`, so ``except ValueError`` keeps working; the message always names the
    offending file and/or field.
    """


class CalibrationError(JaxfishError):
    """A calibration file or calibration value is malformed (message names file and field)."""


class ImageError(JaxfishError):
    """An image file is missing, unreadable, corrupt, or has the wrong size or dtype."""
