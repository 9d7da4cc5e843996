"""Camera models: immutable pytrees with pure ``project`` / ``unproject``."""

from ._base import MAX_IMAGE_SIDE as MAX_IMAGE_SIDE
from ._base import AbstractCamera as AbstractCamera
from ._carla_wide_angle import CARLA_CAMERA_MODELS as CARLA_CAMERA_MODELS
from ._carla_wide_angle import CarlaWideAngle as CarlaWideAngle
from ._distortion import MAX_DISTORTED_RADIUS as MAX_DISTORTED_RADIUS
from ._distortion import RADTAN_MARGIN_RAD as RADTAN_MARGIN_RAD
from ._double_sphere import DoubleSphere as DoubleSphere
from ._equirectangular import Cylindrical as Cylindrical
from ._equirectangular import Equirectangular as Equirectangular
from ._fisheye624 import Fisheye624 as Fisheye624
from ._fov import FieldOfView as FieldOfView
from ._ftheta import FTHETA_POLY_LENGTH as FTHETA_POLY_LENGTH
from ._ftheta import FTheta as FTheta
from ._kannala_brandt import KB_THETA_MAX_MARGIN_RAD as KB_THETA_MAX_MARGIN_RAD
from ._kannala_brandt import KannalaBrandt as KannalaBrandt
from ._mei import MeiCamera as MeiCamera
from ._ocamcalib import OCAM_INVPOL_LENGTH as OCAM_INVPOL_LENGTH
from ._ocamcalib import OCAM_POL_LENGTH as OCAM_POL_LENGTH
from ._ocamcalib import OCamCalib as OCamCalib
from ._opencv import OpenCVPinhole as OpenCVPinhole
from ._orthographic import Orthographic as Orthographic
from ._pinhole import Pinhole as Pinhole
from ._unified import ExtendedUnifiedCamera as ExtendedUnifiedCamera
from ._unified import UnifiedCamera as UnifiedCamera
from ._woodscape import THETA_MAX_MARGIN_RAD as THETA_MAX_MARGIN_RAD
from ._woodscape import WoodScapeFisheye as WoodScapeFisheye
