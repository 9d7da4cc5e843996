"""Label files: index PNGs (``gtLabels``), colour PNGs (``rgbLabels``) carrying their palette as
metadata, 2D box CSV (WoodScape format), 3D box pickle, depth ``.npy`` and the per-actor
displacement text file."""

from __future__ import annotations

import functools
import math
import os
import pickle
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from .._errors import ImageError
from ._atomic import atomic_path, atomic_write_bytes, atomic_write_text
from ._images import PNG_LEVEL, read_image, read_image_metadata, write_image
from ._json import write_json

PALETTE_ATTRIBUTE = "jaxfish:palette"
"""Metadata key of the palette JSON in colour label PNGs."""


def write_label_png(path: str | os.PathLike, labels: np.ndarray, *, png_level: int = PNG_LEVEL) -> Path:
    """Index PNG of a label map (uint8 if every label fits, else uint16); negative labels -> 0."""
    a = np.asarray(labels)
    if a.ndim != 2:
        raise ImageError(f"{path}: labels must be (H, W), got {a.shape}")
    a = np.clip(a.astype(np.int64), 0, None)
    dtype = np.uint8 if a.max(initial=0) < 256 else np.uint16
    if a.max(initial=0) > 65535:
        raise ImageError(f"{path}: labels above 65535 do not fit a PNG")
    return write_image(path, a.astype(dtype), png_level=png_level)


def read_label_png(path: str | os.PathLike) -> np.ndarray:
    """Read an index PNG as ``(H, W)`` int32; a file that is not a PNG by content (a JPEG renamed
    ``.png``: wrong labels) raises `ImageError` naming it."""
    return read_image(path, lossless=True)[..., 0].astype(np.int32)


def write_color_png(path: str | os.PathLike, rgb: np.ndarray, palette: Mapping[str, Any] | None = None, *,
                    png_level: int = PNG_LEVEL) -> Path:
    """RGB uint8 PNG with ``palette`` (JSON-able, e.g. ``{"classes": [...], "colors": [...]}``)
    stored as the PNG text attribute `PALETTE_ATTRIBUTE` (atomic)."""
    path = Path(path)
    a = np.ascontiguousarray(np.asarray(rgb, np.uint8))
    if a.ndim != 3 or a.shape[-1] != 3:
        raise ImageError(f"{path}: colour labels must be (H, W, 3) uint8, got {a.shape}")
    return write_image(path, a, metadata=None if palette is None else {PALETTE_ATTRIBUTE: palette}, png_level=png_level)


def read_palette(path: str | os.PathLike) -> dict[str, Any]:
    """The palette stored in a colour PNG by `write_color_png`."""
    return read_image_metadata(path, PALETTE_ATTRIBUTE)


def synwoodscape_palette_dict() -> dict[str, Any]:
    """The SynWoodScape palette as metadata: ``{"classes": names, "colors": [[r, g, b], ...]}``
    (also the content of a ``seg_annotation_info.json``)."""
    from ..groundtruth import SYNWOODSCAPE_CLASSES, SYNWOODSCAPE_PALETTE

    return {"classes": list(SYNWOODSCAPE_CLASSES), "colors": SYNWOODSCAPE_PALETTE.astype(int).tolist()}


def write_boxes_2d_csv(path: str | os.PathLike, rows: Sequence[tuple[str, int, int, int, int, int]]) -> Path:
    """WoodScape 2D box file: one line ``class_name,class_id,x1,y1,x2,y2`` per box (integer pixel
    coordinates of the extreme pixels, pixel-centre convention, inclusive); empty file if none."""
    lines = []
    for r in rows:
        name, cid, x1, y1, x2, y2 = r
        if "," in str(name):
            raise ImageError(f"{path}: class name {name!r} contains a comma")
        lines.append(f"{name},{int(cid)},{int(x1)},{int(y1)},{int(x2)},{int(y2)}")
    return atomic_write_text(path, "".join(line + "\n" for line in lines))


def read_boxes_2d_csv(path: str | os.PathLike) -> list[tuple[str, int, int, int, int, int]]:
    """Read a WoodScape 2D box file (spaces after commas tolerated)."""
    path = Path(path)
    if not path.is_file():
        raise ImageError(f"{path}: file missing")
    out = []
    for i, line in enumerate(path.read_text().splitlines(), 1):
        if not line.strip():
            continue
        parts = [p.strip() for p in line.split(",")]
        if len(parts) != 6:
            raise ImageError(f"{path}:{i}: expected 6 fields class_name,class_id,x1,y1,x2,y2, got {len(parts)}")
        try:
            out.append((parts[0], *(int(float(p)) for p in parts[1:])))
        except ValueError as e:
            raise ImageError(f"{path}:{i}: non-numeric field ({e})") from e
    return out  # type: ignore[return-value]


def boxes_2d_rows(xyxy: np.ndarray, present: np.ndarray, class_id: np.ndarray) -> list[tuple[str, int, int, int, int, int]]:
    """CSV rows of the present boxes (`jaxfish.groundtruth.Boxes2D` arrays and box classes)."""
    from ..groundtruth import SYNWOODSCAPE_CLASSES

    rows = []
    for b, c, p in zip(np.asarray(xyxy), np.asarray(class_id), np.asarray(present), strict=True):
        if p and 0 <= int(c) < len(SYNWOODSCAPE_CLASSES):
            rows.append((SYNWOODSCAPE_CLASSES[int(c)], int(c), *(int(v) for v in b)))
    return rows  # type: ignore[return-value]


def write_boxes_3d_pickle(path: str | os.PathLike, boxes: Mapping[int, Any]) -> Path:
    """3D boxes in SynWoodScape's released format: a pickle ``{actor_id (int): (8, 3) float64 corners
    in CARLA world coordinates}`` (order `jaxfish.groundtruth.CORNER_SIGNS`), every actor, no class
    (the class and vehicle-frame corners go to `write_boxes_3d_ext_json`)."""
    clean = {}
    for k, v in sorted(boxes.items()):
        try:
            a = np.asarray(v, np.float64)
        except (TypeError, ValueError) as e:
            raise ImageError(f"{path}: box {k}: corners must be an (8, 3) array of numbers ({e})") from e
        if a.shape != (8, 3):
            raise ImageError(f"{path}: box {k}: corners must be (8, 3), got {a.shape}")
        if not np.all(np.isfinite(a)):
            raise ImageError(f"{path}: not written: box {k}: corners are not finite numbers")
        clean[int(k)] = a
    return atomic_write_bytes(path, pickle.dumps(clean, protocol=4))


def write_boxes_3d_ext_json(path: str | os.PathLike, boxes: Mapping[int, Mapping[str, Any]]) -> Path:
    """jaxfish's extra 3D box file (JSON): ``{"frames": ..., "boxes": [{"actor_id", "class_id",
    "class_name", "corners_world" (8 x 3, CARLA world), "corners_vehicle" (8 x 3, ISO 8855 vehicle
    frame at t)}, ...]}`` in actor-id order."""
    rows = []
    for k, v in sorted(boxes.items()):
        rows.append({"actor_id": int(k), "class_id": int(v["class_id"]), "class_name": str(v["class_name"]),
                     "corners_world": np.round(np.asarray(v["corners_world"], np.float64), 6).tolist(),
                     "corners_vehicle": np.round(np.asarray(v["corners_vehicle"], np.float64), 6).tolist()})
    doc = {"frames": {"corners_world": "CARLA world (x forward, y right, z up; left-handed), metres",
                      "corners_vehicle": "ISO 8855 ego vehicle frame at t (x forward, y left, z up), metres"},
           "corner_order": "index = 4 ix + 2 iy + iz over the signs (-, +) of the box axes (CARLA get_local_vertices)",
           "boxes": rows}
    return write_json(path, doc, indent=1, error=ImageError)


def read_boxes_3d_pickle(path: str | os.PathLike) -> dict[int, Any]:
    """Read a 3D box pickle ``{actor_id: (8, 3) corners}`` (trusted files only: pickle runs code)."""
    path = Path(path)
    if not path.is_file():
        raise ImageError(f"{path}: file missing")
    with open(path, "rb") as fh:
        return pickle.load(fh)


def write_displacements(path: str | os.PathLike, actor_id: Sequence[int], class_id: Sequence[int],
                        displacement_m: Sequence[float], *, threshold_m: float) -> Path:
    """Text file of every actor's displacement between t-1 and t: a header line, then
    ``actor_id class_id displacement_m moving`` per actor (moving = displacement > threshold)."""
    lines = [f"# actor_id class_id displacement_m moving(threshold_m={threshold_m:g})"]
    for a, c, d in zip(actor_id, class_id, displacement_m, strict=True):
        if not math.isfinite(float(d)):
            raise ImageError(f"{path}: not written: the displacement of actor {int(a)} is not a finite number ({float(d)})")
        lines.append(f"{int(a)} {int(c)} {float(d):.6f} {int(float(d) > threshold_m)}")
    return atomic_write_text(path, "\n".join(lines) + "\n")


def read_displacements(path: str | os.PathLike) -> dict[int, float]:
    """Read `write_displacements`' file: ``{actor_id: displacement_m}``."""
    path = Path(path)
    if not path.is_file():
        raise ImageError(f"{path}: file missing")
    out = {}
    for i, line in enumerate(path.read_text().splitlines(), 1):
        if not line.strip() or line.startswith("#"):
            continue
        parts = line.split()
        if len(parts) != 4:
            raise ImageError(f"{path}:{i}: expected 4 fields, got {len(parts)}")
        out[int(parts[0])] = float(parts[2])
    return out


def write_depth_npy(path: str | os.PathLike, depth_m: np.ndarray) -> Path:
    """Depth map as float32 ``.npy`` (metres; range or z-depth as documented by the caller; sky 1000)."""
    path = Path(path)
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        np.save(fh, np.asarray(depth_m, np.float32), allow_pickle=False)
    return path


DEPTH_ATTRIBUTE = "jaxfish:depth"
"""Metadata key of the definition JSON in the depth EXRs written by `write_depth_exr`."""


def write_depth_exr(path: str | os.PathLike, depth_m: np.ndarray, definition: Mapping[str, Any] | None = None) -> Path:
    """Depth map as a one-channel float32 OpenEXR (channel ``Z``, uncompressed: 3x faster to write
    than zip for 20 % more bytes), with ``definition`` (JSON-able: what the values are) stored as
    the text attribute `DEPTH_ATTRIBUTE`; atomic. Read it back with `read_depth_exr`."""
    d = np.asarray(depth_m, np.float32)
    if d.ndim != 2:
        raise ImageError(f"{path}: depth must be (H, W), got {d.shape}")
    return write_image(path, d, channel_names=("Z",), exr_compression="none",
                       metadata=None if definition is None else {DEPTH_ATTRIBUTE: dict(definition)})


def read_depth_exr(path: str | os.PathLike) -> np.ndarray:
    """A depth EXR written by `write_depth_exr` as ``(H, W)`` float32 metres."""
    a = read_image(path)
    if a.shape[-1] != 1 or a.dtype != np.float32:
        raise ImageError(f"{path}: expected a one-channel float32 depth EXR, got {a.dtype} {a.shape}")
    return a[..., 0]


RANGE_DEPTH_DEFINITION = {"quantity": "Euclidean range along the pixel's ray (not planar z-depth)", "unit": "m",
                          "sky_m": 1000.0, "no_ray": 0.0, "instant": "t"}
"""What the dataset's depth EXRs hold (their `DEPTH_ATTRIBUTE` metadata)."""


def write_npz(path: str | os.PathLike, **arrays: np.ndarray) -> Path:
    """``np.savez``-compatible ``.npz`` with fixed zip timestamps (1980-01-01), so the same arrays
    always give the same bytes (``np.savez`` stamps the current time); atomic, no pickle."""
    import zipfile

    path = Path(path)
    with atomic_path(path) as tmp, zipfile.ZipFile(tmp, "w", compression=zipfile.ZIP_STORED) as zf:
        for name, arr in arrays.items():
            info = zipfile.ZipInfo(f"{name}.npy", date_time=(1980, 1, 1, 0, 0, 0))
            info.compress_type = zipfile.ZIP_STORED
            with zf.open(info, "w", force_zip64=True) as fh:
                np.lib.format.write_array(fh, np.asanyarray(arr), allow_pickle=False)
    return path


DEPTH_COLOR_RANGE_M = (0.5, 100.0)
"""Range (metres) spanned by the depth colour map: nearer is brightest, farther darkest."""
_MAGMA = np.asarray([[0, 0, 4], [59, 15, 112], [140, 41, 129], [222, 73, 104], [254, 159, 109], [252, 253, 191]], np.float64)


def depth_to_color(depth_m: np.ndarray) -> np.ndarray:
    """Colour rendering of a depth map (``depth_maps/colormap``): magma-like ramp on log depth over
    `DEPTH_COLOR_RANGE_M` (near = bright yellow, far = dark purple); 0 (no ray) and the sky (1000)
    are black. ``(H, W)`` metres -> ``(H, W, 3)`` uint8."""
    d = np.asarray(depth_m, np.float32)
    lo, hi = DEPTH_COLOR_RANGE_M
    # float32 (3x faster than float64 on a full frame): at most one step of the 1024-step ramp apart.
    scale = np.float32(1023.0 / (np.log(hi) - np.log(lo)))
    x = np.float32(1023.0) - (np.log(np.clip(d, np.float32(lo), np.float32(hi))) - np.float32(np.log(lo))) * scale
    idx = np.clip(np.rint(x), 0, 1023).astype(np.intp)
    # One 3-byte gather per pixel (a row gather of the (1024, 3) table is 5x slower).
    out = _depth_ramp().view("V3").reshape(-1)[idx].view(np.uint8).reshape(idx.shape + (3,))
    out[~((d > 0) & (d < 999.0))] = 0
    return out


@functools.cache
def _depth_ramp() -> np.ndarray:
    """The 1024 x 3 uint8 colour table of `depth_to_color` (far -> near)."""
    ramp = np.linspace(0.0, len(_MAGMA) - 1, 1024)
    return np.rint(np.stack([np.interp(ramp, np.arange(len(_MAGMA)), _MAGMA[:, c]) for c in range(3)], -1)).astype(np.uint8)


def events_color(events: np.ndarray, *, width: int, height: int) -> np.ndarray:
    """NumPy twin of `jaxfish.groundtruth.events_to_color` (no recompilation per event count):
    white background, blue ``(0, 0, 255)`` where a pixel's events sum to a net positive polarity,
    red ``(255, 0, 0)`` net negative. ``(H, W, 3)`` uint8."""
    ev = np.asarray(events)
    x, y = ev["x"].astype(np.int64), ev["y"].astype(np.int64)
    pol = ev["pol"] if "pol" in (ev.dtype.names or ()) else ev["p"] > 0
    ok = (x >= 0) & (x < width) & (y >= 0) & (y < height)
    net = np.zeros(width * height, np.int64)
    np.add.at(net, (y * width + x)[ok], np.where(pol, 1, -1)[ok])
    net = net.reshape(height, width)
    out = np.full((height, width, 3), 255, np.uint8)
    out[net > 0] = (0, 0, 255)
    out[net < 0] = (255, 0, 0)
    return out


def map_face_events(targets: np.ndarray, width: int, face_size: int, face: np.ndarray, x: np.ndarray, y: np.ndarray,
                    t: np.ndarray, pol: np.ndarray, fanout: np.ndarray | None = None) -> np.ndarray:
    """NumPy twin of `jaxfish.groundtruth.map_events` + `compact_events` (same rule, same order:
    stable sort by time, ties in face-event then fisheye-pixel order) for an `EventMap`'s
    ``targets`` (and ``fanout``, derived from ``targets`` when omitted); returns CARLA-dtype
    fisheye events (t unchanged, ns)."""
    from ._carla import DVS_EVENT_DTYPE

    tg_all = np.asarray(targets)
    n_src = tg_all.shape[0]
    fan = np.sum(tg_all >= 0, axis=1) if fanout is None else np.asarray(fanout)
    s = int(face_size)
    f, xi, yi = (np.asarray(a, np.int64) for a in (face, x, y))
    inb = (f >= 0) & (xi >= 0) & (xi < s) & (yi >= 0) & (yi < s)
    src = (f * s + yi) * s + xi
    inb &= (src >= 0) & (src < n_src)
    src = np.where(inb, src, 0)
    counts = np.where(inb, fan[src], 0)
    ev_idx = np.repeat(np.arange(src.shape[0]), counts)  # each face event, once per fisheye pixel it feeds
    slot = np.arange(ev_idx.shape[0]) - np.repeat(np.cumsum(counts) - counts, counts)
    flat = tg_all[src[ev_idx], slot]
    tt = np.asarray(t, np.int64)[ev_idx]
    order = np.argsort(tt, kind="stable")
    out = np.empty(order.shape[0], DVS_EVENT_DTYPE)
    out["x"], out["y"] = flat[order] % width, flat[order] // width
    out["t"], out["pol"] = tt[order], np.asarray(pol, bool)[ev_idx][order]
    return out


# ---------------------------------------------------------------------------- capture -> ground truth
BOX_SLOT_QUANTUM = 32
"""Box slots are allocated in multiples of this many (inactive padding), so that frames whose actor
counts differ (CARLA spawns and removes actors) share compiled programs instead of compiling per count."""


def box_slots(num_actors: int) -> int:
    """The number of box slots for ``num_actors`` actors: the next multiple of `BOX_SLOT_QUANTUM`
    (at least one quantum). Padding changes no output: inactive boxes own no pixel and no file row."""
    q = BOX_SLOT_QUANTUM
    return max(q, -(-int(num_actors) // q) * q)


def _frame_motion(reader, frame: int, pad: int | None = None, actors: list | None = None):
    """``(actors, boxes at t-1, boxes at t, vehicle -> world at t-1, at t)`` of a capture frame (the
    boxes padded to ``pad`` slots, default `box_slots`; ``actors``: the frame's ``actors.json``
    records when already read); a malformed ``actors.json`` / ``ego.json`` raises `CaptureError`
    naming the frame."""
    from .. import groundtruth as gt
    from ._capture import CaptureError

    actors = reader.actors(frame) if actors is None else actors  # names the frame when it is missing
    ego = reader.ego(frame)
    try:
        pad = box_slots(len(actors)) if pad is None else int(pad)
        boxes_prev = gt.boxes_from_actors(actors, "t-1", pad_to=pad)
        boxes = gt.boxes_from_actors(actors, "t", pad_to=pad)
        v2w_p = gt.vehicle_to_world_from_carla(np.asarray(ego["transform_prev"]["location"], np.float32),
                                               np.asarray(ego["transform_prev"]["rotation"], np.float32))
        v2w = gt.vehicle_to_world_from_carla(np.asarray(ego["transform"]["location"], np.float32),
                                             np.asarray(ego["transform"]["rotation"], np.float32))
    except (KeyError, TypeError, ValueError) as e:
        raise CaptureError(f"{reader.root}: frame {frame}: malformed actors.json / ego.json ({e})") from e
    return actors, boxes_prev, boxes, v2w_p, v2w


def _carla_version(reader, carla_version: str | None) -> str:
    return carla_version or str(reader.meta.get("carla_semantic_tags", "0.9.10"))  # checked by CaptureReader


def capture_ground_truth(reader, frame: int, camera: str, *, lut=None, rays=None, event_map=None,
                         backward_flow: bool = False, carla_version: str | None = None,
                         **options: Any) -> dict[str, Any]:
    """Everything `jaxfish.groundtruth.fisheye_ground_truth` computes for one fisheye camera of a
    capture frame (`CaptureReader`), plus its events mapped to the fisheye
    (`capture_rig_ground_truth` of this one camera).

    ``lut`` (cube -> fisheye `Lut` of this camera), ``rays`` (`pixel_rays`) and ``event_map``
    (`jaxfish.groundtruth.event_map_from_lut` of the LUT) are per-calibration constants: pass them
    when processing many frames (built here otherwise). Returns ``{"truth": CameraGroundTruth,
    "boxes_prev", "boxes": Boxes3D, "vehicle_to_world_prev", "vehicle_to_world": Pose, "events":
    CARLA-dtype fisheye events (t in ns, time order), "camera": the fisheye model, "rays": its
    `pixel_rays`, "actors": the actor records}``.
    """
    return capture_rig_ground_truth(reader, frame, [camera], constants={camera: (lut, rays, event_map)},
                                    backward_flow=backward_flow, carla_version=carla_version, **options)[0]


def camera_events(reader, frame: int, camera: str, event_map) -> np.ndarray:
    """The DVS events of a capture camera's faces mapped to its fisheye through ``event_map``
    (`jaxfish.groundtruth.event_map_from_lut`): CARLA-dtype events, t in ns, time order."""
    cols = {k: [] for k in ("face", "x", "y", "t", "pol")}
    for i, face in enumerate(reader.faces):
        ev = reader.dvs(frame, camera, face)
        cols["face"].append(np.full(ev.shape[0], i, np.int32))
        for k in ("x", "y", "t", "pol"):
            cols[k].append(ev[k])
    cat = {k: np.concatenate(v) for k, v in cols.items()}
    return map_face_events(np.asarray(event_map.targets), int(event_map.width), int(event_map.face_size), cat["face"],
                           cat["x"], cat["y"], cat["t"], cat["pol"], fanout=np.asarray(event_map.fanout))


def capture_rig_ground_truth(reader, frame: int | Sequence[int], cameras: Sequence[str] | None = None, *,
                             constants=None, backward_flow: bool = False, carla_version: str | None = None,
                             batch: str = "auto", **options: Any) -> list:
    """`capture_ground_truth` for several fisheye cameras of a capture frame at once (default: all
    of them, in `CaptureReader.cameras` order), through `jaxfish.groundtruth.rig_ground_truth`:
    the faces of every camera are decoded in one pool of threads, and ``batch`` chooses how the
    cameras are mapped (``"auto"``: a loop of per-camera programs on CPU, `jax.vmap` elsewhere).

    ``frame`` may also be a sequence of frames: they are computed together (one
    `rig_ground_truth` call with a sample axis, their boxes padded to one `box_slots` size) and the
    result is one list per frame. On CPU (loop mode) each frame's values are those of a call with
    that frame alone; with ``batch="vmap"`` they agree to float32 rounding.

    ``constants`` ``{camera: (lut, rays, event_map)}``: the per-calibration constants (those
    missing or None are built here). Returns one `capture_ground_truth` result dict per camera, in
    order (a list of such lists for a sequence of frames)."""
    import concurrent.futures

    import jax
    import jax.numpy as jnp

    from .. import groundtruth as gt
    from ..scene import CameraImages
    from ..transforms import Pose
    from ._capture import CaptureError

    single = isinstance(frame, (int, np.integer))
    frames = [int(frame)] if single else [int(f) for f in frame]
    if not frames:
        raise CaptureError(f"{reader.root}: no frame to compute (an empty sequence of frames)")
    rig = reader.rig()
    names = list(reader.cameras if cameras is None else cameras)
    if not names:
        raise CaptureError(f"{reader.root / 'capture.json'}: no camera to compute (field 'cameras' is empty)")
    missing = [c for c in names if c not in rig]
    if missing:
        raise CaptureError(f"{reader.root}/calibration: camera(s) {missing} missing (have {sorted(rig)})")
    calibs = [rig[c].astype(jnp.float32) for c in names]
    cams = [cal.camera.astype(jnp.float32) for cal in calibs]
    given, constants = constants or {}, {}
    for c, cam in zip(names, cams, strict=True):
        lut, rays, emap = given.get(c) or (None, None, None)
        constants[c] = fisheye_constants(reader, c, cam, frame=frames[0], lut=lut, rays=rays, event_map=emap)
    records = [reader.actors(f) for f in frames]
    pad = box_slots(max(len(r) for r in records))  # one box size for the whole batch
    motions = [_frame_motion(reader, f, pad, r) for f, r in zip(frames, records, strict=True)]
    version = _carla_version(reader, carla_version)
    jobs = [(f, c, inst, face) for f in frames for inst in ("prev", "curr") for c in names for face in reader.faces]
    # PNG decoding releases the GIL: every face of every camera in one pool of threads.
    with concurrent.futures.ThreadPoolExecutor(max(1, min(len(jobs), os.cpu_count() or 1))) as pool:
        imgs = dict(zip(jobs, pool.map(lambda j: reader.face(j[0], j[1], j[3], j[2], actor_ids=False), jobs),
                        strict=True))
    def stack(inst: str, k: str) -> np.ndarray:  # one copy into an (N, C, F, S, S[, 3]) array
        parts = [getattr(imgs[(f, c, inst, face)], k) for f in frames for c in names for face in reader.faces]
        return np.stack(parts).reshape((len(frames), len(names), len(reader.faces)) + parts[0].shape)

    stacked = {inst: CameraImages(*(stack(inst, k) for k in ("rgb", "depth_m", "semantic")), None)
               for inst in ("prev", "curr")}
    c2v = Pose(np.stack([np.asarray(cal.camera_to_vehicle.rotation_matrix, np.float32) for cal in calibs]),
               np.stack([np.asarray(cal.camera_to_vehicle.translation, np.float32) for cal in calibs]))
    per_sample = jax.tree_util.tree_map(lambda *xs: np.stack([np.asarray(x) for x in xs]), *[m[1:] for m in motions])
    rows = gt.rig_ground_truth([constants[c][0] for c in names], cams, c2v, stacked["prev"], stacked["curr"],
                               *per_sample, rays=[constants[c][1] for c in names], backward_flow=backward_flow,
                               carla_version=version, batch=batch, stacked=False, **options)
    out = [[{"truth": truth, "boxes_prev": bp, "boxes": bc, "vehicle_to_world_prev": vp, "vehicle_to_world": vc,
             "events": camera_events(reader, f, c, constants[c][2]), "camera": cam, "rays": constants[c][1],
             "actors": actors} for c, cam, truth in zip(names, cams, row, strict=True)]
           for f, (actors, bp, bc, vp, vc), row in zip(frames, motions, rows, strict=True)]
    return out[0] if single else out


def compiled_pixel_rays(camera):
    """`jaxfish.groundtruth.pixel_rays` in float32, compiled once per process and camera type/size."""
    return _jitted()["pixel_rays"](camera)


def fisheye_constants(reader, camera: str, model, *, frame: int | None = None, lut=None, rays=None, event_map=None):
    """The per-calibration constants ``(lut, rays, event_map)`` of a capture's fisheye ``camera``
    (``model``: its float32 camera model), building those not given: the cube -> fisheye LUT at
    the capture's ``face_size`` (or, when the header lacks it, the size of ``frame``'s first face),
    `compiled_pixel_rays` and the event map of the LUT."""
    import jax.numpy as jnp

    from .. import groundtruth as gt
    from ..reprojection import CubeRig, build_lut
    from ._capture import CaptureError

    if lut is None:
        size = int(reader.meta.get("face_size", 0))
        if size <= 0:
            if frame is None:
                raise CaptureError(f"{reader.root / 'capture.json'}: field 'face_size' missing or not positive")
            size = reader.face(frame, camera, reader.faces[0], actor_ids=False).rgb.shape[0]
        lut = build_lut(CubeRig(size, faces=tuple(reader.faces), dtype=jnp.float32), model)
        if not bool(jnp.any(lut.valid)):  # an empty dataset, not a camera
            raise CaptureError(f"{reader.root / 'calibration' / f'{camera}.json'}: field 'intrinsic': no pixel of camera "
                               f"{camera} has a ray inside its lens and the capture's cube faces (every pixel invalid in "
                               "float32): its lens parameters make the camera useless")
    return (lut, compiled_pixel_rays(model) if rays is None else rays,
            gt.event_map_from_lut(lut) if event_map is None else event_map)


def _jitted():
    import jax

    from .. import groundtruth as gt

    global _JIT
    if _JIT is None:
        _JIT = {"colorize": jax.jit(gt.colorize_labels), "instance_colors": jax.jit(gt.instance_colors),
                "z_depth": jax.jit(gt.range_to_z_depth),
                "pixel_rays": jax.jit(functools.partial(gt.pixel_rays, dtype=np.float32))}
    return _JIT


_JIT: dict[str, Any] | None = None


def write_camera_ground_truth(root: str | os.PathLike, sample: str, camera: str, result: Mapping[str, Any], *,
                              motion_threshold_m: float = 0.5, png_level: int = PNG_LEVEL) -> list[Path]:
    """Write one camera's ground truth (a `capture_ground_truth` result, or the BEV's
    `capture_bev_ground_truth` result with camera ``"BEV"``) in SynWoodScape's layout under
    ``root`` with file stem ``{sample}_{camera}``: ``rgb_images``, ``previous_images``
    (``{stem}_prev.png``), ``depth_maps/raw_data`` (range along the ray, float32 ``.npy``, sky
    1000), ``depth_maps/exr`` (the same range as a one-channel float32 EXR, `write_depth_exr`),
    ``depth_maps/z_depth`` (``.npy``) and ``depth_maps/colormap`` (``.png``),
    ``semantic_annotations``, ``instance_annotations`` (actor ids) and ``motion_annotations``
    (0/255) as ``gtLabels`` + ``rgbLabels``, ``optical_flow/{raw_data .flo, kitti .png,
    color_coded .png}`` (forward, t-1 -> t on the t-1 grid), ``dvs_signals/{raw_data .npy (CARLA
    dtype, ns), tonic .npz (µs), color_coded .png}`` (skipped when ``result["events"] is None``,
    e.g. the BEV), ``box_2d_annotations`` (visible boxes) and ``box_2d_full_annotations`` (full
    extent) CSV. The per-sample files (3D boxes, displacements) are `write_sample_ground_truth`'s.
    Every file is written atomically and deterministically; PNGs with zlib level
    ``png_level``. Returns the paths written."""
    from ._events import carla_to_tonic, write_events_npy
    from ._flow import write_flo, write_flow_color, write_kitti_flow

    jit = _jitted()
    root = Path(root)
    t = result["truth"]
    boxes = result["boxes"]
    stem = f"{sample}_{camera}"
    out: list[Path] = []
    add = out.append
    h, w = np.asarray(t.images.valid).shape
    add(write_image(root / "rgb_images" / f"{stem}.png", np.asarray(t.images.rgb), png_level=png_level))
    add(write_image(root / "previous_images" / f"{stem}_prev.png", np.asarray(t.images_prev.rgb), png_level=png_level))
    rng = np.asarray(t.images.range_m, np.float32)
    add(write_depth_npy(root / "depth_maps" / "raw_data" / f"{stem}.npy", rng))
    add(write_depth_exr(root / "depth_maps" / "exr" / f"{stem}.exr", rng, RANGE_DEPTH_DEFINITION))
    add(write_depth_npy(root / "depth_maps" / "z_depth" / f"{stem}.npy",
                        np.asarray(jit["z_depth"](result["camera"], t.images.range_m, rays=result.get("rays")))))
    add(write_image(root / "depth_maps" / "colormap" / f"{stem}.png", depth_to_color(rng), png_level=png_level))
    pal = synwoodscape_palette_dict()
    sem = np.asarray(t.semantic)
    add(write_label_png(root / "semantic_annotations" / "gtLabels" / f"{stem}.png", sem, png_level=png_level))
    add(write_color_png(root / "semantic_annotations" / "rgbLabels" / f"{stem}.png", np.asarray(jit["colorize"](sem)), pal,
                        png_level=png_level))
    ids = np.asarray(t.instances.actor_id)
    add(write_label_png(root / "instance_annotations" / "gtLabels" / f"{stem}.png", ids, png_level=png_level))
    add(write_color_png(root / "instance_annotations" / "rgbLabels" / f"{stem}.png",
                        np.asarray(jit["instance_colors"](ids)),
                        {"colors": "jaxfish.groundtruth.instance_colors(actor_id)", "background": [0, 0, 0]}, png_level=png_level))
    mot = np.asarray(t.motion).astype(np.uint8) * 255
    add(write_label_png(root / "motion_annotations" / "gtLabels" / f"{stem}.png", mot, png_level=png_level))
    add(write_color_png(root / "motion_annotations" / "rgbLabels" / f"{stem}.png", np.repeat(mot[..., None], 3, -1),
                        {"classes": ["static", "moving"], "colors": [[0, 0, 0], [255, 255, 255]],
                         "threshold_m": motion_threshold_m}, png_level=png_level))
    fl, fv = np.asarray(t.flow.flow), np.asarray(t.flow.valid)
    add(write_flo(root / "optical_flow" / "raw_data" / f"{stem}.flo", np.where(fv[..., None], fl, 0.0)))
    add(write_kitti_flow(root / "optical_flow" / "kitti" / f"{stem}.png", fl, fv, png_level=png_level))
    add(write_flow_color(root / "optical_flow" / "color_coded" / f"{stem}.png", fl, fv, png_level=png_level))
    ev = result.get("events")
    if ev is not None:
        add(write_events_npy(root / "dvs_signals" / "raw_data" / f"{stem}.npy", ev))
        add(write_npz(root / "dvs_signals" / "tonic" / f"{stem}.npz", events=carla_to_tonic(ev),
                      time_unit=np.asarray("us"), sensor_size=np.asarray([w, h, 2], np.int64)))
        add(write_image(root / "dvs_signals" / "color_coded" / f"{stem}.png", events_color(ev, width=w, height=h),
                                png_level=png_level))
    cls = np.asarray(boxes.class_id)
    add(write_boxes_2d_csv(root / "box_2d_annotations" / f"{stem}.txt",
                           boxes_2d_rows(np.asarray(t.boxes_2d.xyxy), np.asarray(t.boxes_2d.present), cls)))
    add(write_boxes_2d_csv(root / "box_2d_full_annotations" / f"{stem}.txt",
                           boxes_2d_rows(np.asarray(t.boxes_2d_full.xyxy), np.asarray(t.boxes_2d_full.present), cls)))
    return out


def write_sample_ground_truth(root: str | os.PathLike, sample: str, result: Mapping[str, Any], *,
                              motion_threshold_m: float = 0.5) -> list[Path]:
    """Write the per-sample (camera-independent) files of a sample from any camera's
    `capture_ground_truth` result: ``box_3d_annotations/{sample}.pkl`` (SynWoodScape's format:
    ``{actor_id: (8, 3) CARLA-world corners}``, every actor), ``box_3d_annotations_ext/{sample}.json``
    (class and ISO-vehicle corners, `write_boxes_3d_ext_json`) and ``distances_traveled/{sample}.txt``
    (every actor's displacement between t-1 and t, `write_displacements`). Returns the paths."""
    from .. import groundtruth as gt

    root = Path(root)
    boxes = result["boxes"]
    cls = np.asarray(boxes.class_id)
    world = np.asarray(boxes.corners(), np.float64)
    veh = np.asarray(gt.boxes_in_frame(boxes, result["vehicle_to_world"].inverse()), np.float64)
    names = gt.SYNWOODSCAPE_CLASSES
    act = np.asarray(boxes.active)
    aid = np.asarray(boxes.actor_id)
    out = [write_boxes_3d_pickle(root / "box_3d_annotations" / f"{sample}.pkl",
                                 {int(a): world[i] for i, a in enumerate(aid) if act[i]})]
    ext = {int(a): {"corners_world": world[i], "corners_vehicle": veh[i], "class_id": int(cls[i]),
                    "class_name": names[int(cls[i])] if 0 <= int(cls[i]) < len(names) else "unknown"}
           for i, a in enumerate(aid) if act[i]}
    out.append(write_boxes_3d_ext_json(root / "box_3d_annotations_ext" / f"{sample}.json", ext))
    disp = np.asarray(result["truth"].displacement_m)
    out.append(write_displacements(root / "distances_traveled" / f"{sample}.txt", aid[act], cls[act], disp[act],
                                   threshold_m=motion_threshold_m))
    return out
