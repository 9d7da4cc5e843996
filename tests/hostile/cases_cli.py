"""Hostile command lines held already (paths and arguments)."""

from __future__ import annotations

from .corpus import Case

CASES = [
    Case("build-missing-capture", "build {tmp}/nope {tmp}/out", says=("{tmp}/nope", "not found"), absent=("{tmp}/out",)),
    Case("build-frame-not-in-capture", "build {capture} {tmp}/out --frames 1,9", says=("--frames", "9 not in"),
         absent=("{tmp}/out",)),
    Case("build-zero-workers", "build {capture} {tmp}/out --workers 0", says=("--workers",), absent=("{tmp}/out",)),
    Case("convert-out-is-directory", "convert {calib} --to kannala_brandt --out {tmp}", says=("is a directory",)),
]
