"""Bird's-eye view: the top-view grid, height maps and occupancy, multi-camera fusion of fisheye
range + semantic maps, the inverse-perspective-mapping (IPM) baseline and mIoU (see ``docs/bev.md``)."""

from ._grid import HEIGHT_COLOR_RANGE_M as HEIGHT_COLOR_RANGE_M
from ._grid import OCCUPANCY_MIN_HEIGHT_M as OCCUPANCY_MIN_HEIGHT_M
from ._grid import bev_ground_points as bev_ground_points
from ._grid import bev_pixel_to_vehicle as bev_pixel_to_vehicle
from ._grid import colorize_height as colorize_height
from ._grid import height_map as height_map
from ._grid import occupancy_map as occupancy_map
from ._grid import vehicle_to_bev_pixels as vehicle_to_bev_pixels
