"""Hostile inputs of the scene's surface detail: ``jaxfish synth --texture`` and
``CaptureConfig(textured=...)``."""

from __future__ import annotations

from .corpus import Case


def _config(value):
    def call(tmp):
        from jaxfish.scene import CaptureConfig

        return CaptureConfig(textured=value)

    return call


CASES = [
    Case("texture-synth-flag-with-a-value", "synth --out {tmp}/cap --texture=yes", says=("--texture",),
         absent=("{tmp}/cap",)),
    Case("texture-synth-without-out", "synth --texture", says=("--out",)),
    Case("texture-synth-bad-frames", "synth --out {tmp}/cap --texture --frames 0", says=("--frames",),
         absent=("{tmp}/cap",)),
    Case("texture-config-not-a-bool", call=_config("yes"), raises=ValueError, says=("textured",)),
    Case("texture-config-int", call=_config(1), raises=ValueError, says=("textured",)),
]
