"""Constants of the CARLA world that every layer of jaxfish shares, defined once (plain Python and
NumPy: the file codecs import them without the JAX core)."""

from __future__ import annotations

import numpy as np

FAR_DEPTH_M = 1000.0
"""The far distance in metres: CARLA's depth camera saturates at 1000 m, so sky and anything at or
beyond it reads exactly this planar depth, and jaxfish's depth and range maps keep exactly this value
for far / sky pixels (a far sample is never interpolated). Published as
`jaxfish.reprojection.FAR_DEPTH_M`; `jaxfish.groundtruth.FAR_RANGE_M`, `jaxfish.scene.FAR_M` and
`jaxfish.io.CARLA_MAX_DEPTH_M` are the same value under the names of their domains."""

DVS_EVENT_DTYPE = np.dtype([("x", "<u2"), ("y", "<u2"), ("t", "<i8"), ("pol", "?")])
"""CARLA's DVS event dtype (``np.frombuffer(raw, dtype=DVS_EVENT_DTYPE)``, 13 bytes an event):
``x`` column and ``y`` row (uint16), ``t`` time in nanoseconds (int64), ``pol`` polarity (True:
brighter). Published as `jaxfish.io.DVS_EVENT_DTYPE`; `jaxfish.scene.DVS_DTYPE` is the same dtype."""
