"""The pipeline: what flows from a source to a sink, and the one function between them.

A source yields `Frame`\\ s (one capture instant pair of the whole vehicle: cube faces at t-1 and
t, events, actors, ego, other sensors); `rig_constants` builds the per-calibration constants once;
`sample_truth` turns a frame into a `SampleTruth` (every camera's `CameraTruth`, the BEV's
`BevTruth`, 3D boxes); a sink writes it. Pure JAX / NumPy: nothing here reads or writes files.
"""

from .._sequences import sequence_slots as sequence_slots
from .._sequences import set_sequence_slots as set_sequence_slots
from ._constants import BevConstants as BevConstants
from ._constants import CameraConstants as CameraConstants
from ._constants import EmptyCameraError as EmptyCameraError
from ._constants import RigConstants as RigConstants
from ._constants import bev_constants as bev_constants
from ._constants import camera_constants as camera_constants
from ._constants import compiled_pixel_rays as compiled_pixel_rays
from ._constants import rig_constants as rig_constants
from ._events import FaceEventTable as FaceEventTable
from ._events import camera_events as camera_events
from ._events import face_event_table as face_event_table
from ._events import map_face_events as map_face_events
from ._frame import BOX_SLOT_QUANTUM as BOX_SLOT_QUANTUM
from ._frame import TAG_TABLES as TAG_TABLES
from ._frame import CameraFrame as CameraFrame
from ._frame import CubeFaces as CubeFaces
from ._frame import Frame as Frame
from ._frame import Motion as Motion
from ._frame import SensorRecords as SensorRecords
from ._frame import ViewFrame as ViewFrame
from ._frame import ViewImages as ViewImages
from ._frame import box_slots as box_slots
from ._frame import motion_from_records as motion_from_records
from ._maps import CameraMaps as CameraMaps
from ._maps import camera_maps as camera_maps
from ._render import DEPTH_COLOR_RANGE_M as DEPTH_COLOR_RANGE_M
from ._render import depth_to_color as depth_to_color
from ._render import events_color as events_color
from ._sensors import RADAR_VEHICLE_DTYPE as RADAR_VEHICLE_DTYPE
from ._sensors import SEMANTIC_LIDAR_VEHICLE_DTYPE as SEMANTIC_LIDAR_VEHICLE_DTYPE
from ._sensors import EgoState as EgoState
from ._sensors import GnssFix as GnssFix
from ._sensors import ImuReading as ImuReading
from ._sensors import SensorTruth as SensorTruth
from ._sensors import radar_points_local as radar_points_local
from ._sensors import sensor_to_vehicle_matrix as sensor_to_vehicle_matrix
from ._sensors import sensor_truth as sensor_truth
from ._sensors import vehicle_to_world_matrix as vehicle_to_world_matrix
from ._truth import BevTruth as BevTruth
from ._truth import CameraTruth as CameraTruth
from ._truth import GroundTruthOptions as GroundTruthOptions
from ._truth import SampleTruth as SampleTruth
from ._truth import bev_truth as bev_truth
from ._truth import forget_last_images as forget_last_images
from ._truth import sample_truth as sample_truth
from ._truth import sample_truths as sample_truths
