"""Sensors as CARLA 0.9.10 produces them, simulated on the embedded scene.

Every function returns plain NumPy arrays in physical units (uint8 RGB, metres, tags, ids); the
CARLA *encodings* (BGRA, 24-bit depth, tag in red) are applied by the capture writer
(`jaxfish.io`), which is edge code. Frames: world and sensor-local frames are CARLA/Unreal
(x forward, y right, z up); camera images use the pixel-centre convention of every jaxfish camera.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping

import jax.numpy as jnp
import numpy as np

from .._constants import DVS_EVENT_DTYPE
from ..calibration import Calibration, mounting_rotation
from ..cameras import AbstractCamera, Orthographic, Pinhole
from ..reprojection import FIVE_FACES, CubeRig
from ..transforms import CARLA_TO_ISO, Pose
from ._caster import DEFAULT_CHUNK, RenderBuffers, cast_rays, render, render_rgb
from ._generator import ego_body_boxes
from ._model import EGO_OBJECT, StreetFrame

GRAVITY_M_S2 = 9.81
"""Standard gravity (m/s²) added to the accelerometer, as CARLA's IMU does."""
EARTH_RADIUS_M = 6378137.0
"""CARLA's equatorial Earth radius (metres) for its GNSS Mercator projection."""
LIDAR_ATTENUATION_PER_M = 0.004
"""CARLA lidar atmosphere attenuation rate (1/m): intensity = exp(-rate * distance)."""
SEMANTIC_LIDAR_DTYPE = np.dtype(
    [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("CosAngle", "<f4"), ("ObjIdx", "<u4"), ("ObjTag", "<u4")]
)
"""Semantic lidar point dtype, as CARLA's ``SemanticLidarDetection`` raw data."""
RADAR_DTYPE = np.dtype([("velocity", "<f4"), ("azimuth", "<f4"), ("altitude", "<f4"), ("depth", "<f4")])
"""Radar detection dtype, as CARLA's ``RadarDetection`` raw data (m/s, rad, rad, m)."""
DVS_DTYPE = DVS_EVENT_DTYPE
"""CARLA's DVS event dtype (t in nanoseconds): `jaxfish.io.DVS_EVENT_DTYPE` (the same object)."""


@dataclasses.dataclass(frozen=True)
class CaptureConfig:
    """What a capture frame renders and how (every size in pixels, distances in metres, angles in
    degrees). Defaults follow SynWoodScape (5 faces per camera, BEV 1024 px) and CARLA's sensor
    defaults (DVS C = 0.3, log eps 1e-3). ``textured`` renders the scene with surface detail
    (``generate_street(..., textured=True)``: RGB with the pixel statistics of a CARLA render; labels,
    depth and motion unchanged); off by default."""

    face_size: int = 768
    faces: tuple[str, ...] = FIVE_FACES
    dvs_substeps: int = 4
    dvs_threshold: float = 0.3
    dvs_log_eps: float = 1e-3
    bev_size: int = 1024
    bev_metres_per_pixel: float = 0.04
    bev_height_m: float = 50.0
    front_width: int = 1632
    front_height: int = 1224
    front_fov_deg: float = 90.0
    lidar_channels: int = 32
    lidar_points_per_channel: int = 1024
    lidar_upper_fov_deg: float = 10.0
    lidar_lower_fov_deg: float = -30.0
    lidar_range_m: float = 100.0
    radar_points: int = 150
    radar_horizontal_fov_deg: float = 30.0
    radar_vertical_fov_deg: float = 10.0
    radar_range_m: float = 100.0
    chunk_size: int = DEFAULT_CHUNK
    textured: bool = False

    def __post_init__(self):
        for name in ("face_size", "bev_size", "front_width", "front_height", "lidar_channels",
                     "lidar_points_per_channel", "dvs_substeps", "chunk_size"):
            if int(getattr(self, name)) <= 0:
                raise ValueError(f"CaptureConfig.{name} must be positive, got {getattr(self, name)}")
        if self.dvs_threshold <= 0:
            raise ValueError(f"CaptureConfig.dvs_threshold must be positive, got {self.dvs_threshold}")
        if not isinstance(self.textured, bool):
            raise ValueError(f"CaptureConfig.textured must be True or False, got {self.textured!r}")


@dataclasses.dataclass(frozen=True)
class CameraImages:
    """One camera image as CARLA's RGB, depth, semantic (and 0.9.14+ instance) cameras see it:
    `rgb` uint8 ``(H, W, 3)``, `depth_m` float32 planar z-depth (1000 = far/sky), `semantic`
    uint8 CARLA 0.9.10 tags, `actor_id` int32 (0 = no actor)."""

    rgb: np.ndarray
    depth_m: np.ndarray
    semantic: np.ndarray
    actor_id: np.ndarray


def to_uint8(rgb) -> np.ndarray:
    """Linear RGB in [0, 1] -> uint8 (rounded, clipped): the stored image."""
    return np.clip(np.rint(np.asarray(rgb, np.float32) * 255.0), 0, 255).astype(np.uint8)


def _images(b: RenderBuffers) -> CameraImages:
    return CameraImages(
        rgb=to_uint8(b.rgb),
        depth_m=np.asarray(b.depth_m, np.float32),
        semantic=np.asarray(b.semantic).astype(np.uint8),
        actor_id=np.asarray(b.actor_id).astype(np.int32),
    )


# ---------------------------------------------------------------------------- mounts
def ego_extent(rig: Mapping[str, Calibration] | None) -> tuple[float, float, float, float]:
    """``(x_rear, x_front, half_width, top)`` of the ego body in the ego actor frame (metres)."""
    boxes = ego_body_boxes(rig)
    lo = np.min([np.asarray(c) - np.asarray(h) for c, h in boxes], axis=0)
    hi = np.max([np.asarray(c) + np.asarray(h) for c, h in boxes], axis=0)
    return float(lo[0]), float(hi[0]), float(hi[1]), float(hi[2])


@dataclasses.dataclass(frozen=True)
class SensorMounts:
    """Where the non-fisheye sensors sit on the ego vehicle, as ISO 8855 vehicle poses (camera
    poses map the OpenCV camera frame; lidar/radar/IMU/GNSS poses map the sensor's frame with
    ISO axes). `carla_transforms` gives the equivalent CARLA ``(location, rotation)``."""

    bev_camera_to_vehicle: Pose
    front_camera_to_vehicle: Pose
    lidar_location: tuple[float, float, float]
    radar_location: tuple[float, float, float]

    def carla_transforms(self) -> dict[str, dict[str, list[float]]]:
        """Sensor -> ego actor CARLA transforms ``{"location": [x, y, z], "rotation": [pitch, yaw, roll]}``."""
        from ..transforms import opencv_camera_pose_to_carla

        out = {}
        for name, pose in (("bev", self.bev_camera_to_vehicle), ("front", self.front_camera_to_vehicle)):
            loc, rot = opencv_camera_pose_to_carla(pose).as_carla()
            out[name] = {"location": [float(v) for v in np.asarray(loc)], "rotation": [float(v) for v in np.asarray(rot)]}
        for name, loc in (("lidar", self.lidar_location), ("radar", self.radar_location)):
            out[name] = {"location": [loc[0], -loc[1], loc[2]], "rotation": [0.0, 0.0, 0.0]}
        out["imu"] = out["gnss"] = {"location": [0.0, 0.0, 0.0], "rotation": [0.0, 0.0, 0.0]}
        return out


def sensor_mounts(rig: Mapping[str, Calibration] | None, config: CaptureConfig) -> SensorMounts:
    """Default mounts: the BEV camera `bev_height_m` above the ego body's centre looking straight
    down with image up = vehicle forward; the front camera at the top front of the cabin looking
    forward, level; the lidar 0.4 m above the roof centre; the radar on the front bumper."""
    x_rear, x_front, _, top = ego_extent(rig)
    xc = 0.5 * (x_rear + x_front)
    # OpenCV x (image right) = vehicle right (-y_iso), y (image down) = vehicle backward, z = down.
    bev_r = np.array([[0.0, -1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
    bev = Pose(bev_r, np.array([xc, 0.0, config.bev_height_m]))
    front = Pose(mounting_rotation(0.0, 0.0), np.array([x_rear + 0.62 * (x_front - x_rear), 0.0, top + 0.05]))
    return SensorMounts(bev, front, (xc, 0.0, top + 0.4), (x_front + 0.05, 0.0, 0.6))


def bev_camera(config: CaptureConfig) -> Orthographic:
    """The BEV top camera: `Orthographic`, ``bev_size`` square, ``bev_metres_per_pixel``."""
    return Orthographic(config.bev_metres_per_pixel, width=config.bev_size, height=config.bev_size, dtype=jnp.float32)


def front_camera(config: CaptureConfig) -> Pinhole:
    """The front perspective camera (CARLA pinhole, ``front_fov_deg`` horizontal)."""
    return Pinhole.from_fov(config.front_width, config.front_height, config.front_fov_deg, dtype=jnp.float32)


# ---------------------------------------------------------------------------- cameras
def render_camera(frame: StreetFrame, camera: AbstractCamera, camera_to_vehicle: Pose, *, time: float = 1.0,
                  chunk_size: int = DEFAULT_CHUNK) -> RenderBuffers:
    """Render ``camera`` mounted on the ego by ``camera_to_vehicle`` (OpenCV -> ISO 8855) at ``time``
    (0 = t-1, 1 = t); the camera moves with the ego vehicle."""
    pose = frame.scene.camera_to_world(camera_to_vehicle, time)
    return render(frame.scene, camera, pose, time=time, chunk_size=chunk_size)


def render_cube_faces(frame: StreetFrame, calib: Calibration, face_size: int, *, time: float = 1.0,
                      faces: tuple[str, ...] = FIVE_FACES, chunk_size: int = DEFAULT_CHUNK) -> dict[str, RenderBuffers]:
    """The cube faces of one fisheye camera (`CubeRig` geometry: CARLA fov-90 pinholes rotated
    relative to the fisheye's CARLA transform), rendered at ``time``."""
    rig = CubeRig(face_size, faces=faces, dtype=jnp.float32)
    out = {}
    for name in faces:
        mount = Pose(calib.camera_to_vehicle.rotation_matrix, calib.camera_to_vehicle.translation, dtype=jnp.float32)
        out[name] = render_camera(frame, rig.face, mount @ rig.face_pose(name), time=time, chunk_size=chunk_size)
    return out


def log_intensity(rgb_uint8: np.ndarray, log_eps: float = 1e-3) -> np.ndarray:
    """CARLA DVS log intensity ``log(eps + I)`` with ``I = (0.2989 R + 0.5870 G + 0.1140 B) / 255``."""
    a = np.asarray(rgb_uint8, np.float64)
    i = (0.2989 * a[..., 0] + 0.5870 * a[..., 1] + 0.1140 * a[..., 2]) / 255.0
    return np.log(log_eps + i)


def dvs_events(log_frames: np.ndarray, times_ns: np.ndarray, threshold: float = 0.3) -> np.ndarray:
    """DVS events from log-intensity sub-frames ``(K+1, H, W)`` at ``times_ns`` ``(K+1,)``.

    ESIM-style, as CARLA's DVS: each pixel keeps a reference level starting at the first frame;
    between consecutive sub-frames the log intensity is linear in time, and each crossing of
    ``reference ± threshold`` emits an event (timestamp interpolated, polarity True = brighter) and
    moves the reference. Returns `DVS_EVENT_DTYPE` events sorted by time (x = column, y = row, t in ns).
    """
    lf = np.asarray(log_frames, np.float64)
    times = np.asarray(times_ns, np.float64)
    ref = lf[0].copy()
    out = []
    for k in range(1, lf.shape[0]):
        la, lb = lf[k - 1], lf[k]
        span = lb - la
        for sign in (1.0, -1.0):
            n = np.floor(np.maximum(sign * (lb - ref), 0.0) / threshold).astype(np.int64)
            ys, xs = np.nonzero(n)
            if ys.size == 0:
                continue
            cnt = n[ys, xs]
            rep = np.repeat(np.arange(ys.size), cnt)
            j = np.arange(rep.size) - np.repeat(np.cumsum(cnt) - cnt, cnt) + 1
            level = ref[ys, xs][rep] + sign * threshold * j
            sp = span[ys, xs][rep]
            frac = np.where(np.abs(sp) > 0, (level - la[ys, xs][rep]) / np.where(np.abs(sp) > 0, sp, 1.0), 1.0)
            frac = np.clip(frac, 0.0, 1.0)
            t = times[k - 1] + frac * (times[k] - times[k - 1])
            ev = np.empty(rep.size, DVS_EVENT_DTYPE)
            ev["x"], ev["y"] = xs[rep], ys[rep]
            ev["t"] = np.rint(t).astype(np.int64)
            ev["pol"] = sign > 0
            out.append(ev)
            ref[ys, xs] += sign * threshold * cnt
    if not out:
        return np.empty(0, DVS_EVENT_DTYPE)
    ev = np.concatenate(out)
    return ev[np.argsort(ev["t"], kind="stable")]


@dataclasses.dataclass(frozen=True)
class CameraCapture:
    """One fisheye camera's capture: per face the images at t-1 (`prev`) and t (`curr`) and the DVS
    events between them (face pixel coordinates, absolute t in ns)."""

    prev: dict[str, CameraImages]
    curr: dict[str, CameraImages]
    dvs: dict[str, np.ndarray]


def frame_times_ns(frame: StreetFrame, substeps: int) -> np.ndarray:
    """Absolute simulation times (ns) of ``substeps + 1`` equally spaced instants from t-1 to t."""
    t0 = frame.timestamp_s - frame.dt_s
    return np.rint((t0 + np.linspace(0.0, 1.0, substeps + 1) * frame.dt_s) * 1e9).astype(np.int64)


def simulate_camera(frame: StreetFrame, calib: Calibration, config: CaptureConfig, *,
                    prev: Mapping[str, CameraImages] | None = None) -> CameraCapture:
    """Cube faces at t-1 and t, and DVS events rendered from ``dvs_substeps`` sub-frames.

    ``prev``: the faces at t-1 when they are already rendered, i.e. the previous frame's
    `CameraCapture.curr` of the same camera and settings (frame ``k``'s t-1 is frame ``k - 1``'s t
    bit for bit in `generate_street`, so the result is the same, one render per face fewer)."""
    rig = CubeRig(config.face_size, faces=config.faces, dtype=jnp.float32)
    mount = Pose(calib.camera_to_vehicle.rotation_matrix, calib.camera_to_vehicle.translation, dtype=jnp.float32)
    k = config.dvs_substeps
    times_ns = frame_times_ns(frame, k)
    before, curr, dvs = {}, {}, {}
    for name in config.faces:
        pose = mount @ rig.face_pose(name)
        logs = []
        for i in range(k + 1):
            if i == 0 and prev is not None:
                img = before[name] = prev[name]
                rgb = img.rgb
            elif i == 0 or i == k:
                img = _images(render_camera(frame, rig.face, pose, time=i / k, chunk_size=config.chunk_size))
                (before if i == 0 else curr)[name] = img
                rgb = img.rgb
            else:
                world = frame.scene.camera_to_world(pose, i / k)
                rgb = to_uint8(render_rgb(frame.scene, rig.face, world, time=i / k, chunk_size=config.chunk_size))
            logs.append(log_intensity(rgb, config.dvs_log_eps))
        dvs[name] = dvs_events(np.stack(logs), times_ns, config.dvs_threshold)
    return CameraCapture(before, curr, dvs)


def simulate_view(frame: StreetFrame, camera: AbstractCamera, camera_to_vehicle: Pose, config: CaptureConfig, *,
                  prev: CameraImages | None = None) -> tuple[CameraImages, CameraImages, np.ndarray]:
    """A single camera (BEV or front) at t-1 and t, plus its height map at t: the world z (metres
    above the ground plane) of the surface each pixel sees (0 for sky). ``prev``: the images at t-1
    when already rendered (the previous frame's images at t: see `simulate_camera`)."""
    if prev is None:
        prev = _images(render_camera(frame, camera, camera_to_vehicle, time=0.0, chunk_size=config.chunk_size))
    b1 = render_camera(frame, camera, camera_to_vehicle, time=1.0, chunk_size=config.chunk_size)
    height = np.where(np.asarray(b1.hit), np.asarray(b1.point_world[..., 2]), 0.0).astype(np.float32)
    return prev, _images(b1), height


# ---------------------------------------------------------------------------- lidar / radar
def _sensor_to_world(frame: StreetFrame, location_iso: tuple[float, float, float]) -> Pose:
    """Sensor frame (Unreal axes, CARLA ``Rotation(0, 0, 0)`` on the ego) -> world, at t."""
    ego = frame.scene.ego_to_world(1.0)
    loc = jnp.asarray([location_iso[0], -location_iso[1], location_iso[2]], jnp.float32)
    return ego @ Pose(jnp.eye(3, dtype=jnp.float32), loc)


def lidar_directions(config: CaptureConfig) -> np.ndarray:
    """Unit ray directions ``(points_per_channel * channels, 3)`` of one full rotation in the sensor
    frame (Unreal: x forward, y right, z up), azimuth-major: for each azimuth step (clockwise from x
    seen from above, i.e. towards +y) the channels from the upper to the lower field-of-view limit,
    as CARLA's ray-cast lidar sweeps."""
    elev = np.deg2rad(np.linspace(config.lidar_upper_fov_deg, config.lidar_lower_fov_deg, config.lidar_channels))
    az = np.deg2rad(np.arange(config.lidar_points_per_channel) * 360.0 / config.lidar_points_per_channel)
    a, e = np.meshgrid(az, elev, indexing="ij")  # azimuth-major: chunks of rays are narrow wedges
    return np.stack([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)], axis=-1).reshape(-1, 3)


def simulate_lidar(frame: StreetFrame, location_iso: tuple[float, float, float], config: CaptureConfig) -> tuple[np.ndarray, np.ndarray]:
    """One rotation at t (CARLA casts a whole sweep against the world of one tick). Returns the
    lidar ``(N, 4)`` float32 ``x, y, z, intensity`` and the semantic lidar (`SEMANTIC_LIDAR_DTYPE`)
    for the hits within ``lidar_range_m``, in the sensor frame (Unreal axes, metres). ``ObjIdx`` is
    the actor id (0 for the static world and ground)."""
    pose = _sensor_to_world(frame, location_iso)
    d_local = jnp.asarray(lidar_directions(config), jnp.float32)
    d = pose.rotate(d_local)
    o = jnp.broadcast_to(pose.translation, d.shape)
    b = cast_rays(frame.scene, o, d, time=1.0, chunk_size=config.chunk_size)
    r = np.asarray(b.range_m)
    keep = np.asarray(b.hit) & (r <= config.lidar_range_m)
    pts = np.asarray(d_local)[keep] * r[keep, None]
    intensity = np.exp(-LIDAR_ATTENUATION_PER_M * r[keep])
    lidar = np.concatenate([pts, intensity[:, None]], axis=-1).astype(np.float32)
    sem = np.empty(pts.shape[0], SEMANTIC_LIDAR_DTYPE)
    sem["x"], sem["y"], sem["z"] = pts[:, 0], pts[:, 1], pts[:, 2]
    cos_inc = -np.sum(np.asarray(b.normal_world)[keep] * np.asarray(d)[keep], axis=-1)
    sem["CosAngle"] = np.clip(cos_inc, -1.0, 1.0)
    sem["ObjIdx"] = np.asarray(b.actor_id)[keep].astype(np.uint32)
    sem["ObjTag"] = np.asarray(b.semantic)[keep].astype(np.uint32)
    return lidar, sem


def simulate_radar(frame: StreetFrame, location_iso: tuple[float, float, float], config: CaptureConfig) -> np.ndarray:
    """Radar detections at t (`RADAR_DTYPE`): ``radar_points`` rays drawn uniformly (seeded by the
    scene seed and frame) in the field of view; per hit the azimuth and altitude (radians, sensor
    frame, azimuth positive to the right), depth (metres) and radial velocity (m/s, the rate of
    change of the range: negative when approaching)."""
    rng = np.random.default_rng([frame.seed, frame.frame, 7])
    n = config.radar_points
    az = np.deg2rad(rng.uniform(-0.5, 0.5, n) * config.radar_horizontal_fov_deg)
    alt = np.deg2rad(rng.uniform(-0.5, 0.5, n) * config.radar_vertical_fov_deg)
    d_local = np.stack([np.cos(alt) * np.cos(az), np.cos(alt) * np.sin(az), np.sin(alt)], axis=-1)
    pose = _sensor_to_world(frame, location_iso)
    d = pose.rotate(jnp.asarray(d_local, jnp.float32))
    o = jnp.broadcast_to(pose.translation, d.shape)
    b = cast_rays(frame.scene, o, d, time=1.0, chunk_size=config.chunk_size)
    scene = frame.scene
    p = b.point_world
    p_prev = scene.move_points(b.object_index, p, 1.0, 0.0)
    v_point = (p - p_prev) / scene.dt_s
    sensor_prev = scene.move_points(jnp.asarray(EGO_OBJECT), pose.translation, 1.0, 0.0)
    v_sensor = (pose.translation - sensor_prev) / scene.dt_s
    radial = np.sum(np.asarray(v_point - v_sensor) * np.asarray(d), axis=-1)
    r = np.asarray(b.range_m)
    keep = np.asarray(b.hit) & (r <= config.radar_range_m)
    out = np.empty(int(keep.sum()), RADAR_DTYPE)
    out["velocity"], out["azimuth"], out["altitude"], out["depth"] = radial[keep], az[keep], alt[keep], r[keep]
    return out


# ---------------------------------------------------------------------------- IMU / GNSS
def simulate_imu(frame: StreetFrame) -> dict[str, object]:
    """CARLA-style IMU at the ego origin at t: ``accelerometer`` (m/s², ego frame, Unreal axes,
    gravity included: +9.81 on z at rest), ``gyroscope`` (rad/s, ego frame; z positive = yaw
    increasing), ``compass`` (radians from north = world -y, clockwise; east = +x)."""
    yaw = math.radians(frame.ego.rotation[1])
    c, s = math.cos(yaw), math.sin(yaw)
    a = np.asarray(frame.ego_motion.acceleration) + np.array([0.0, 0.0, GRAVITY_M_S2])
    acc = [c * a[0] + s * a[1], -s * a[0] + c * a[1], a[2]]
    gyro = [0.0, 0.0, math.radians(frame.ego_motion.angular_velocity[2])]
    compass = math.atan2(c, -s) % (2 * math.pi)
    return {"accelerometer": [float(v) for v in acc], "gyroscope": gyro, "compass": compass,
            "timestamp_s": frame.timestamp_s}


def location_to_geo(location, *, lat0_deg: float = 0.0, lon0_deg: float = 0.0, alt0_m: float = 0.0) -> tuple[float, float, float]:
    """CARLA's world -> (latitude, longitude, altitude) transform (``carla::geom::GeoLocation``:
    Mercator around the map's geo-reference; x east, -y north, z up)."""
    x, y, z = (float(v) for v in location)
    scale = math.cos(math.radians(lat0_deg))
    mx = scale * lon0_deg * math.pi * EARTH_RADIUS_M / 180.0 + x
    my = scale * EARTH_RADIUS_M * math.log(math.tan((90.0 + lat0_deg) * math.pi / 360.0)) - y
    lon = mx * 180.0 / (math.pi * EARTH_RADIUS_M * scale)
    lat = 360.0 * math.atan(math.exp(my / (EARTH_RADIUS_M * scale))) / math.pi - 90.0
    return lat, lon, alt0_m + z


def simulate_gnss(frame: StreetFrame) -> dict[str, float]:
    """GNSS fix of the ego origin at t (degrees, metres), noise-free, geo-reference (0, 0, 0)."""
    lat, lon, alt = location_to_geo(frame.ego.location)
    return {"latitude": lat, "longitude": lon, "altitude": alt, "timestamp_s": frame.timestamp_s}


def iso_location_to_carla(location_iso) -> tuple[float, float, float]:
    """ISO 8855 vehicle coordinates -> the ego actor's CARLA coordinates (y flipped)."""
    v = np.asarray(CARLA_TO_ISO) @ np.asarray(location_iso, float)
    return float(v[0]), float(v[1]), float(v[2])

