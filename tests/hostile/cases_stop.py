"""Hostile arguments around a build's workers (stopping a build: tests/dataset/test_stop.py)."""

from __future__ import annotations

from .corpus import Case

CASES = [
    Case("stop-build-scheduler-malformed", "build {capture} {tmp}/out --scheduler notanaddress",
         says=("notanaddress", "cannot connect")),
    Case("stop-build-workers-not-a-number", "build {capture} {tmp}/out --workers two", says=("--workers",),
         absent=("{tmp}/out",)),
    Case("stop-build-workers-negative", "build {capture} {tmp}/out --workers -3 --threads", says=("--workers",),
         absent=("{tmp}/out",)),
]
