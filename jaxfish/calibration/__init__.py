"""Calibrated cameras, exact resize/crop of intrinsics, and jaxfish's default rig."""

from ._calibration import CAMERA_NAMES as CAMERA_NAMES
from ._calibration import (
    SYNWOODSCAPE_CORRECTED_TRANSLATIONS_CARLA as SYNWOODSCAPE_CORRECTED_TRANSLATIONS_CARLA,
)
from ._calibration import Calibration as Calibration
from ._calibration import crop_fisheye as crop_fisheye
from ._calibration import resize_fisheye as resize_fisheye
from ._default_rig import default_rig as default_rig
from ._default_rig import mounting_rotation as mounting_rotation
