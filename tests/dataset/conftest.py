"""One small capture (the demo's settings at scale 0.05: fisheyes 64 x 48, BEV 51 px, 2 frames) and
one serial reference build of it, shared by every dataset test."""

from __future__ import annotations

# ``small_capture`` and ``reference_build`` are session fixtures of tests/conftest.py (other test
# folders read the same build).
