"""BEV ground truth of a capture: scale and axes of the true top view, height and occupancy, the
extra files and their metadata, and clear errors for broken captures."""

from __future__ import annotations

import json
import shutil

import jax.numpy as jnp
import numpy as np
import pytest

import jaxfish as jf
from jaxfish import bev as jbev
from jaxfish.io import (
    CaptureError,
    CaptureReader,
    capture_bev_ground_truth,
    read_bev_metadata,
    write_bev_ground_truth,
)
from jaxfish.scene import generate_street
from tests.bev.small_capture import BEV_MPP as MPP
from tests.bev.small_capture import BEV_SIZE as BEV
from tests.bev.small_capture import SEED, write_bev_capture
from tests.tolerances import BEV_HEIGHT_FROM_DEPTH_M


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    root = write_bev_capture(tmp_path_factory.mktemp("bevcapture"))
    reader = CaptureReader(root)
    return root, reader, capture_bev_ground_truth(reader, 0)


def test_result_keys_scale_and_axes(capture):
    root, reader, res = capture
    assert set(res) >= {"truth", "boxes_prev", "boxes", "vehicle_to_world_prev", "vehicle_to_world", "camera",
                        "actors", "events", "height_m", "occupancy", "metres_per_pixel", "camera_to_vehicle"}
    assert res["events"] is None and res["metres_per_pixel"] == pytest.approx(MPP)
    assert res["height_m"].shape == (BEV, BEV) and res["height_m"].dtype == np.float32
    assert res["occupancy"].dtype == bool and res["truth"].semantic.shape == (BEV, BEV)
    # Axes and scale: every actor's box centre (vehicle frame, from actors.json) falls on a BEV
    # pixel (documented convention: x = x0 - (v - cy) m, y = -(u - cx) m) that shows that actor.
    sens = reader.sensors()["bev"]
    x0 = sens["camera_to_vehicle"]["translation"][0]
    frame = generate_street(SEED, frame=0, rig=reader.rig())
    v2w = res["vehicle_to_world"]
    centres = np.asarray(jf.groundtruth.apply_pose(v2w.inverse(), res["boxes"].box_to_world.translation))
    ids = np.asarray(res["truth"].instances.actor_id)
    hits = seen = 0
    for a, c in zip(np.asarray(res["boxes"].actor_id), centres, strict=True):
        u = round(sens["cx"] - c[1] / MPP)
        v = round(sens["cy"] - (c[0] - x0) / MPP)
        if 1 <= u < BEV - 1 and 1 <= v < BEV - 1 and a != frame.ego.id:
            seen += 1
            hits += int(a in ids[v - 1:v + 2, u - 1:u + 2])
    assert seen >= 3 and hits >= seen - 1  # a tree crown may hide one actor from above


def test_height_and_occupancy(capture):
    _, reader, res = capture
    cam, c2v = res["camera"], res["camera_to_vehicle"]
    from_depth = np.asarray(jbev.height_map(cam, c2v, jnp.asarray(reader.view(0, "bev").depth_m)))
    assert np.max(np.abs(from_depth - res["height_m"])) < BEV_HEIGHT_FROM_DEPTH_M
    sem = np.asarray(res["truth"].semantic)
    road = sem == 7
    assert road.sum() > 50 and np.all(np.abs(res["height_m"][road]) < BEV_HEIGHT_FROM_DEPTH_M)
    assert not res["occupancy"][road].any()
    vehicles = np.isin(sem, (10, 24))
    assert vehicles.any() and res["occupancy"][vehicles].mean() > 0.9
    np.testing.assert_array_equal(res["occupancy"], res["height_m"] > jbev.OCCUPANCY_MIN_HEIGHT_M)


def test_write_files_and_metadata(capture, tmp_path):
    _, _, res = capture
    paths = write_bev_ground_truth(tmp_path, "00001", res)
    rel = sorted(str(p.relative_to(tmp_path)) for p in paths)
    assert rel == ["bev_height/colormap/00001_BEV.png", "bev_height/raw_data/00001_BEV.npy",
                   "bev_occupancy/00001_BEV.png"]
    np.testing.assert_array_equal(np.load(tmp_path / rel[1]), res["height_m"])
    occ = jf.io.read_image(tmp_path / rel[2])[..., 0]
    np.testing.assert_array_equal(occ, res["occupancy"].astype(np.uint8) * 255)
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
    res2 = capture_bev_ground_truth(CaptureReader(copy), 0)
    assert np.max(np.abs(res2["height_m"] - res["height_m"])) < BEV_HEIGHT_FROM_DEPTH_M


def test_errors_name_file_and_field(capture, tmp_path):
    root, _, res = capture
    copy = tmp_path / "cap"
    shutil.copytree(root, copy)
    (copy / "frames/000000/bev/depth_prev.png").unlink()
    with pytest.raises(CaptureError, match="depth_prev.png"):
        capture_bev_ground_truth(CaptureReader(copy), 0)
    sensors = json.loads((copy / "sensors.json").read_text())
    del sensors["bev"]["metres_per_pixel"]
    (copy / "sensors.json").write_text(json.dumps(sensors))
    with pytest.raises(CaptureError, match=r"sensors.json.*bev.metres_per_pixel"):
        capture_bev_ground_truth(CaptureReader(copy), 0)
    with pytest.raises(CaptureError, match="frame 7"):
        capture_bev_ground_truth(CaptureReader(root), 7)
    bad = dict(res, height_m=np.zeros((3, 3), np.float32))
    with pytest.raises(jf.JaxfishError, match="height"):
        write_bev_ground_truth(tmp_path / "out", "00002", bad)
