"""BEV ground truth of a capture: scale and axes of the true top view, height and occupancy, the
extra files and their metadata, and clear errors for broken captures."""

from __future__ import annotations

import json
import shutil

import equinox as eqx
import jax.numpy as jnp
import numpy as np
import pytest

import jaxfish as jf
from jaxfish import bev as jbev
from jaxfish.dataset import CaptureSource
from jaxfish.dataset._sink import write_bev_files
from jaxfish.io import CaptureError, CaptureReader, read_bev_metadata
from jaxfish.pipeline import GroundTruthOptions, RigConstants, bev_constants, bev_truth
from tests.bev.conftest import BOXES, ground_class, pattern_is_uniform
from tests.bev.small_capture import ACTOR_ID, TAG, shared_bev_capture
from tests.bev.small_capture import BEV_MPP as MPP
from tests.bev.small_capture import BEV_SIZE as BEV
from tests.tolerances import BEV_HEIGHT_FROM_DEPTH_M


def _bev_truth(root, frame: int):
    """The BEV ground truth of a capture frame through the pipeline (the BEV's constants only)."""
    source = CaptureSource(root)
    constants = RigConstants((), bev_constants(*source.bev_sensor()), source.faces, source.face_size)
    return bev_truth(source.read(frame, bev=True, cameras=False, sensors=False), constants, GroundTruthOptions())


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    root = shared_bev_capture(tmp_path_factory)
    reader = CaptureReader(root)
    return root, reader, _bev_truth(root, 0)


def test_result_fields_scale_and_axes(capture):
    root, reader, res = capture
    assert res.view.name == "BEV" and res.view.events is None and float(res.camera.metres_per_pixel) == pytest.approx(MPP)
    assert res.height_m.shape == (BEV, BEV) and res.height_m.dtype == np.float32
    assert res.occupancy.dtype == bool and res.view.truth.semantic.shape == (BEV, BEV)
    # Axes and scale: the documented convention x = x0 - (v - cy) m, y = -(u - cx) m puts every
    # ground cell on the class the analytic pattern has there, and the car's actor id on its box.
    sens = reader.sensors()["bev"]
    x0 = sens["camera_to_vehicle"]["translation"][0]
    v, u = np.mgrid[0:BEV, 0:BEV].astype(np.float64)
    x, y = x0 - (v - sens["cy"]) * MPP, -(u - sens["cx"]) * MPP
    sem = np.asarray(res.view.truth.semantic)
    ground = pattern_is_uniform(x, y, 1e-3) & ~np.isin(sem, (5, 10, 11, 22)) & (res.height_m < 0.01)
    pattern = np.vectorize(TAG.get)(ground_class(x, y))  # tags = SynWoodScape classes for these
    assert ground.sum() > 0.8 * ground.size  # one ray per pixel: its centre
    np.testing.assert_array_equal(sem[ground], pattern[ground])
    ids = np.asarray(res.view.truth.instances.actor_id)
    bx0, bx1, by0, by1, *_ = BOXES[0]
    inside = (x > bx0) & (x < bx1) & (y > by0) & (y < by1)
    near = (x > bx0 - 0.1) & (x < bx1 + 0.1) & (y > by0 - 0.1) & (y < by1 + 0.1)
    assert inside.sum() >= 6 and np.all(ids[inside] == ACTOR_ID) and np.all(ids[~near] == 0)


def test_height_and_occupancy(capture):
    _, reader, res = capture
    cam, c2v = res.camera, res.camera_to_vehicle
    from_depth = np.asarray(jbev.height_map(cam, c2v, jnp.asarray(reader.view(0, "bev").depth_m)))
    assert np.max(np.abs(from_depth - res.height_m)) < BEV_HEIGHT_FROM_DEPTH_M
    sem = np.asarray(res.view.truth.semantic)
    road = (sem == 7) & (res.height_m < 0.01)
    assert road.sum() > 50 and np.all(np.abs(res.height_m[road]) < BEV_HEIGHT_FROM_DEPTH_M)
    assert not res.occupancy[road].any()
    tall = np.isin(sem, (10, 11, 22))  # the boxes above 0.2 m: the car (0.5 m), static (0.3 m), wall (1.5 m)
    assert tall.sum() >= 4 and res.occupancy[tall].all()
    np.testing.assert_array_equal(res.occupancy, res.height_m > jbev.OCCUPANCY_MIN_HEIGHT_M)


def test_write_files_and_metadata(capture, tmp_path):
    _, _, res = capture
    paths = write_bev_files(tmp_path, "00001", res, png_level=1)
    rel = sorted(str(p.relative_to(tmp_path)) for p in paths)
    assert rel == ["bev_height/colormap/00001_BEV.png", "bev_height/raw_data/00001_BEV.npy",
                   "bev_occupancy/00001_BEV.png"]
    np.testing.assert_array_equal(np.load(tmp_path / rel[1]), res.height_m)
    occ = jf.io.read_image(tmp_path / rel[2])[..., 0]
    np.testing.assert_array_equal(occ, res.occupancy.astype(np.uint8) * 255)
    for p in (rel[0], rel[2]):
        meta = read_bev_metadata(tmp_path / p)
        assert meta["metres_per_pixel"] == pytest.approx(MPP) and "forward" in meta["axes"]
        a = np.asarray(meta["pixel_to_vehicle_xy"])
        # pixel (cx, cy - 1), one row up, is one cell forward of the centre
        cx, cy = meta["cx"], meta["cy"]
        np.testing.assert_allclose(a @ [cx, cy - 1, 1] - a @ [cx, cy, 1], [MPP, 0.0], atol=1e-6)
        np.testing.assert_allclose(a @ [cx + 1, cy, 1] - a @ [cx, cy, 1], [0.0, -MPP], atol=1e-6)
    assert not list(tmp_path.rglob("*.part*"))


def test_height_from_depth_when_exr_absent(capture, tmp_path):
    root, _, res = capture
    copy = tmp_path / "cap"
    shutil.copytree(root, copy)
    (copy / "frames/000000/bev/height_curr.exr").unlink()
    res2 = _bev_truth(copy, 0)
    assert np.max(np.abs(res2.height_m - res.height_m)) < BEV_HEIGHT_FROM_DEPTH_M


def test_errors_name_file_and_field(capture, tmp_path):
    root, _, res = capture
    copy = tmp_path / "cap"
    shutil.copytree(root, copy)
    (copy / "frames/000000/bev/depth_prev.png").unlink()
    with pytest.raises(CaptureError, match="depth_prev.png"):
        _bev_truth(copy, 0)
    sensors = json.loads((copy / "sensors.json").read_text())
    del sensors["bev"]["metres_per_pixel"]
    (copy / "sensors.json").write_text(json.dumps(sensors))
    with pytest.raises(CaptureError, match=r"sensors.json.*bev.metres_per_pixel"):
        _bev_truth(copy, 0)
    with pytest.raises(CaptureError, match="frame 7"):
        _bev_truth(root, 7)
    bad = eqx.tree_at(lambda b: b.height_m, res, np.zeros((3, 3), np.float32))
    with pytest.raises(jf.JaxfishError, match="height"):
        write_bev_files(tmp_path / "out", "00002", bad, png_level=1)


def test_calibration_poses_must_be_rotations_and_metadata_json(capture, tmp_path):
    import OpenImageIO as oiio

    from jaxfish.bev import bev_metadata
    from jaxfish.io import BEV_METADATA_ATTRIBUTE, load_bev_calibration

    _, _, res = capture
    meta = bev_metadata(res.camera, res.camera_to_vehicle)
    for bad in (np.diag([1.0, 1.0, -1.0]), 2 * np.eye(3), [[1.0, 0.5, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]):
        path = tmp_path / "BEV.json"
        path.write_text(json.dumps(dict(meta, camera_to_vehicle={"rotation_matrix": np.asarray(bad).tolist(),
                                                                 "translation": [0.0, 0.0, 50.0]})))
        with pytest.raises(jf.ImageError, match=r"BEV.json.*camera_to_vehicle.rotation_matrix.*not a rotation"):
            load_bev_calibration(path)
    cam, pose = load_bev_calibration(_write_json(tmp_path / "ok.json", meta))
    assert cam.width == res.camera.width
    png = tmp_path / "broken.png"
    out = oiio.ImageOutput.create(str(png))
    spec = oiio.ImageSpec(2, 2, 1, oiio.UINT8)
    spec.attribute(BEV_METADATA_ATTRIBUTE, "{not json")
    assert out.open(str(png), spec) and out.write_image(np.zeros((2, 2, 1), np.uint8))
    out.close()
    with pytest.raises(jf.ImageError, match=r"broken.png.*not valid JSON"):
        read_bev_metadata(png)


def _write_json(path, obj):
    path.write_text(json.dumps(obj))
    return path
