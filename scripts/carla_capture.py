"""Capture CARLA (0.9.10 - 0.9.16) into jaxfish's capture layout (``docs/capture_layout.md``).

Needs a running CARLA server and the matching client package (``pip install 'jaxfish[carla]'``, or
``pip install carla==<server version>``). For every weather preset it writes one capture directory
``OUT/<Preset>/`` that ``jaxfish build`` turns into a SynWoodScape-style dataset:

    uv run python scripts/carla_capture.py --town Town10HD --frames 100 --weather ClearNoon --out captures/

The ego vehicle and traffic drive on the traffic manager's autopilot, pedestrians walk with AI
controllers; the world runs in synchronous mode at 10 FPS (``fixed_delta_seconds = 0.1``). Every
fisheye camera of the calibration is rendered as five 90-degree cube faces (RGB, depth, semantic,
0.9.14+ instance and DVS each), with one fixed exposure on every face. Frame k holds the ticks
k (t-1) and k+1 (t). Everything spawned is destroyed, and the world's settings restored, on exit.
``--build DATASET_DIR`` instead of ``--out`` builds the dataset while capturing, without writing a
capture (``DATASET_DIR/<Preset>/``: the same sample files as capturing, then ``jaxfish build``).
Options: ``--help``; details: ``docs/carla_capture.md``.
"""

from __future__ import annotations

import argparse
import queue
import random
import sys
import time
import uuid
import warnings
from collections import deque
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from jaxfish import JaxfishError, default_rig, load_rig
from jaxfish.carla import (
    CarlaCaptureError,
    CarlaExposure,
    CarlaImages,
    CarlaSource,
    bev_pinhole,
    capture_sensor_specs,
    carla_actor_records,
    carla_ego_motion,
    carla_frame,
    carla_geo_reference,
    carla_semantic_tags,
    carla_street_frame,
    carla_transform_tuple,
    dvs_to_events,
    finish_carla_header,
    gnss_to_dict,
    height_from_depth,
    image_to_bgra,
    import_carla,
    imu_to_dict,
    lidar_to_points,
    parse_carla_version,
    radar_to_records,
    rear_axle_origin,
    rig_on_actor,
    semantic_lidar_to_records,
    sensor_carla_mounts,
    set_blueprint_attributes,
    validate_weather,
    with_bev_altitude,
    write_carla_frame,
)
from jaxfish.dataset import rig_names
from jaxfish.io import (
    check_capture_folder,
    decode_depth,
    write_capture_header,
)
from jaxfish.io._folder import folder_lock, remove_temporaries
from jaxfish.reprojection import UndersampledFacesWarning, warn_undersampled_faces
from jaxfish.scene import CaptureConfig, front_camera, sensor_mounts

DT_S = 0.1  # 10 FPS, SynWoodScape's rate
#: The ego blueprint tried when --ego-blueprint is not given: CARLA 0.9.12+ spell the Lincoln
#: MKZ 2017 ``mkz_2017``, 0.9.10 / 0.9.11 ``mkz2017``.
DEFAULT_EGO_BLUEPRINTS = ("vehicle.lincoln.mkz_2017", "vehicle.lincoln.mkz2017")


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    """The command line (see ``--help``)."""
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--host", default="127.0.0.1", help="CARLA server host")
    p.add_argument("--port", type=int, default=2000, help="CARLA server RPC port")
    p.add_argument("--tm-port", type=int, default=8000, help="traffic manager port")
    p.add_argument("--timeout", type=float, default=60.0, help="client timeout and per-sensor wait (s)")
    p.add_argument("--dvs-wait", type=float, default=0.2,
                   help="after the other sensors of a tick, how long to wait for DVS readings (s, all DVS together); "
                        "a DVS without one had no event")
    p.add_argument("--town", default=None, help="map to load (e.g. Town10HD); default: keep the loaded map")
    p.add_argument("--frames", type=int, default=10, help="frames per weather preset (each frame = 2 ticks: t-1, t)")
    p.add_argument("--warmup", type=int, default=30, help="ticks to let traffic start before the first frame")
    p.add_argument("--weather", action="append", default=None,
                   help="weather preset (repeatable), a carla.WeatherParameters name, e.g. ClearNoon; default ClearNoon")
    p.add_argument("--calibration", type=Path, default=None,
                   help="directory of WoodScape/SynWoodScape calibration JSONs (FV, MVL, MVR, RV); default: jaxfish's default rig")
    p.add_argument("--vehicle-origin", default="auto",
                   help="where the calibration's vehicle origin is in the ego actor frame: 'auto' (rear axle on the "
                        "ground for WoodScape-flavour files, the actor origin for SynWoodScape ones), 'actor', or 'X,Y,Z' "
                        "metres in CARLA axes")
    p.add_argument("--face-size", type=int, default=1152,
                   help="cube face side S in pixels (fov 90); a size that undersamples the rig's fisheyes is warned about")
    p.add_argument("--bev-size", type=int, default=1024, help="BEV image side in pixels")
    p.add_argument("--bev-metres-per-pixel", type=float, default=0.04, help="BEV ground resolution")
    p.add_argument("--bev-altitude", type=float, default=500.0, help="height of the BEV pinhole above the ego (m)")
    p.add_argument("--front-size", type=int, nargs=2, default=(1632, 1224), metavar=("W", "H"), help="front camera size")
    p.add_argument("--vehicles", type=int, default=50, help="traffic vehicles on autopilot")
    p.add_argument("--walkers", type=int, default=50, help="pedestrians with AI controllers")
    p.add_argument("--ego-blueprint", default=None,
                   help="ego vehicle blueprint id; default: the Lincoln MKZ 2017 (vehicle.lincoln.mkz_2017, or "
                        "vehicle.lincoln.mkz2017 on CARLA 0.9.10 / 0.9.11)")
    p.add_argument("--seed", type=int, default=0, help="seed of spawn points, blueprints, traffic manager")
    p.add_argument("--shutter-speed", type=float, default=200.0, help="fixed exposure: shutter speed (1/s)")
    p.add_argument("--iso", type=float, default=100.0, help="fixed exposure: ISO")
    p.add_argument("--fstop", type=float, default=1.4, help="fixed exposure: f-number")
    p.add_argument("--exposure-compensation", type=float, default=0.0, help="fixed exposure: compensation (EV)")
    p.add_argument("--dry-run", action="store_true",
                   help="print every sensor (blueprint, mount, attributes) and exit, without a server")
    p.add_argument("--carla-version", default="0.9.15", help="the CARLA release --dry-run assumes")
    p.add_argument("--out", type=Path, default=None, help="output directory (one capture per weather preset); "
                                                          "--out or --build is required unless --dry-run")
    p.add_argument("--build", type=Path, default=None, metavar="DATASET_DIR",
                   help="online mode: build the SynWoodScape dataset while capturing (one per weather preset, "
                        "DATASET_DIR/<Preset>/), without writing a capture")
    args = p.parse_args(argv)
    if args.frames <= 0 or args.face_size <= 0 or args.vehicles < 0 or args.walkers < 0 or args.warmup < 1:
        p.error("--frames, --face-size, --warmup must be positive; --vehicles, --walkers non-negative")
    if args.out is not None and args.build is not None:
        p.error("--out (write a capture) and --build (build a dataset while capturing) exclude each other")
    if args.out is None and args.build is None and not args.dry_run:
        p.error("--out or --build is required (unless --dry-run)")
    return args


class Session:
    """One CARLA session: world settings, the spawned actors and sensors, and per-tick collection."""

    def __init__(self, carla, client, args):
        self.carla, self.client, self.args = carla, client, args
        self.world = client.get_world()
        self.original_settings = self.world.get_settings()
        self.tm = None
        self.actor_ids: list[int] = []  # vehicles and walkers
        self.controllers: list = []  # started AI walker controllers
        self.controller_ids: list[int] = []
        self.sensors: dict[tuple, object] = {}
        self.queues: dict[tuple, queue.Queue] = {}
        self.ego = None
        self.ego_blueprint: str | None = None  # the blueprint id the ego was spawned from
        self.dvs_missed: dict[tuple, set[int]] = {}  # per DVS sensor: frames recorded without a reading

    # ------------------------------------------------------------------ setup
    def synchronous(self) -> None:
        settings = self.world.get_settings()
        settings.synchronous_mode = True
        settings.fixed_delta_seconds = DT_S
        self.world.apply_settings(settings)
        self.tm = self.client.get_trafficmanager(self.args.tm_port)
        self.tm.set_synchronous_mode(True)
        if hasattr(self.tm, "set_random_device_seed"):
            self.tm.set_random_device_seed(self.args.seed)

    def spawn_ego(self, rng: random.Random):
        """Spawn the ego at the first free shuffled spawn point; returns the other spawn points."""
        lib = self.world.get_blueprint_library()
        candidates = (self.args.ego_blueprint,) if self.args.ego_blueprint else DEFAULT_EGO_BLUEPRINTS
        found = []
        for name in candidates:
            found = lib.filter(name)
            if found:
                break
        if not found:
            raise CarlaCaptureError(f"--ego-blueprint {' / '.join(candidates)}: no such blueprint on this server")
        bp = found[0]
        self.ego_blueprint = bp.id
        if bp.has_attribute("role_name"):
            bp.set_attribute("role_name", "hero")
        random_color(bp, rng)
        points = self.world.get_map().get_spawn_points()
        rng.shuffle(points)
        for sp in points:
            ego = self.world.try_spawn_actor(bp, sp)
            if ego is not None:
                self.ego = ego
                self.actor_ids.append(ego.id)
                ego.set_autopilot(True, self.args.tm_port)
                return [p for p in points if p is not sp]  # the ego's point is taken
        raise CarlaCaptureError("no free spawn point for the ego vehicle")

    def spawn_traffic(self, rng: random.Random, points) -> None:
        carla = self.carla
        lib = self.world.get_blueprint_library()
        bps = [b for b in lib.filter("vehicle.*") if b.id != self.ego_blueprint]
        batch = []
        if len(points) < self.args.vehicles:
            print(f"note: only {len(points)} free spawn points for --vehicles {self.args.vehicles}")
        for sp in points[: self.args.vehicles]:
            bp = rng.choice(bps)
            if bp.has_attribute("role_name"):
                bp.set_attribute("role_name", "autopilot")
            random_color(bp, rng)
            batch.append(carla.command.SpawnActor(bp, sp).then(
                carla.command.SetAutopilot(carla.command.FutureActor, True, self.args.tm_port)))
        failed = []
        for r in self.client.apply_batch_sync(batch, True):
            if not r.error:
                self.actor_ids.append(r.actor_id)
            else:
                failed.append(r.error)
        report_failures("traffic vehicles", len(batch), failed)
        walker_bps = list(lib.filter("walker.pedestrian.*"))
        batch, speeds = [], []
        for _ in range(self.args.walkers):
            loc = self.world.get_random_location_from_navigation()
            if loc is None:
                continue
            bp = rng.choice(walker_bps)
            if bp.has_attribute("is_invincible"):
                bp.set_attribute("is_invincible", "false")
            speed = bp.get_attribute("speed").recommended_values[1] if bp.has_attribute("speed") else "1.4"
            batch.append(carla.command.SpawnActor(bp, carla.Transform(loc)))
            speeds.append(float(speed))
        walkers, failed = [], []
        if len(batch) < self.args.walkers:
            print(f"note: {self.args.walkers - len(batch)} of {self.args.walkers} walkers got no navigation location")
        for r, speed in zip(self.client.apply_batch_sync(batch, True), speeds, strict=True):
            if not r.error:
                walkers.append((r.actor_id, speed))
                self.actor_ids.append(r.actor_id)
            else:
                failed.append(r.error)
        report_failures("walkers", len(batch), failed)
        ctrl_bp = lib.find("controller.ai.walker")
        results = self.client.apply_batch_sync(
            [carla.command.SpawnActor(ctrl_bp, carla.Transform(), wid) for wid, _ in walkers], True)
        started = [(r.actor_id, speed) for r, (_, speed) in zip(results, walkers, strict=True) if not r.error]
        report_failures("walker controllers", len(walkers), [r.error for r in results if r.error])
        self.controller_ids.extend(cid for cid, _ in started)  # destroyed on exit even if starting fails
        self.world.tick()  # controllers need one tick before they start
        for cid, speed in started:
            ctrl = self.world.get_actor(cid)
            ctrl.start()
            ctrl.go_to_location(self.world.get_random_location_from_navigation())
            ctrl.set_max_speed(speed)
            self.controllers.append(ctrl)

    def attach_sensors(self, specs) -> tuple[list[tuple], list[tuple]]:
        lib = self.world.get_blueprint_library()
        missing_attrs: dict[str, set] = {}
        for spec in specs:
            bp = lib.find(spec.blueprint)
            missing = set_blueprint_attributes(bp, spec.attributes)
            if missing:
                missing_attrs.setdefault(spec.blueprint, set()).update(missing)
            sensor = self.world.spawn_actor(bp, spec.mount.to_carla(self.carla), attach_to=self.ego)
            self.sensors[spec.key] = sensor
            self.queues[spec.key] = q = queue.Queue()
            sensor.listen(q.put)
        for bp_id, names in sorted(missing_attrs.items()):
            print(f"note: {bp_id} has no attribute(s) {', '.join(sorted(names))} in this CARLA release")
        dvs = [k for k in self.sensors if k[-1] == "dvs"]
        return [k for k in self.sensors if k[-1] != "dvs"], dvs

    # ------------------------------------------------------------------ ticks
    def _get(self, key: tuple, frame: int, timeout: float):
        deadline = time.monotonic() + timeout
        while True:
            remaining = deadline - time.monotonic()
            try:
                data = self.queues[key].get(timeout=remaining) if remaining > 0 else self.queues[key].get_nowait()
            except queue.Empty:
                return None
            if data.frame == frame:
                return data
            if data.frame > frame:  # should not happen in synchronous mode
                raise CarlaCaptureError(f"sensor {'/'.join(key)}: got frame {data.frame} while waiting for {frame}")
            missed = self.dvs_missed.get(key)
            if missed is not None and data.frame in missed:  # a DVS reading that came after --dvs-wait
                missed.discard(data.frame)
                print(f"warning: sensor {'/'.join(key)}: its reading of frame {data.frame} came after --dvs-wait "
                      f"{self.args.dvs_wait} s and was dropped (that frame lists it in carla_frame.json's dvs_missing); "
                      "raise --dvs-wait", file=sys.stderr)

    def warm_up(self) -> None:
        """One tick whose readings are not needed (sensors may skip their first frames): the
        queues are emptied without waiting; late readings are dropped by `tick` as stale."""
        self.world.tick()
        for q in self.queues.values():
            while True:
                try:
                    q.get_nowait()
                except queue.Empty:
                    break

    def tick(self, required: list[tuple], dvs: list[tuple]) -> dict:
        frame = self.world.tick()
        snapshot = self.world.get_snapshot()
        data: dict = {"frame": frame, "snapshot": snapshot}
        for key in required:
            item = self._get(key, frame, self.args.timeout)
            if item is None:
                raise CarlaCaptureError(f"sensor {'/'.join(key)}: no data for frame {frame} within {self.args.timeout} s")
            data[key] = convert(key, item)
        deadline = time.monotonic() + self.args.dvs_wait  # the DVS sends nothing when no pixel changed
        data["dvs_missing"] = []
        for key in dvs:
            item = self._get(key, frame, max(deadline - time.monotonic(), 0.0))
            if item is None:
                data["dvs_missing"].append(f"{key[1]}/{key[2]}")  # ("camera", cam, face, "dvs")
                missed = self.dvs_missed.setdefault(key, set())
                missed.add(frame)
                while len(missed) > 8:  # a reading later than 8 ticks never comes: forget the oldest
                    missed.discard(min(missed))
            data[key] = dvs_to_events(item, "/".join(key)) if item is not None else dvs_to_events(b"")
        return data

    # ------------------------------------------------------------------ teardown
    def destroy(self) -> None:
        carla = self.carla
        for sensor in self.sensors.values():
            try:
                sensor.stop()
            except RuntimeError:
                pass
        for ctrl in self.controllers:
            try:
                ctrl.stop()
            except RuntimeError:
                pass
        ids = [s.id for s in self.sensors.values()] + self.controller_ids + self.actor_ids
        if ids:
            self.client.apply_batch_sync([carla.command.DestroyActor(i) for i in ids], False)
        self.sensors.clear()
        self.controllers.clear()
        self.controller_ids.clear()
        self.actor_ids.clear()
        if self.tm is not None:
            self.tm.set_synchronous_mode(False)
        self.world.apply_settings(self.original_settings)


def report_failures(what: str, tried: int, errors: list) -> None:
    """Print how many of ``tried`` spawns of ``what`` failed, and the distinct reasons."""
    if errors:
        reasons = "; ".join(sorted({str(e) for e in errors})[:3])
        print(f"note: {len(errors)} of {tried} {what} failed to spawn ({reasons})")


def random_color(blueprint, rng: random.Random) -> None:
    """A random recommended colour for a vehicle blueprint (as SynWoodScape's random ego colour)."""
    if blueprint.has_attribute("color"):
        values = list(blueprint.get_attribute("color").recommended_values)
        if values:
            blueprint.set_attribute("color", rng.choice(values))


def convert(key: tuple, item):
    """One sensor reading -> the capture's array (see `jaxfish.io` conversions)."""
    what = "/".join(key)
    kind = key[-1]
    if kind in ("rgb", "depth", "semantic", "instance"):
        return image_to_bgra(item, what)
    return {"lidar": lidar_to_points, "semantic_lidar": semantic_lidar_to_records, "radar": radar_to_records,
            "imu": lambda m, _w: imu_to_dict(m), "gnss": lambda m, _w: gnss_to_dict(m)}[kind](item, what)


def images(tick: dict, prefix: tuple) -> CarlaImages:
    """The RGB/depth/semantic(/instance) BGRA arrays of one camera in a tick."""
    return CarlaImages(tick[prefix + ("rgb",)], tick[prefix + ("depth",)], tick[prefix + ("semantic",)],
                       tick.get(prefix + ("instance",)))


def vehicle_origin(args, rig, ego) -> tuple[float, float, float]:
    """Where the calibrations' vehicle origin is in the ego actor frame (``--vehicle-origin``)."""
    if args.vehicle_origin == "actor":
        return (0.0, 0.0, 0.0)
    if args.vehicle_origin != "auto":
        try:
            x, y, z = (float(v) for v in args.vehicle_origin.split(","))
        except ValueError as e:
            raise CarlaCaptureError(f"--vehicle-origin {args.vehicle_origin!r}: expected auto, actor or X,Y,Z") from e
        return (x, y, z)
    if all(c.flavor == "synwoodscape" for c in rig.values()):
        return (0.0, 0.0, 0.0)
    try:
        wheels = [w.position for w in ego.get_physics_control().wheels]
    except AttributeError as e:  # a release without WheelPhysicsControl.position
        raise CarlaCaptureError("cannot read the ego's wheel positions for --vehicle-origin auto; "
                                "pass --vehicle-origin X,Y,Z (metres, CARLA axes) or actor") from e
    return rear_axle_origin(wheels, carla_transform_tuple(ego.get_transform()))


def capture_config(args) -> CaptureConfig:
    """The `CaptureConfig` of the command line (sizes; the other sensor settings are jaxfish's defaults)."""
    return CaptureConfig(face_size=args.face_size, bev_size=args.bev_size, bev_metres_per_pixel=args.bev_metres_per_pixel,
                         front_width=args.front_size[0], front_height=args.front_size[1])


def capture_exposure(args) -> CarlaExposure:
    """The fixed exposure of the command line."""
    return CarlaExposure(args.shutter_speed, args.iso, args.fstop, args.exposure_compensation)


def dry_run(args, rig) -> None:
    """Print every sensor the capture would attach (blueprint, mount, attributes) for
    ``--carla-version``, without a server; the rig as given (vehicle origin: the actor's)."""
    config = capture_config(args)
    specs = capture_sensor_specs(rig, config, sensor_mounts(rig, config), carla_version=args.carla_version,
                                 bev_altitude_m=args.bev_altitude, exposure=capture_exposure(args))
    print(f"{len(specs)} sensors for CARLA {args.carla_version} (tags {carla_semantic_tags(args.carla_version)}):")
    for spec in specs:
        loc = ", ".join(f"{v:.3f}" for v in spec.mount.location)
        rot = ", ".join(f"{v:.2f}" for v in spec.mount.rotation)
        attrs = " ".join(f"{k}={v}" for k, v in spec.attributes.items())
        print(f"{'/'.join(spec.key):28s} {spec.blueprint:38s} location ({loc}) rotation ({rot}) {attrs}")


def warn_undersampled(face_size: int, rig) -> None:
    """``warning: ...`` on stderr when ``face_size``-px cube faces undersample one of the rig's
    fisheyes (`jaxfish.reprojection.warn_undersampled_faces`), as ``jaxfish synth`` warns."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UndersampledFacesWarning)
        message = warn_undersampled_faces(face_size, {name: calib.camera for name, calib in rig.items()})
    if message:
        print(f"warning: {message}", file=sys.stderr)


def capture_weather(carla, client, args, weather: str, rig_file) -> Path:
    """Spawn everything, capture ``args.frames`` frames under ``weather`` into ``OUT/weather``.

    The capture folder must be new, empty or a jaxfish capture (`jaxfish.io.check_capture_folder`);
    it is locked before anything is spawned and while the capture is written (a second writer
    raises `CarlaCaptureError`), and the temporary files a killed run left there are removed."""
    root = check_capture_folder(args.out / weather)
    root.mkdir(parents=True, exist_ok=True)
    with folder_lock(root, CarlaCaptureError, "capture writer"):
        remove_temporaries(root)
        _capture_locked(carla, client, args, weather, rig_file, root)
    return root


class Rigged:
    """A session's rig and sensors once set up (`set_up`): what every frame of it needs."""

    def __init__(self, rig, config, raised, specs, version, tags, required, dvs):
        self.rig, self.config, self.raised, self.specs = rig, config, raised, specs
        self.version, self.tags, self.required, self.dvs = version, tags, required, dvs

    def views(self, args, names=("bev", "front")) -> dict:
        """``{name: (camera, camera_to_vehicle)}`` of the views whose height maps are computed."""
        cameras = {"bev": (bev_pinhole(self.config, args.bev_altitude), self.raised.bev_camera_to_vehicle),
                   "front": (front_camera(self.config), self.raised.front_camera_to_vehicle)}
        return {n: cameras[n] for n in names}


def set_up(session, carla, client, args, weather: str, rig_file, header_root: Path | None, *,
           online: bool = False) -> Rigged:
    """Synchronous mode, the weather, the ego (and the rig moved onto it), traffic, every sensor,
    the warm-up ticks; with ``header_root`` also the capture's header files (`write_capture_header`,
    `finish_carla_header`). ``online``: without the sensors a dataset does not use (the front view,
    the instance cameras)."""
    version = client.get_server_version()
    config, exposure = capture_config(args), capture_exposure(args)
    rng = random.Random(args.seed)
    session.synchronous()
    session.world.set_weather(getattr(carla.WeatherParameters, weather))
    points = session.spawn_ego(rng)
    session.world.tick()  # the ego's physics (wheel positions) exist after a tick
    rig = rig_on_actor(rig_file, vehicle_origin(args, rig_file, session.ego))
    session.spawn_traffic(rng, points)
    mounts = sensor_mounts(rig, config)
    specs = capture_sensor_specs(rig, config, mounts, carla_version=version, bev_altitude_m=args.bev_altitude,
                                 exposure=exposure)
    if online:
        specs = [spec for spec in specs if spec.key[:2] != ("view", "front") and spec.key[-1] != "instance"]
    raised = with_bev_altitude(mounts, bev_altitude_m=args.bev_altitude)
    if header_root is not None:
        write_capture_header(header_root, rig, config, raised, seed=args.seed, source="carla", dt_s=DT_S)
        finish_carla_header(header_root, carla_version=version, mounts=sensor_carla_mounts(raised),
                            bev_altitude_m=args.bev_altitude, config=config,
                            geo=carla_geo_reference(session.world.get_map(), carla),
                            extra={"town": session.world.get_map().name, "weather": weather})
    required, dvs = session.attach_sensors(specs)
    print(f"[{weather}] {len(specs)} sensors on the ego, {len(session.actor_ids) - 1} other actors; "
          f"warming up {args.warmup} ticks")
    for _ in range(args.warmup - 1):
        session.warm_up()
    return Rigged(rig, config, raised, specs, version, carla_semantic_tags(version), required, dvs)


def _capture_locked(carla, client, args, weather: str, rig_file, root: Path) -> None:
    session = Session(carla, client, args)
    try:
        rigged = set_up(session, carla, client, args, weather, rig_file, root)
        rig, config, tags, required, dvs = rigged.rig, rigged.config, rigged.tags, rigged.required, rigged.dvs
        views = rigged.views(args)
        prev = session.tick(required, dvs)
        start = time.monotonic()
        # One writer thread: frame k is encoded and written while the server simulates the next ticks
        # (one thread only, so that frames reach capture.json in order); at most two frames wait.
        writer = ThreadPoolExecutor(max_workers=1, thread_name_prefix="capture-writer")
        pending: deque = deque()
        done = 0
        try:
            for k in range(args.frames):
                curr = session.tick(required, dvs)
                pending.append(writer.submit(frame_writer(root, k, prev, curr, session, rig, config, views, tags)))
                prev = curr
                while pending and (len(pending) > 2 or k == args.frames - 1):
                    pending.popleft().result()  # re-raises a writing error here
                    done += 1
                    rate = done / max(time.monotonic() - start, 1e-9)
                    print(f"[{weather}] frame {done}/{args.frames} written ({rate:.2f} frames/s)", flush=True)
        finally:
            writer.shutdown(wait=True)
    finally:
        session.destroy()


def online_frames(session, rigged: Rigged, args, cameras):
    """Tick the world and yield every frame (`jaxfish.pipeline.Frame`, `jaxfish.carla.carla_frame`)
    of the capture as the reader of the offline mode's files would decode it, its fisheye cameras
    in the order ``cameras``: the cube faces, the BEV and the other sensors stay in memory. The
    world ticks when the consumer asks for the next frame."""
    views = rigged.views(args, names=("bev",))
    prev = session.tick(rigged.required, rigged.dvs)
    for k in range(args.frames):
        curr = session.tick(rigged.required, rigged.dvs)
        street = street_frame(k, prev, curr, session, rigged.tags)
        faces, out_views, sensors = frame_arrays(prev, curr, cameras, rigged.config, views)
        yield carla_frame(street, tag_table=rigged.tags, faces=faces, bev=out_views["bev"], **sensors)
        prev = curr


def online_source(session, rigged: Rigged, args, settings: dict) -> CarlaSource:
    """The session as the dataset builder's source: frame ``k`` is ticked when the builder reads it."""
    state: dict = {}

    def next_frame(k: int):
        if "frames" not in state:
            state["frames"] = online_frames(session, rigged, args, source.cameras)
        return next(state["frames"])

    source = CarlaSource(rigged.rig, config=rigged.config, bev_camera_to_vehicle=rigged.raised.bev_camera_to_vehicle,
                         carla_version=rigged.version, frames=args.frames, next_frame=next_frame, settings=settings,
                         seed=args.seed, dt_s=DT_S)
    return source


def build_weather(carla, client, args, weather: str, rig_file) -> Path:
    """Spawn everything and build the dataset of ``args.frames`` frames under ``weather`` into
    ``BUILD/weather`` while the world ticks (`jaxfish.dataset.build_dataset` of a
    `jaxfish.carla.CarlaSource`), without writing a capture.

    The folder must be new, empty or a jaxfish dataset without samples (a live session cannot
    resume an earlier build); it is checked, and its lock tried, before anything is spawned (a
    second writer raises `jaxfish.dataset.DatasetError`). A sample that fails is reported and the
    program exits with status 2 after the others."""
    from jaxfish.dataset import DONE_DIR, DatasetError, build_dataset, check_output_folder

    out = check_output_folder(args.build / weather)
    if any((out / DONE_DIR).glob("*.json")):
        raise CarlaCaptureError(f"{out}: holds samples of an earlier build; a build while capturing cannot resume it "
                                "(it is another simulation): use a new or empty folder")
    out.mkdir(parents=True, exist_ok=True)
    with folder_lock(out, DatasetError, "build"):  # another writer: refused before anything is spawned
        pass
    session = Session(carla, client, args)
    start = time.monotonic()
    done = 0

    def progress(sample: str, error: str | None) -> None:
        nonlocal done
        done += 1
        rate = done / max(time.monotonic() - start, 1e-9)
        state = "built" if error is None else f"failed: {error}"
        print(f"[{weather}] sample {sample} {state} ({done}/{args.frames}, {rate:.2f} samples/s)", flush=True)

    try:
        rigged = set_up(session, carla, client, args, weather, rig_file, None, online=True)
        settings = {"town": session.world.get_map().name, "weather": weather, "session": uuid.uuid4().hex}
        start = time.monotonic()
        report = build_dataset(online_source(session, rigged, args, settings), out, progress=progress)
    finally:
        session.destroy()
    if report.failed:
        first = sorted(report.failed)[0]
        raise CarlaCaptureError(f"{out}: {len(report.failed)} of {len(report.samples)} samples failed (sample {first}: "
                                f"{report.failed[first]})")
    return out


def street_frame(k: int, prev: dict, curr: dict, session, tags: str):
    """Frame ``k``'s actor and ego records (`jaxfish.scene.StreetFrame`) from the ticks t-1
    (``prev``) and t (``curr``): the world's actors are read from the server now."""
    snap_p, snap_c = prev["snapshot"], curr["snapshot"]
    ego_id = session.ego.id
    world_actors = session.world.get_actors()
    actors = list(world_actors.filter("vehicle.*")) + list(world_actors.filter("walker.pedestrian.*"))
    records = carla_actor_records(actors, snap_p, snap_c, ego_id=ego_id, tag_table=tags)
    return carla_street_frame(k, snap_c.timestamp.elapsed_seconds, records, carla_ego_motion(snap_c.find(ego_id)),
                              dt_s=DT_S, seed=session.args.seed)


def frame_arrays(prev: dict, curr: dict, cameras, config, views: dict) -> tuple[dict, dict, dict]:
    """``(faces, views, sensors)`` of the ticks t-1 (``prev``) and t (``curr``) as `write_carla_frame`
    takes them: ``faces[camera][face] = (prev, curr, dvs events)`` in the capture's face order,
    ``views[name] = (prev, curr, height map at t)`` for the views of ``views`` (``{name: (camera,
    camera_to_vehicle)}``), and the lidar, radar, IMU and GNSS readings at t."""
    faces = {cam: {f: (images(prev, ("camera", cam, f)), images(curr, ("camera", cam, f)),
                       curr[("camera", cam, f, "dvs")]) for f in config.faces} for cam in cameras}
    out_views = {}
    for name, (camera, pose) in views.items():
        c = images(curr, ("view", name))
        height = height_from_depth(decode_depth(c.depth), camera, pose)
        out_views[name] = (images(prev, ("view", name)), c, height)
    sensors = {name: curr[(name,)] for name in ("lidar", "semantic_lidar", "radar", "imu", "gnss")}
    return faces, out_views, sensors


def frame_writer(root, k, prev, curr, session, rig, config, views, tags):
    """Assemble frame ``k`` from the ticks t-1 (``prev``) and t (``curr``): the actor records are read
    from the server now; the returned function converts and writes the frame (any thread)."""
    frame = street_frame(k, prev, curr, session, tags)

    def write() -> None:
        faces, out_views, sensors = frame_arrays(prev, curr, rig, config, views)
        write_carla_frame(root, frame, faces=faces, views=out_views, prev_from_frame=k - 1 if k > 0 else None,
                          dvs_missing=curr["dvs_missing"], **sensors)

    return write


def load_calibrations(directory: Path) -> dict:
    """Every ``*.json`` calibration of a directory (``FV, MVL, MVR, RV`` first)."""
    names = rig_names(directory) if directory.is_dir() else ()
    if not names:
        raise CarlaCaptureError(f"--calibration {directory}: no calibration JSON files there")
    return load_rig(directory, names=names)


def main(argv: list[str] | None = None) -> int:
    """Run the capture; 0 on success, 2 on a bad input or CARLA error (with the reason)."""
    args = parse_args(argv)
    try:
        weathers = validate_weather(args.weather or ["ClearNoon"])
        rig = load_calibrations(args.calibration) if args.calibration else default_rig()
        warn_undersampled(args.face_size, rig)
        if args.dry_run:
            parse_carla_version(args.carla_version)
            dry_run(args, rig)
            return 0
        carla = import_carla()
        validate_weather(weathers, carla=carla)
        client = carla.Client(args.host, args.port)
        client.set_timeout(args.timeout)
        server, client_version = client.get_server_version(), client.get_client_version()
        parse_carla_version(server)
        if server.split("-")[0] != client_version.split("-")[0]:
            print(f"warning: carla client {client_version} and server {server} differ; install carla=={server}")
        if args.town:
            client.load_world(args.town)
        for weather in weathers:
            if args.build is not None:
                out = build_weather(carla, client, args, weather, rig)
                print(f"[{weather}] dataset built in {out}")
            else:
                out = capture_weather(carla, client, args, weather, rig)
                print(f"[{weather}] capture written to {out}")
    except (JaxfishError, FileNotFoundError) as e:  # bad options, calibration files, unknown presets
        print(f"error: {e}", file=sys.stderr)
        return 2
    except RuntimeError as e:  # CARLA's client raises RuntimeError (time-outs, lost connection)
        print(f"error: CARLA: {e}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
