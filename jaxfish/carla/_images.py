"""One camera's raw CARLA images at one instant, and their decoding into the arrays a capture
reader returns."""

from __future__ import annotations

import dataclasses
from typing import ClassVar

import numpy as np

from ..io import bgra_to_rgb, decode_depth, decode_instance, decode_semantic, encode_instance
from ..scene import CameraImages
from ._version import CarlaCaptureError


@dataclasses.dataclass(frozen=True)
class CarlaImages:
    """One camera's raw CARLA images at one instant, BGRA uint8 ``(H, W, 4)``: `rgb`, `depth`
    (24-bit encoded), `semantic` (tag in R) and `instance` (0.9.14+; None before)."""

    KINDS: ClassVar[tuple[str, ...]] = ("rgb", "depth", "semantic", "instance")
    """The image kinds, in the order they are checked and written."""

    rgb: np.ndarray
    depth: np.ndarray
    semantic: np.ndarray
    instance: np.ndarray | None = None

    def checked(self, what: str, instant: str) -> CarlaImages:
        """These images as arrays, each checked to be BGRA uint8 ``(H, W, 4)`` of the `rgb` image's
        size, with `instance` filled in when None (no instance camera before 0.9.14: the tag in R and
        actor id 0, unknown). A bad image raises `CarlaCaptureError` naming ``what`` (the sensor,
        e.g. ``"FV/front"``), the image and ``instant`` (``"prev"`` or ``"curr"``)."""
        out, shape = {}, None
        for kind in self.KINDS:
            a = getattr(self, kind)
            if a is None and kind == "instance" and shape is not None:
                a = encode_instance(decode_semantic(out["semantic"]), np.zeros(shape[:2], np.int64))
            a = np.asarray(a)
            if a.dtype != np.uint8 or a.ndim != 3 or a.shape[-1] != 4:
                raise CarlaCaptureError(f"{what}: {kind}_{instant} must be BGRA uint8 (H, W, 4), got {a.dtype} {a.shape}")
            if shape is not None and a.shape != shape:
                raise CarlaCaptureError(f"{what}: {kind}_{instant} is {a.shape}, the rgb image {shape}")
            shape = a.shape
            out[kind] = a
        return CarlaImages(**out)

    def decoded(self, what: str, instant: str, *, actor_ids: bool = False) -> CameraImages:
        """The `jaxfish.scene.CameraImages` a capture reader decodes from these images once written
        (`jaxfish.io.CaptureReader.face` / ``view``): RGB uint8 ``(H, W, 3)``, planar depth in metres
        float32 (`jaxfish.io.decode_depth`: CARLA's 24-bit quantisation), semantic tags uint8 and,
        with ``actor_ids``, the actor ids of the instance image as int32 (else None). The images are
        checked first (`checked`)."""
        c = self.checked(what, instant)
        ids = decode_instance(c.instance)[1].astype(np.int32) if actor_ids else None
        return CameraImages(rgb=bgra_to_rgb(c.rgb), depth_m=decode_depth(c.depth), semantic=decode_semantic(c.semantic),
                            actor_id=ids)  # type: ignore[arg-type]
