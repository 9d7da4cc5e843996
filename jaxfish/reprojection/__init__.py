"""Reprojection: cube rigs, lookup tables between cameras, and resampling kernels."""

from ._cube import CUBE_FACE_ROTATIONS as CUBE_FACE_ROTATIONS
from ._cube import FIVE_FACES as FIVE_FACES
from ._cube import SIX_FACES as SIX_FACES
from ._cube import CubeRig as CubeRig
from ._cube import cube_face_size as cube_face_size
from ._cube import face_to_camera_rotation as face_to_camera_rotation
