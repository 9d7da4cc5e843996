"""Hostile inputs of ``jaxfish show DATASET SAMPLE --out PNG``: a hand-made miniature dataset
(``{tmp}/ds``: the default rig at 64 x 48, one sample, one box), broken one file or field at a time."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from .corpus import Case, edit_json

SHOW = "show {tmp}/ds 0 --out {tmp}/o.png"
OUT = ("{tmp}/o.png",)
BOXES = "ds/box_3d_annotations_ext/00000.json"


def _mini(tmp: Path) -> Path:
    """The miniature dataset: calibrations, black RGB images, one 2D box per camera, one 3D box."""
    from jaxfish.cli._demo import demo_rig
    from jaxfish.groundtruth import CORNER_SIGNS
    from jaxfish.io import save_rig, write_image

    ds = tmp / "ds"
    rig = demo_rig(0.05)
    save_rig(rig, ds / "calibration_data")
    for name, c in rig.items():
        w, h = c.camera.image_size
        write_image(ds / "rgb_images" / f"00000_{name}.png", np.zeros((h, w, 3), np.uint8))
        (ds / "box_2d_annotations").mkdir(exist_ok=True)
        (ds / "box_2d_annotations" / f"00000_{name}.txt").write_text("vehicles,10,3,4,20,30\n")
    corners = CORNER_SIGNS * np.array([2.0, 0.9, 0.8]) + np.array([7.0, 0.0, 0.8])
    box = {"actor_id": 5, "class_id": 10, "class_name": "vehicles", "corners_world": corners.tolist(),
           "corners_vehicle": corners.tolist()}
    (ds / "box_3d_annotations_ext").mkdir()
    (tmp / BOXES).write_text(json.dumps({"boxes": [box]}))
    return ds


def _with(edit) -> callable:
    """A setup: the miniature dataset, then ``edit(tmp)``."""
    def setup(tmp: Path) -> None:
        _mini(tmp)
        edit(tmp)
    return setup


def _box(field: str, value) -> callable:
    return _with(lambda tmp: edit_json(tmp / BOXES, lambda d: d["boxes"][0].__setitem__(field, value)))


def _lidar(array=None, raw: bytes | None = None) -> callable:
    def edit(tmp: Path) -> None:
        path = tmp / "ds" / "lidar_vehicle" / "00000.npy"
        path.parent.mkdir()
        if raw is not None:
            path.write_bytes(raw)
        else:
            np.save(path, array)
    return _with(edit)


CASES = [
    Case("show-dataset-missing", "show {tmp}/nope 0 --out {tmp}/o.png", says=("{tmp}/nope", "not found"), absent=OUT),
    Case("show-not-a-dataset", "show {capture} 0 --out {tmp}/o.png", says=("{capture}", "not a built dataset"),
         absent=OUT),
    Case("show-sample-missing", "show {tmp}/ds 7 --out {tmp}/o.png", setup=_mini,
         says=("rgb_images/00007_FV.png", "sample 00007 not found", "00000"), absent=OUT),
    Case("show-sample-not-an-id", "show {tmp}/ds ../x --out {tmp}/o.png", setup=_mini, says=("SAMPLE", "../x"),
         absent=OUT),
    Case("show-camera-unknown", SHOW + " --camera BEV", setup=_mini, says=("--camera", "FV, RV, MVL, MVR"), absent=OUT),
    Case("show-out-not-png", "show {tmp}/ds 0 --out {tmp}/o.jpg", setup=_mini, says=("--out", ".png"),
         absent=("{tmp}/o.jpg",)),
    Case("show-out-is-a-folder", "show {tmp}/ds 0 --out {tmp}/ds", setup=_mini, says=("--out", "is a directory")),
    Case("show-samples-per-edge-one", SHOW + " --samples-per-edge 1", setup=_mini, says=("--samples-per-edge",),
         absent=OUT),
    Case("show-boxes-missing", SHOW, setup=_with(lambda tmp: (tmp / BOXES).unlink()),
         says=("box_3d_annotations_ext/00000.json", "not found"), absent=OUT),
    Case("show-boxes-not-json", SHOW, setup=_with(lambda tmp: (tmp / BOXES).write_text("{\"boxes\": [")),
         says=("box_3d_annotations_ext/00000.json", "invalid JSON"), absent=OUT),
    Case("show-boxes-not-a-list", SHOW, setup=_with(lambda tmp: (tmp / BOXES).write_text("{\"boxes\": {}}")),
         says=("box_3d_annotations_ext/00000.json", "'boxes'"), absent=OUT),
    Case("show-boxes-row-not-an-object", SHOW, setup=_with(lambda tmp: (tmp / BOXES).write_text("{\"boxes\": [3]}")),
         says=("box_3d_annotations_ext/00000.json", "'boxes[0]'"), absent=OUT),
    Case("show-boxes-seven-corners", SHOW, setup=_box("corners_vehicle", [[0.0, 0.0, 0.0]] * 7),
         says=("box_3d_annotations_ext/00000.json", "boxes[0].corners_vehicle", "8 corners"), absent=OUT),
    Case("show-boxes-corner-string", SHOW, setup=_box("corners_vehicle", [[0.0, 0.0, "1"]] * 8),
         says=("box_3d_annotations_ext/00000.json", "boxes[0].corners_vehicle"), absent=OUT),
    Case("show-boxes-corner-huge", SHOW, setup=_box("corners_vehicle", [[1e300, 0.0, 0.0]] * 8),
         says=("box_3d_annotations_ext/00000.json", "boxes[0].corners_vehicle", "finite"), absent=OUT),
    Case("show-boxes-corner-nan", SHOW, setup=_box("corners_vehicle", [[float("nan"), 0.0, 0.0]] * 8),
         says=("box_3d_annotations_ext/00000.json", "boxes[0].corners_vehicle", "finite"), absent=OUT),
    Case("show-boxes-class-id-text", SHOW, setup=_box("class_id", "10"),
         says=("box_3d_annotations_ext/00000.json", "boxes[0].class_id"), absent=OUT),
    Case("show-boxes-2d-short-line", SHOW,
         setup=_with(lambda tmp: (tmp / "ds/box_2d_annotations/00000_RV.txt").write_text("vehicles,10,1,2\n")),
         says=("box_2d_annotations/00000_RV.txt", "expected 6 fields"), absent=OUT),
    Case("show-calibration-k1-text", SHOW,
         setup=_with(lambda tmp: edit_json(tmp / "ds/calibration_data/MVL.json",
                                           lambda d: d["intrinsic"].__setitem__("k1", "x"))),
         says=("calibration_data/MVL.json", "intrinsic.k1"), absent=OUT),
    Case("show-calibration-missing", SHOW, setup=_with(lambda tmp: (tmp / "ds/calibration_data/MVR.json").unlink()),
         says=("calibration_data/MVR.json", "not found"), absent=OUT),
    Case("show-rgb-wrong-size", SHOW, setup=_with(lambda tmp: __import__("jaxfish.io").io.write_image(
        tmp / "ds/rgb_images/00000_FV.png", np.zeros((10, 10, 3), np.uint8))),
         says=("rgb_images/00000_FV.png", "64 x 48"), absent=OUT),
    Case("show-rgb-corrupt", SHOW, setup=_with(lambda tmp: (tmp / "ds/rgb_images/00000_FV.png").write_bytes(b"\x89PNG junk")),
         says=("rgb_images/00000_FV.png",), absent=OUT),
    Case("show-lidar-not-npy", SHOW, setup=_lidar(raw=b"not an array"),
         says=("lidar_vehicle/00000.npy", "not a readable .npy"), absent=OUT),
    Case("show-lidar-three-columns", SHOW, setup=_lidar(np.zeros((5, 3), np.float32)),
         says=("lidar_vehicle/00000.npy", "(N, 4)"), absent=OUT),
    Case("show-lidar-pickled-object", SHOW, setup=_lidar(np.array([{"x": 1}], dtype=object)),
         says=("lidar_vehicle/00000.npy", "not a readable .npy"), absent=OUT),
    Case("show-lidar-nan", SHOW, setup=_lidar(np.array([[1.0, 2.0, 3.0, 0.5], [np.nan, 0.0, 0.0, 0.5]], np.float32)),
         says=("lidar_vehicle/00000.npy", "point 1", "not finite"), absent=OUT),
    Case("show-lidar-absent-says-so", SHOW, setup=_mini, exit=0, says=("no lidar", "lidar_vehicle/00000.npy"),
         stdout_says=("wrote {tmp}/o.png",)),
    Case("show-lidar-huge-points-hold", SHOW, setup=_lidar(np.array([[3e38, 0.0, 0.0, 1.0], [5.0, 1.0, 0.5, 1.0]],
                                                                    np.float32)),
         exit=0, stdout_says=("wrote {tmp}/o.png",)),
]
