"""``jaxfish show DATASET SAMPLE --out PNG``: a built sample's fisheyes with its 3D boxes as
wireframes (the exact fisheye image of every edge, `jaxfish.groundtruth.box_edge_pixels`), its
lidar points coloured by range and its 2D boxes.

Reads, for sample ``ID`` of a jaxfish-built dataset (layout: ``docs/dataset.md``):
``calibration_data/{CAM}.json``, ``rgb_images/{ID}_{CAM}.png``, ``box_3d_annotations_ext/{ID}.json``
(``corners_vehicle``, ISO 8855 vehicle frame), ``box_2d_annotations/{ID}_{CAM}.txt`` and, when
present, ``lidar_vehicle/{ID}.npy`` (float32 ``(N, 4)``: x, y, z in the vehicle frame, intensity).
All reading happens in `read_sample_view`."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import typer

from ._app import app, check_outputs, fail, note, say

FISHEYES = ("FV", "RV", "MVL", "MVR")
"""The fisheyes in sheet order: top row front, rear; bottom row left, right."""
BOX_COLORS = {10: (0, 255, 0), 21: (0, 255, 255), 4: (255, 0, 255), 24: (255, 255, 255)}
"""Wireframe colour of each SynWoodScape box class (vehicle green, two-wheeler cyan, pedestrian
magenta, ego white); any other class orange `OTHER_BOX_COLOR`."""
OTHER_BOX_COLOR = (255, 128, 0)
BOX_2D_COLOR = (255, 255, 0)
"""Outline colour of the 2D boxes (``box_2d_annotations``, visible extent): yellow."""
EGO_CLASS = 24
MAX_COORDINATE_M = 1e6
"""Largest box corner coordinate (metres, vehicle frame) accepted: farther is a corrupt file."""


@dataclass(frozen=True)
class CameraView:
    """One fisheye of a sample: its name, `Calibration`, RGB ``(H, W, 3)`` uint8, 2D boxes
    ``(N, 4)`` int64 ``x1, y1, x2, y2`` and their classes ``(N,)``."""

    name: str
    calibration: object
    rgb: np.ndarray
    boxes_2d: np.ndarray
    boxes_2d_class: np.ndarray


@dataclass(frozen=True)
class SampleView:
    """What `jaxfish show` draws of a sample: its cameras, 3D box corners ``(K, 8, 3)`` (vehicle
    frame, metres) with their classes ``(K,)``, and the lidar ``(N, 4)`` (None when absent, with
    the path looked for)."""

    sample: str
    cameras: tuple[CameraView, ...]
    corners_vehicle: np.ndarray
    class_id: np.ndarray
    lidar: np.ndarray | None
    lidar_path: Path


def _sample_id(text: str) -> str:
    from .._errors import JaxfishError

    if not (text.isascii() and text.isdigit()) or len(text) > 12:
        raise JaxfishError(f"SAMPLE {text!r}: expected a sample id such as 00000")
    return f"{int(text):05d}"


def _boxes_3d(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """``(corners_vehicle (K, 8, 3), class_id (K,))`` of a ``box_3d_annotations_ext`` file; every
    malformed field raises `JaxfishError` naming the file and the field."""
    from .._errors import JaxfishError
    from ..io._json import read_json

    doc = read_json(path, JaxfishError, obj=True)
    rows = doc.get("boxes")
    if not isinstance(rows, list):
        raise JaxfishError(f"{path}: field 'boxes': expected a list of boxes, got {type(rows).__name__}")
    corners, classes = [], []
    for i, row in enumerate(rows):
        if not isinstance(row, dict):
            raise JaxfishError(f"{path}: field 'boxes[{i}]': expected an object, got {type(row).__name__}")
        cid = row.get("class_id")
        if isinstance(cid, bool) or not isinstance(cid, int):
            raise JaxfishError(f"{path}: field 'boxes[{i}].class_id': expected an integer, got {cid!r}")
        c = row.get("corners_vehicle")
        ok = isinstance(c, list) and len(c) == 8 and all(
            isinstance(p, list) and len(p) == 3 and all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in p)
            for p in c)
        if not ok:
            raise JaxfishError(f"{path}: field 'boxes[{i}].corners_vehicle': expected 8 corners of 3 numbers (metres)")
        a = np.asarray(c, np.float64)
        if not np.all(np.abs(a) <= MAX_COORDINATE_M):
            raise JaxfishError(f"{path}: field 'boxes[{i}].corners_vehicle': expected finite coordinates within "
                               f"{MAX_COORDINATE_M:g} m of the vehicle")
        corners.append(a)
        classes.append(cid)
    return np.asarray(corners, np.float64).reshape(-1, 8, 3), np.asarray(classes, np.int64)


def _lidar(path: Path) -> np.ndarray | None:
    """The ``lidar_vehicle`` sweep ``(N, 4)`` float32, or None when the file is absent."""
    from .._errors import JaxfishError
    from ..io import load_npy

    if not path.exists():
        return None
    try:
        a = load_npy(path)
    except (ValueError, OSError, EOFError) as e:
        raise JaxfishError(f"{path}: not a readable .npy array ({e})") from None
    if a.ndim != 2 or a.shape[1] != 4 or not np.issubdtype(a.dtype, np.floating):
        raise JaxfishError(f"{path}: expected a float (N, 4) array (x, y, z, intensity), got {a.dtype} {a.shape}")
    bad = ~np.all(np.isfinite(a[:, :3]), axis=1)
    if bad.any():
        raise JaxfishError(f"{path}: point {int(np.argmax(bad))}: x, y, z are not finite numbers")
    return a.astype(np.float32)


def read_sample_view(dataset: Path, sample: str, cameras: tuple[str, ...]) -> SampleView:
    """Read what `show` draws of ``sample`` of ``dataset`` for ``cameras`` (the command's only
    file reading). Raises `JaxfishError` (or `FileNotFoundError`) naming the file and field."""
    from .._errors import JaxfishError
    from ..io import load_calibration, read_boxes_2d_csv, read_image

    if not dataset.is_dir():
        raise JaxfishError(f"{dataset}: dataset folder not found" if not dataset.exists() else f"{dataset}: not a folder")
    if not (dataset / "calibration_data").is_dir():
        raise JaxfishError(f"{dataset}: not a built dataset (no calibration_data/ folder)")
    sid = _sample_id(sample)
    views = []
    for name in cameras:
        rgb_path = dataset / "rgb_images" / f"{sid}_{name}.png"
        if not rgb_path.exists():
            known = sorted(p.name[: -len("_FV.png")] for p in (dataset / "rgb_images").glob("*_FV.png"))
            shown = ", ".join(known[:8]) + (", ..." if len(known) > 8 else "") if known else "none"
            raise JaxfishError(f"{rgb_path}: sample {sid} not found in {dataset} (samples there: {shown})")
        calib = load_calibration(dataset / "calibration_data" / f"{name}.json")
        rgb = read_image(rgb_path)
        w, h = calib.camera.image_size
        if rgb.dtype != np.uint8 or rgb.shape[:2] != (h, w) or rgb.shape[2] < 3:
            raise JaxfishError(f"{rgb_path}: expected a {w} x {h} RGB uint8 image ({name}'s calibration), "
                               f"got {rgb.dtype} {rgb.shape}")
        rows = read_boxes_2d_csv(dataset / "box_2d_annotations" / f"{sid}_{name}.txt")
        boxes = np.asarray([r[2:] for r in rows], np.int64).reshape(-1, 4)
        classes_2d = np.asarray([r[1] for r in rows], np.int64)
        views.append(CameraView(name, calib, np.ascontiguousarray(rgb[..., :3]), boxes, classes_2d))
    corners, classes = _boxes_3d(dataset / "box_3d_annotations_ext" / f"{sid}.json")
    lidar_path = dataset / "lidar_vehicle" / f"{sid}.npy"
    return SampleView(sid, tuple(views), corners, classes, _lidar(lidar_path), lidar_path)


def default_samples_per_edge(width: int, height: int) -> int:
    """Samples per box edge for an image: one per 8 pixels of its larger side, at least 16."""
    return max(16, math.ceil(max(width, height) / 8))


def draw_camera(view: CameraView, sample: SampleView, *, samples_per_edge: int | None = None,
                ego: bool = False) -> np.ndarray:
    """The RGB image of ``view`` with the lidar points (coloured by range, `depth_to_color`'s ramp,
    nearer over farther), the 3D box wireframes (`BOX_COLORS`) and the 2D boxes (`BOX_2D_COLOR`);
    the ego vehicle's boxes (class 24) only with ``ego``."""
    from ..groundtruth import box_edge_pixels, draw_points, draw_polylines, draw_rectangles, project_points
    from ..pipeline import depth_to_color

    cam = view.calibration.camera
    pose = view.calibration.vehicle_to_camera
    w, h = cam.image_size
    stroke = max(1, round(max(w, h) / 640))
    img = view.rgb
    if sample.lidar is not None and len(sample.lidar):
        pts = project_points(cam, pose, sample.lidar[:, :3])
        rng = np.asarray(pts.range_m)
        img = draw_points(img, np.asarray(pts.uv), np.asarray(pts.valid), depth_to_color(rng), size=stroke, order=rng)
    keep = np.ones(len(sample.class_id), bool) if ego else sample.class_id != EGO_CLASS
    if keep.any():
        corners = sample.corners_vehicle[keep].astype(np.float32)
        n = samples_per_edge or default_samples_per_edge(w, h)
        edges = box_edge_pixels(cam, pose, corners, n)
        colors = np.asarray([BOX_COLORS.get(int(c), OTHER_BOX_COLOR) for c in sample.class_id[keep]], np.uint8)
        colors = np.broadcast_to(colors[:, None, :], (len(colors), 12, 3))
        img = draw_polylines(img, np.asarray(edges.uv), np.asarray(edges.drawn), colors, thickness=stroke)
    keep_2d = slice(None) if ego else view.boxes_2d_class != EGO_CLASS
    return draw_rectangles(img, view.boxes_2d[keep_2d], BOX_2D_COLOR, thickness=stroke)


def sheet(images: list[np.ndarray]) -> np.ndarray:
    """One image as is; several on a grid of two columns in their order (tiles of the largest
    size, top-left aligned, black elsewhere)."""
    if len(images) == 1:
        return images[0]
    th = max(i.shape[0] for i in images)
    tw = max(i.shape[1] for i in images)
    rows = math.ceil(len(images) / 2)
    out = np.zeros((rows * th, 2 * tw, 3), np.uint8)
    for k, img in enumerate(images):
        r, c = divmod(k, 2)
        out[r * th: r * th + img.shape[0], c * tw: c * tw + img.shape[1]] = img
    return out


@app.command()
def show(
    dataset: Path = typer.Argument(..., help="A dataset built by jaxfish (calibration_data/, rgb_images/, ...)."),
    sample: str = typer.Argument(..., help="Sample id, e.g. 00000 (or 0)."),
    out: Path = typer.Option(..., "--out", "-o", help="Output PNG."),
    camera: str | None = typer.Option(None, "--camera", "-c", help="Draw only this fisheye (FV, RV, MVL or MVR)."),
    samples_per_edge: int | None = typer.Option(None, "--samples-per-edge", help="Points per box edge "
                                                "(default: one per 8 pixels of the image's larger side, at least 16)."),
    ego: bool = typer.Option(False, "--ego", help="Also draw the ego vehicle's own box (it surrounds the cameras)."),
) -> None:
    """Draw a sample's fisheyes (2 x 2: FV, RV / MVL, MVR) with its 3D boxes as exact fisheye
    wireframes, its lidar points coloured by range and its 2D boxes."""
    check_outputs(out=out)
    if out.suffix.lower() != ".png":
        raise fail(f"--out {out}: expected a .png path")
    if camera is not None and camera not in FISHEYES:
        raise fail(f"--camera {camera!r}: expected one of {', '.join(FISHEYES)}")
    if samples_per_edge is not None and not 2 <= samples_per_edge <= 100_000:
        raise fail(f"--samples-per-edge must lie in [2, 100000], got {samples_per_edge}")
    from ..io import write_image

    view = read_sample_view(dataset, sample, (camera,) if camera else FISHEYES)
    if view.lidar is None:
        note(f"no lidar: {view.lidar_path} not found; drawing no lidar points")
    images = [draw_camera(v, view, samples_per_edge=samples_per_edge, ego=ego) for v in view.cameras]
    write_image(out, sheet(images))
    say(f"wrote {out}")
