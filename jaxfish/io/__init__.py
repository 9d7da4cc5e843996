"""I/O adapters at the edge (files in, arrays out): never imported by the pure-JAX core."""

from ._atomic import atomic_path as atomic_path
from ._atomic import atomic_write_bytes as atomic_write_bytes
from ._atomic import atomic_write_text as atomic_write_text
from ._calibration_json import calibration_from_dict as calibration_from_dict
from ._calibration_json import calibration_to_dict as calibration_to_dict
from ._calibration_json import load_calibration as load_calibration
from ._calibration_json import load_rig as load_rig
from ._calibration_json import save_calibration as save_calibration
from ._calibration_json import save_rig as save_rig
from ._carla import CARLA_MAX_DEPTH_M as CARLA_MAX_DEPTH_M
from ._carla import DVS_EVENT_DTYPE as DVS_EVENT_DTYPE
from ._carla import bgra_to_rgb as bgra_to_rgb
from ._carla import decode_depth as decode_depth
from ._carla import decode_dvs as decode_dvs
from ._carla import decode_instance as decode_instance
from ._carla import decode_semantic as decode_semantic
from ._carla import encode_depth as encode_depth
from ._carla import encode_instance as encode_instance
from ._carla import encode_semantic as encode_semantic
from ._carla import rgb_to_bgra as rgb_to_bgra
from ._images import read_image as read_image
from ._images import write_image as write_image
