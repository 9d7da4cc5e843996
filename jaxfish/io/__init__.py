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
from ._images import read_image as read_image
from ._images import write_image as write_image
