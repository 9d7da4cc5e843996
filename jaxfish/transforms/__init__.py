"""Rigid transforms and the CARLA / ISO 8855 / OpenCV frame conventions."""

from ._frames import CARLA_TO_ISO as CARLA_TO_ISO
from ._frames import UNREAL_CAMERA_TO_OPENCV as UNREAL_CAMERA_TO_OPENCV
from ._frames import carla_camera_pose_to_opencv as carla_camera_pose_to_opencv
from ._frames import carla_pose_to_iso as carla_pose_to_iso
from ._frames import carla_to_iso as carla_to_iso
from ._frames import iso_pose_to_carla as iso_pose_to_carla
from ._frames import iso_to_carla as iso_to_carla
from ._frames import opencv_camera_pose_to_carla as opencv_camera_pose_to_carla
from ._frames import opencv_to_unreal_camera as opencv_to_unreal_camera
from ._frames import unreal_camera_to_opencv as unreal_camera_to_opencv
from ._pose import Pose as Pose
from ._pose import carla_rotation_matrix as carla_rotation_matrix
from ._pose import matrix_to_quaternion_xyzw as matrix_to_quaternion_xyzw
from ._pose import quaternion_xyzw_to_matrix as quaternion_xyzw_to_matrix
