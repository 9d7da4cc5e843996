"""From a capture directory to ground-truth files: the capture adapter reproduces the in-memory
ground truth (up to CARLA's 24-bit depth encoding) and the writer produces SynWoodScape's layout."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest

from jaxfish import groundtruth as gt
from jaxfish.dataset import CaptureSource
from jaxfish.dataset._sink import write_box_files, write_camera_files, write_sample_files
from jaxfish.io import (
    read_boxes_2d_csv,
    read_boxes_3d_pickle,
    read_displacements,
    read_events_npy,
    read_flo,
    read_label_png,
    write_capture_header,
    write_frame,
)
from jaxfish.pipeline import (
    CameraConstants,
    GroundTruthOptions,
    RigConstants,
    compiled_pixel_rays,
    face_event_table,
    sample_truth,
)
from jaxfish.scene import RADAR_DTYPE, SEMANTIC_LIDAR_DTYPE, CameraCapture, CameraImages, CaptureConfig, sensor_mounts


@pytest.fixture(scope="module")
def capture(sample, tmp_path_factory):
    root = tmp_path_factory.mktemp("capture")
    rig = {"FV": sample.calib}
    config = CaptureConfig(face_size=sample.face_size)
    write_capture_header(root, rig, config, sensor_mounts(rig, config), seed=0)
    names = list(config.faces)
    imgs = lambda f: {n: CameraImages(f.rgb[i], f.depth_m[i], f.semantic[i], f.actor_id[i]) for i, n in enumerate(names)}  # noqa: E731
    rng = np.random.default_rng(0)
    dvs = {}
    for n in names:
        ev = np.empty(200, np.dtype([("x", "<u2"), ("y", "<u2"), ("t", "<i8"), ("pol", "?")]))
        ev["x"], ev["y"] = rng.integers(0, sample.face_size, 200), rng.integers(0, sample.face_size, 200)
        ev["t"], ev["pol"] = np.sort(rng.integers(0, 10**8, 200)), rng.random(200) < 0.5
        dvs[n] = ev
    write_frame(root, sample.frame, cameras={"FV": CameraCapture(imgs(sample.faces_prev), imgs(sample.faces), dvs)}, views={},
                lidar=np.zeros((0, 4), np.float32), semantic_lidar=np.empty(0, SEMANTIC_LIDAR_DTYPE),
                radar=np.empty(0, RADAR_DTYPE), imu={}, gnss={})
    source = CaptureSource(root)
    calib = source.rig()["FV"].astype(jnp.float32)
    cam = calib.camera.astype(jnp.float32)
    table = face_event_table(gt.event_map_from_lut(sample.lut))
    constants = RigConstants((CameraConstants("FV", cam, calib.camera_to_vehicle, sample.lut, compiled_pixel_rays(cam), table),),
                             None, source.faces, source.face_size)
    frame = source.read(sample.frame.frame, bev=False)
    return frame, sample_truth(frame, constants, GroundTruthOptions(bev=False)), dvs


def test_capture_adapter_matches_the_in_memory_ground_truth(sample, capture):
    _, res, dvs = capture
    t, ref = res.cameras[0].truth, sample.truth
    v = np.asarray(t.images.valid)
    assert np.mean(np.asarray(t.instances.actor_id)[v] == np.asarray(ref.instances.actor_id)[v]) > 0.999
    assert np.mean(np.asarray(t.semantic)[v] == np.asarray(ref.semantic)[v]) > 0.999
    ok = np.asarray(t.flow.valid) & np.asarray(ref.flow.valid)
    assert np.median(np.linalg.norm(np.asarray(t.flow.flow) - np.asarray(ref.flow.flow), axis=-1)[ok]) < 1e-2
    ev = res.cameras[0].events
    assert np.all(np.diff(ev["t"]) >= 0)
    fan = np.asarray(gt.event_map_from_lut(sample.lut).fanout)
    s = sample.face_size
    want = sum(int(fan[(i * s + d["y"].astype(int)) * s + d["x"].astype(int)].sum()) for i, d in enumerate(dvs.values()))
    assert ev.shape[0] == want


def test_writer_produces_the_synwoodscape_layout(sample, capture, tmp_path):
    frame, res, _ = capture
    cam = res.cameras[0]
    paths = write_camera_files(tmp_path, "00003", cam, motion_threshold_m=0.5, png_level=1)
    paths += write_box_files(tmp_path, "00003", cam, np.asarray(res.motion.boxes.class_id))
    assert all(p.is_file() for p in paths)
    rel = {str(p.relative_to(tmp_path)) for p in paths}
    for want in ("rgb_images/00003_FV.png", "previous_images/00003_FV_prev.png", "depth_maps/raw_data/00003_FV.npy",
                 "semantic_annotations/gtLabels/00003_FV.png", "semantic_annotations/rgbLabels/00003_FV.png",
                 "instance_annotations/gtLabels/00003_FV.png", "motion_annotations/gtLabels/00003_FV.png",
                 "optical_flow/raw_data/00003_FV.flo", "optical_flow/color_coded/00003_FV.png",
                 "dvs_signals/raw_data/00003_FV.npy", "box_2d_annotations/00003_FV.txt", "depth_maps/colormap/00003_FV.png"):
        assert want in rel
    t = cam.truth
    np.testing.assert_array_equal(read_label_png(tmp_path / "instance_annotations/gtLabels/00003_FV.png"), np.asarray(t.instances.actor_id))
    np.testing.assert_array_equal(read_label_png(tmp_path / "semantic_annotations/gtLabels/00003_FV.png"), np.asarray(t.semantic))
    flo = read_flo(tmp_path / "optical_flow/raw_data/00003_FV.flo")
    np.testing.assert_array_equal(flo[np.asarray(t.flow.valid)], np.asarray(t.flow.flow)[np.asarray(t.flow.valid)])
    np.testing.assert_array_equal(read_events_npy(tmp_path / "dvs_signals/raw_data/00003_FV.npy"), cam.events)
    rows = read_boxes_2d_csv(tmp_path / "box_2d_annotations/00003_FV.txt")
    assert len(rows) == int(np.asarray(t.boxes_2d.present).sum()) and all(r[1] in (4, 10, 21, 24) for r in rows)
    per_sample = write_sample_files(tmp_path, "00003", res, motion_threshold_m=0.5)
    assert {str(p.relative_to(tmp_path)) for p in per_sample} == {
        "box_3d_annotations/00003.pkl", "box_3d_annotations_ext/00003.json", "distances_traveled/00003.txt"}
    box3d = read_boxes_3d_pickle(tmp_path / "box_3d_annotations/00003.pkl")  # SynWoodScape's format
    assert set(box3d) == {a["id"] for a in frame.motion.actors}
    assert all(isinstance(v, np.ndarray) and v.shape == (8, 3) for v in box3d.values())
    assert read_displacements(tmp_path / "distances_traveled/00003.txt").keys() == box3d.keys()
