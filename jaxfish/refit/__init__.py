"""Refitting and converting lens calibrations: least squares on jaxfish's differentiable cameras."""

from ._convert import BEHIND_AXIS_MARGIN_RAD as BEHIND_AXIS_MARGIN_RAD
from ._convert import ConversionResult as ConversionResult
from ._convert import camera_theta_max as camera_theta_max
from ._convert import convert_camera as convert_camera
from ._convert import initial_camera as initial_camera
from ._convert import sample_rays as sample_rays
from ._fit import LOSSES as LOSSES
from ._fit import Correspondences as Correspondences
from ._fit import RefitResult as RefitResult
from ._fit import estimate_pose as estimate_pose
from ._fit import refit as refit
from ._fit import reprojection_residuals as reprojection_residuals
from ._fit import robust_rho as robust_rho
from ._fit import rotation_from_vector as rotation_from_vector
from ._parameters import APPROXIMATION_PARAMETERS as APPROXIMATION_PARAMETERS
from ._parameters import MODEL_ALIASES as MODEL_ALIASES
from ._parameters import MODEL_CLASSES as MODEL_CLASSES
from ._parameters import PARAMETER_NAMES as PARAMETER_NAMES
from ._parameters import STRING_PARAMETERS as STRING_PARAMETERS
from ._parameters import camera_from_intrinsics as camera_from_intrinsics
from ._parameters import canonical_model_name as canonical_model_name
from ._parameters import intrinsics_from_dict as intrinsics_from_dict
from ._parameters import intrinsics_to_dict as intrinsics_to_dict
from ._parameters import intrinsics_vector as intrinsics_vector
from ._parameters import parameter_names as parameter_names
from ._parameters import with_intrinsics as with_intrinsics
