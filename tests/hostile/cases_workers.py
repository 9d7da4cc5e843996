"""Hostile inputs of the compile cache (``jaxfish build --compile-cache DIR``, ``BuildOptions.compile_cache``):
an unusable folder warns and the build goes on uncached; contradictory flags or a bad option value are refused."""

from __future__ import annotations

from tests.hostile.corpus import Case


def _bad_option(tmp):
    from jaxfish.dataset import BuildOptions

    return BuildOptions(compile_cache=3)


CASES = [
    Case("workers-compile-cache-is-a-file", "build {capture} {tmp}/out --compile-cache {tmp}/capture/capture.json",
         exit=0, says=("warning:", "cannot be used as the compile cache"), kept=("{tmp}/out/dataset.json",
                                                                              "{tmp}/capture/capture.json")),
    Case("workers-compile-cache-under-a-file", "build {capture} {tmp}/out --compile-cache {tmp}/capture/capture.json/xla",
         exit=0, says=("cannot be used as the compile cache",), kept=("{tmp}/out/dataset.json",)),
    Case("workers-compile-cache-both-flags", "build {capture} {tmp}/out --compile-cache {tmp}/xla --no-compile-cache",
         says=("--compile-cache and --no-compile-cache",), absent=("{tmp}/out", "{tmp}/xla")),
    Case("workers-compile-cache-option-not-a-folder", call=_bad_option, says=("compile_cache",)),
]
