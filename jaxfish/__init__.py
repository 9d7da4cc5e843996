"""jaxfish: a JAX functional reprojection engine for surround-view fisheye cameras.

The public API (see the docs for every convention)::

    import jaxfish as jf
    calib = jf.load_calibration("FV.json")
    uv, valid = calib.camera.project(points_cam)
    rays, valid = calib.camera.unproject(uv)
    p_vehicle = calib.camera_to_vehicle.apply(points_cam)

Importing jaxfish (or any core subpackage) loads no file or command-line library: the calibration
readers and writers re-exported here (`load_calibration`, `load_rig`, `save_calibration`,
`save_rig`) come from `jaxfish.io`, which is imported on their first use.
"""

import typing

from ._errors import CalibrationError as CalibrationError
from ._errors import ImageError as ImageError
from ._errors import JaxfishError as JaxfishError
from .calibration import CAMERA_NAMES as CAMERA_NAMES
from .calibration import (
    SYNWOODSCAPE_CORRECTED_TRANSLATIONS_CARLA as SYNWOODSCAPE_CORRECTED_TRANSLATIONS_CARLA,
)
from .calibration import Calibration as Calibration
from .calibration import crop_fisheye as crop_fisheye
from .calibration import default_rig as default_rig
from .calibration import resize_fisheye as resize_fisheye
from .cameras import AbstractCamera as AbstractCamera
from .cameras import CarlaWideAngle as CarlaWideAngle
from .cameras import Cylindrical as Cylindrical
from .cameras import DoubleSphere as DoubleSphere
from .cameras import Equirectangular as Equirectangular
from .cameras import ExtendedUnifiedCamera as ExtendedUnifiedCamera
from .cameras import FieldOfView as FieldOfView
from .cameras import Fisheye624 as Fisheye624
from .cameras import FTheta as FTheta
from .cameras import KannalaBrandt as KannalaBrandt
from .cameras import MeiCamera as MeiCamera
from .cameras import OCamCalib as OCamCalib
from .cameras import OpenCVPinhole as OpenCVPinhole
from .cameras import Orthographic as Orthographic
from .cameras import Pinhole as Pinhole
from .cameras import UnifiedCamera as UnifiedCamera
from .cameras import WoodScapeFisheye as WoodScapeFisheye
from .groundtruth import Boxes3D as Boxes3D
from .groundtruth import analytic_flow as analytic_flow
from .groundtruth import fisheye_ground_truth as fisheye_ground_truth
from .groundtruth import flow_to_color as flow_to_color
from .groundtruth import instance_segmentation as instance_segmentation
from .reprojection import CubeRig as CubeRig
from .reprojection import Lut as Lut
from .reprojection import build_lut as build_lut
from .reprojection import cube_face_size as cube_face_size
from .reprojection import resample_bilinear as resample_bilinear
from .reprojection import resample_depth as resample_depth
from .reprojection import resample_nearest as resample_nearest
from .scene import Scene as Scene
from .scene import StreetFrame as StreetFrame
from .scene import generate_street as generate_street
from .scene import oracle_errors as oracle_errors
from .scene import render_fisheye as render_fisheye
from .transforms import Pose as Pose

__version__ = "0.1.0"

if typing.TYPE_CHECKING:
    from .io import load_calibration as load_calibration
    from .io import load_rig as load_rig
    from .io import save_calibration as save_calibration
    from .io import save_rig as save_rig

_FROM_IO = ("load_calibration", "load_rig", "save_calibration", "save_rig")
"""Names re-exported from `jaxfish.io` on first use (`__getattr__`)."""


def __getattr__(name: str):
    """`jaxfish.io`'s re-exported names, imported on first use; AttributeError for any other name."""
    if name in _FROM_IO:
        from . import io

        value = getattr(io, name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'jaxfish' has no attribute {name!r}")


def __dir__() -> list[str]:
    """The module's names, the lazily re-exported ones included."""
    return sorted(set(globals()) | set(_FROM_IO))
