"""Reprojection: cube rigs, lookup tables between cameras, and resampling kernels."""

from .._constants import FAR_DEPTH_M as FAR_DEPTH_M
from ._cube import CUBE_FACE_ROTATIONS as CUBE_FACE_ROTATIONS
from ._cube import FIVE_FACES as FIVE_FACES
from ._cube import SIX_FACES as SIX_FACES
from ._cube import CubeRig as CubeRig
from ._cube import UndersampledFacesWarning as UndersampledFacesWarning
from ._cube import cube_face_size as cube_face_size
from ._cube import face_to_camera_rotation as face_to_camera_rotation
from ._cube import max_radial_density as max_radial_density
from ._cube import warn_undersampled_faces as warn_undersampled_faces
from ._lut import Lut as Lut
from ._lut import build_lut as build_lut
from ._lut import centre_sample as centre_sample
from ._lut import compiled_build_lut as compiled_build_lut
from ._lut import lut_from_map as lut_from_map
from ._lut import ring_positions as ring_positions
from ._lut import stack_luts as stack_luts
from ._lut import supersample_offsets as supersample_offsets
from ._resample import DEPTH_AGREEMENT_REL_TOL as DEPTH_AGREEMENT_REL_TOL
from ._resample import pad_faces as pad_faces
from ._resample import resample_bilinear as resample_bilinear
from ._resample import resample_depth as resample_depth
from ._resample import resample_nearest as resample_nearest
