"""Bird's-eye view: the top-view grid, height maps and occupancy, multi-camera fusion of fisheye
range + semantic maps, the inverse-perspective-mapping (IPM) baseline and mIoU (see ``docs/bev.md``)."""

from ._cameras import rig_rays as rig_rays
from ._cameras import stack_cameras as stack_cameras
from ._cameras import stack_poses as stack_poses
from ._fusion import GATHER_FILL_RADIUS as GATHER_FILL_RADIUS
from ._fusion import GATHER_HEIGHT_TOLERANCE_M as GATHER_HEIGHT_TOLERANCE_M
from ._fusion import GATHER_HEIGHT_TOLERANCE_RAD as GATHER_HEIGHT_TOLERANCE_RAD
from ._fusion import GATHER_RANGE_TOLERANCE as GATHER_RANGE_TOLERANCE
from ._fusion import HEIGHT_QUANTUM_M as HEIGHT_QUANTUM_M
from ._fusion import MAX_CLASSES as MAX_CLASSES
from ._fusion import MIN_HEIGHT_M as MIN_HEIGHT_M
from ._fusion import UNOBSERVED as UNOBSERVED
from ._fusion import BevFusion as BevFusion
from ._fusion import fuse_cameras as fuse_cameras
from ._fusion import fuse_cameras_dense as fuse_cameras_dense
from ._grid import HEIGHT_COLOR_RANGE_M as HEIGHT_COLOR_RANGE_M
from ._grid import OCCUPANCY_MIN_HEIGHT_M as OCCUPANCY_MIN_HEIGHT_M
from ._grid import bev_ground_points as bev_ground_points
from ._grid import bev_pixel_to_vehicle as bev_pixel_to_vehicle
from ._grid import colorize_height as colorize_height
from ._grid import height_map as height_map
from ._grid import occupancy_map as occupancy_map
from ._grid import vehicle_to_bev_pixels as vehicle_to_bev_pixels
from ._ipm import IpmBev as IpmBev
from ._ipm import ipm_semantics as ipm_semantics
from ._metadata import BEV_AXES as BEV_AXES
from ._metadata import bev_metadata as bev_metadata
from ._metrics import VOID_CLASS as VOID_CLASS
from ._metrics import BevScores as BevScores
from ._metrics import IouScores as IouScores
from ._metrics import bev_scores as bev_scores
from ._metrics import pool_bev_scores as pool_bev_scores
from ._metrics import semantic_iou as semantic_iou
from ._metrics import truth_class_miou as truth_class_miou
