"""Camera models: immutable pytrees with pure ``project`` / ``unproject``."""

from ._base import AbstractCamera as AbstractCamera
from ._equirectangular import Cylindrical as Cylindrical
from ._equirectangular import Equirectangular as Equirectangular
from ._orthographic import Orthographic as Orthographic
from ._pinhole import Pinhole as Pinhole
from ._woodscape import THETA_MAX_MARGIN_RAD as THETA_MAX_MARGIN_RAD
from ._woodscape import WoodScapeFisheye as WoodScapeFisheye
