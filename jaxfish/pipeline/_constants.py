"""Per-rig constants: what the pipeline needs of each camera, built once per calibration."""

from __future__ import annotations

import functools
from collections.abc import Mapping, Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float

from ..calibration import Calibration
from ..cameras import AbstractCamera, Orthographic
from ..groundtruth import event_map_from_lut, pixel_rays
from ..reprojection import CubeRig, Lut, compiled_build_lut
from ..transforms import Pose
from ._events import FaceEventTable, face_event_table


class CameraConstants(eqx.Module):
    """One fisheye camera's constants (float32).

    - `name`: the camera's name; `camera`: its lens model; `camera_to_vehicle`: its mount;
    - `lut`: the cube -> fisheye `Lut` at the rig's face size and faces;
    - `rays`: its `jaxfish.groundtruth.pixel_rays` ``((H, W, 3) unit rays, (H, W) valid)``;
    - `event_table`: the inverse LUT mapping face DVS events to fisheye pixels, as the host
      `FaceEventTable` of its `jaxfish.groundtruth.EventMap` (`camera_events` maps with it).
    """

    name: str = eqx.field(static=True)
    camera: AbstractCamera
    camera_to_vehicle: Pose
    lut: Lut
    rays: tuple[Float[Array, "H W 3"], Bool[Array, "H W"]]
    event_table: FaceEventTable


class BevConstants(eqx.Module):
    """The BEV top view's constants: its `Orthographic` `camera` (float32), its mount
    `camera_to_vehicle` and its `rays` (`pixel_rays`)."""

    camera: Orthographic
    camera_to_vehicle: Pose
    rays: tuple[Float[Array, "H W 3"], Bool[Array, "H W"]]


class RigConstants(eqx.Module):
    """Everything `sample_truth` needs of a rig that does not change between frames: one
    `CameraConstants` per fisheye camera (`cameras`, in the frames' camera order), the BEV's
    (`bev`, or None), the cube `faces` and their side `face_size` (pixels)."""

    cameras: tuple[CameraConstants, ...]
    bev: BevConstants | None
    faces: tuple[str, ...] = eqx.field(static=True)
    face_size: int = eqx.field(static=True)

    @property
    def names(self) -> tuple[str, ...]:
        """The fisheye camera names, in order."""
        return tuple(c.name for c in self.cameras)


@functools.cache
def _jit_rays():
    return jax.jit(functools.partial(pixel_rays, dtype=np.float32))


def compiled_pixel_rays(camera: AbstractCamera) -> tuple[Float[Array, "H W 3"], Bool[Array, "H W"]]:
    """`jaxfish.groundtruth.pixel_rays` in float32, compiled once per process and camera type / size."""
    return _jit_rays()(camera)


class EmptyCameraError(ValueError):
    """A camera whose every pixel is invalid in float32 for the rig's cube faces (its lens
    parameters make it useless); ``camera`` names it."""

    def __init__(self, camera: str):
        super().__init__(f"no pixel of camera {camera} has a ray inside its lens and the capture's cube faces "
                         f"(every pixel invalid in float32): its lens parameters make the camera useless")
        self.camera = camera


def camera_constants(name: str, calibration: Calibration, *, faces: Sequence[str], face_size: int) -> CameraConstants:
    """The `CameraConstants` of one calibrated fisheye camera for cube faces ``faces`` of side
    ``face_size`` pixels. Raises `EmptyCameraError` when no pixel of the camera sees a face."""
    calib = calibration.astype(jnp.float32)
    cam = calib.camera.astype(jnp.float32)
    lut = compiled_build_lut(CubeRig(int(face_size), faces=tuple(faces), dtype=jnp.float32), cam)
    if not np.any(np.asarray(lut.valid)):
        raise EmptyCameraError(name)
    # The dense event map lives only while its compact table is made: the table holds a third of
    # its bytes at a fan-out of 2, and the constants are kept for a whole build.
    table = face_event_table(event_map_from_lut(lut))
    return CameraConstants(name, cam, calib.camera_to_vehicle, lut, compiled_pixel_rays(cam), table)


def bev_constants(camera: Orthographic, camera_to_vehicle: Pose) -> BevConstants:
    """The `BevConstants` of a BEV camera (cast to float32) and its mount."""
    cam = camera.astype(jnp.float32)
    return BevConstants(cam, Pose(camera_to_vehicle.rotation_matrix, camera_to_vehicle.translation, dtype=jnp.float32),
                        compiled_pixel_rays(cam))


def rig_constants(rig: Mapping[str, Calibration], *, faces: Sequence[str], face_size: int,
                  bev: tuple[Orthographic, Pose] | None = None) -> RigConstants:
    """The `RigConstants` of ``rig`` (name -> calibration, in the frames' camera order) for cube
    faces ``faces`` of side ``face_size`` pixels, with the BEV camera and mount ``bev`` when the
    source has a top view. Raises `EmptyCameraError` for a camera no face pixel reaches."""
    cams = tuple(camera_constants(n, c, faces=faces, face_size=face_size) for n, c in rig.items())
    return RigConstants(cams, None if bev is None else bev_constants(*bev), tuple(faces), int(face_size))
