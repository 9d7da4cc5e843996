"""The ``jaxfish`` command line (typer). Each sub-command lives in its own module."""

from __future__ import annotations

from . import _demo as _demo  # noqa: F401  (registers `jaxfish demo`)
from ._app import app as app
from ._app import main as main
