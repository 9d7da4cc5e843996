"""CARLA live glue at the edge: the pure parts of the CARLA capture program (``scripts/carla_capture.py``).

Everything here runs without a CARLA server and without the ``carla`` package (an optional extra,
``pip install 'jaxfish[carla]'``; `import_carla` imports it only when a capture runs): functions that
touch CARLA take the ``carla`` module or CARLA objects as arguments (anything with the same attributes
works, which is how the tests drive them). The program's contract is the capture layout
(``docs/capture_layout.md``); how to run it is ``docs/carla_capture.md``.

- **Releases** (`parse_carla_version`, `carla_semantic_tags`, weather presets).
- **Mounts** of every sensor on the ego actor (`CarlaMount`, `cube_face_mounts`, `sensor_carla_mounts`).
- **Sensors**: blueprint attributes and the list of sensors to spawn (`capture_sensor_specs`).
- **Readings**: CARLA sensor outputs -> the capture's arrays (`image_to_bgra`, `dvs_to_events`, ...).
- **Records** of actors and the ego (`carla_actor_records`, `carla_ego_motion`, `carla_street_frame`).
- **Writing** one frame in the capture layout (`write_carla_frame`, `finish_carla_header`), or
  assembling it in memory as a capture reader would decode it (`carla_frame_records`,
  `carla_frame_sensors`, `CarlaImages.decoded`, `carla_frame`: a `jaxfish.pipeline.Frame`), and
  a live session as the dataset builder's source (`CarlaSource`).

The CARLA pixel codecs (depth, semantic, instance, BGRA, the DVS dtype) are `jaxfish.io`'s: io
encodes and decodes, this package talks to the simulator. The core never imports it.
"""

from ._frame import carla_frame as carla_frame
from ._frame import carla_frame_records as carla_frame_records
from ._frame import carla_frame_sensors as carla_frame_sensors
from ._images import CarlaImages as CarlaImages
from ._mounts import CarlaMount as CarlaMount
from ._mounts import bev_pinhole as bev_pinhole
from ._mounts import bev_pinhole_fov_deg as bev_pinhole_fov_deg
from ._mounts import camera_mount as camera_mount
from ._mounts import carla_angles_from_matrix as carla_angles_from_matrix
from ._mounts import cube_face_mounts as cube_face_mounts
from ._mounts import face_camera_to_vehicle as face_camera_to_vehicle
from ._mounts import rear_axle_origin as rear_axle_origin
from ._mounts import rig_on_actor as rig_on_actor
from ._mounts import sensor_carla_mounts as sensor_carla_mounts
from ._mounts import with_bev_altitude as with_bev_altitude
from ._readings import carla_geo_reference as carla_geo_reference
from ._readings import checked_events as checked_events
from ._readings import dvs_to_events as dvs_to_events
from ._readings import gnss_to_dict as gnss_to_dict
from ._readings import height_from_depth as height_from_depth
from ._readings import image_to_bgra as image_to_bgra
from ._readings import imu_to_dict as imu_to_dict
from ._readings import lidar_to_points as lidar_to_points
from ._readings import radar_to_records as radar_to_records
from ._readings import semantic_lidar_to_records as semantic_lidar_to_records
from ._records import actor_category as actor_category
from ._records import actor_semantic_tag as actor_semantic_tag
from ._records import carla_actor_record as carla_actor_record
from ._records import carla_actor_records as carla_actor_records
from ._records import carla_ego_motion as carla_ego_motion
from ._records import carla_street_frame as carla_street_frame
from ._records import carla_transform_tuple as carla_transform_tuple
from ._sensors import CarlaExposure as CarlaExposure
from ._sensors import SensorSpec as SensorSpec
from ._sensors import camera_attributes as camera_attributes
from ._sensors import capture_sensor_specs as capture_sensor_specs
from ._sensors import gnss_attributes as gnss_attributes
from ._sensors import imu_attributes as imu_attributes
from ._sensors import lidar_attributes as lidar_attributes
from ._sensors import radar_attributes as radar_attributes
from ._sensors import set_blueprint_attributes as set_blueprint_attributes
from ._source import CarlaSource as CarlaSource
from ._version import CARLA_LATER_WEATHER_PRESETS as CARLA_LATER_WEATHER_PRESETS
from ._version import CARLA_WEATHER_PRESETS as CARLA_WEATHER_PRESETS
from ._version import SUPPORTED_CARLA_VERSIONS as SUPPORTED_CARLA_VERSIONS
from ._version import SYNWOODSCAPE_WEATHER_PRESETS as SYNWOODSCAPE_WEATHER_PRESETS
from ._version import CarlaCaptureError as CarlaCaptureError
from ._version import carla_semantic_tags as carla_semantic_tags
from ._version import has_instance_camera as has_instance_camera
from ._version import import_carla as import_carla
from ._version import parse_carla_version as parse_carla_version
from ._version import validate_weather as validate_weather
from ._writer import finish_carla_header as finish_carla_header
from ._writer import write_carla_frame as write_carla_frame
