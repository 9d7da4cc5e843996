"""The ``jaxfish`` command line (typer). Each sub-command lives in its own module."""

from __future__ import annotations

from . import _bev as _bev  # noqa: F401  (registers `jaxfish bev`)
from . import _build as _build  # noqa: F401  (registers `jaxfish build`)
from . import _demo as _demo  # noqa: F401  (registers `jaxfish demo`)
from . import _export as _export  # noqa: F401  (registers `jaxfish export`)
from . import _merge as _merge  # noqa: F401  (registers `jaxfish merge`)
from . import _refit as _refit  # noqa: F401  (registers `jaxfish refit` and `jaxfish convert`)
from . import _reproject as _reproject  # noqa: F401  (registers `jaxfish cube2fisheye` and `jaxfish reproject`)
from . import _show as _show  # noqa: F401  (registers `jaxfish show`)
from . import _synth as _synth  # noqa: F401  (registers `jaxfish synth`)
from ._app import app as app
from ._app import main as main
