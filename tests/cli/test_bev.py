"""``jaxfish bev`` on a capture and on a built SynWoodScape-layout sample (both of the analytic BEV
scene): files, metadata, scores, and clear errors."""

from __future__ import annotations

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from typer.testing import CliRunner

import jaxfish as jf
from jaxfish import bev
from jaxfish.bev import bev_metadata
from jaxfish.cli import app
from jaxfish.io import read_bev_metadata, read_label_png, write_label_png
from tests.bev.conftest import render
from tests.bev.small_capture import BEV_MPP, BEV_SIZE, CAM_H, CAM_W, shared_bev_capture

VIEW_FILES = ("semantic.png", "semantic_color.png", "height.npy", "height.png", "occupancy.png")


def test_bev_on_a_capture(tmp_path, tmp_path_factory):
    cap = shared_bev_capture(tmp_path_factory)
    out = tmp_path / "out"
    result = CliRunner().invoke(app, ["bev", str(cap), "--out", str(out), "--frames", "0"])
    assert result.exit_code == 0, result.output
    assert "fused mIoU" in result.output and "IPM mIoU" in result.output and "road" in result.output
    text = result.output.replace("\n", " ")
    assert "on all cells" in text and "on the cells it observed" in text and "coverage" in text
    for view in ("truth", "fused"):
        for name in VIEW_FILES:
            assert (out / view / f"00000_{name}").is_file(), (view, name)
    assert (out / "ipm" / "00000_semantic_color.png").is_file()
    meta = read_bev_metadata(out / "fused" / "00000_semantic.png")
    assert meta["metres_per_pixel"] == pytest.approx(BEV_MPP) and meta["width"] == BEV_SIZE
    scores = json.loads((out / "scores.json").read_text())
    assert set(scores["miou"]) == {"fused", "ipm"} and 0.0 < scores["miou"]["fused"] <= 1.0
    # both scores and the coverage of both methods: unobserved cells are misses in "miou" only
    for m in ("fused", "ipm"):
        assert scores["miou"][m] <= scores["miou_observed"][m] <= 1.0 and 0.0 < scores["coverage"][m] <= 1.0
        assert scores["samples"][0][f"coverage_{m}"] == pytest.approx(scores["coverage"][m])
    assert "vehicle" in scores["per_class_iou_observed"]["fused"]
    assert scores["samples"][0]["sample"] == "00000" and "vehicle" in scores["per_class_iou"]["fused"]
    truth = read_label_png(out / "truth" / "00000_semantic.png")
    assert {7, 8, 10}.issubset(set(np.unique(truth).tolist()))
    bad = CliRunner().invoke(app, ["bev", str(cap), "--out", str(out), "--frames", "3"])
    assert bad.exit_code == 2 and "not in the capture" in bad.output.replace("\n", "")


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    """A built sample ``00007``: the four fisheyes' range and class maps, calibrations, BEV.json and
    the true top view, all of the analytic scene."""
    root = tmp_path_factory.mktemp("dataset")
    rig = jf.default_rig(width=CAM_W, height=CAM_H, dtype=jnp.float32)
    rays, oks = jax.jit(bev.rig_rays)(bev.stack_cameras([c.camera for c in rig.values()]))
    for (name, calib), ray, ok in zip(rig.items(), rays, oks, strict=True):
        jf.save_calibration(calib, root / "calibration_data" / f"{name}.json")
        r = np.asarray(calib.camera_to_vehicle.rotation_matrix, np.float64)
        rng, cls = render(np.asarray(ray, np.float64) @ r.T, np.asarray(calib.camera_to_vehicle.translation, np.float64))
        (root / "depth_maps" / "raw_data").mkdir(parents=True, exist_ok=True)
        np.save(root / "depth_maps" / "raw_data" / f"00007_{name}.npy", np.where(ok, rng, 0.0).astype(np.float32))
        write_label_png(root / "semantic_annotations" / "gtLabels" / f"00007_{name}.png", np.where(ok, cls, 0))
    cam = jf.Orthographic(BEV_MPP, width=BEV_SIZE, height=BEV_SIZE, dtype=jnp.float32)
    pose = jf.Pose(np.array([[0.0, -1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, -1.0]]), np.array([1.3, 0.0, 50.0]),
                   dtype=jnp.float32)
    (root / "calibration_data" / "BEV.json").write_text(json.dumps(bev_metadata(cam, pose)))
    ground = np.asarray(jax.jit(bev.bev_ground_points)(cam, pose), np.float64) + np.array([0.0, 0.0, 50.0])
    _, top = render(np.broadcast_to([0.0, 0.0, -1.0], ground.shape), ground)
    write_label_png(root / "semantic_annotations" / "gtLabels" / "00007_BEV.png", top)
    return root, rig, cam, pose


def test_bev_on_a_built_sample(dataset, tmp_path):
    root, rig, cam, pose = dataset
    out = tmp_path / "out"
    result = CliRunner().invoke(app, ["bev", str(root), "--out", str(out), "--samples", "00007"])
    assert result.exit_code == 0, result.output
    names = ("FV", "MVL", "MVR", "RV")
    rng = np.stack([np.load(root / "depth_maps" / "raw_data" / f"00007_{n}.npy") for n in names])
    sem = np.stack([read_label_png(root / "semantic_annotations" / "gtLabels" / f"00007_{n}.png") for n in names])
    # The calibrations as the command reads them (their JSON, cast to float32): a rotation given back
    # by its quaternion may differ from the rig's in the last bit, which can move a z-buffer tie.
    calibs = {n: jf.load_calibration(root / "calibration_data" / f"{n}.json").astype(np.float32) for n in names}
    direct = bev.fuse_cameras_dense([calibs[n].camera for n in names], [calibs[n].camera_to_vehicle for n in names],
                                    rng, sem, cam, pose, valid=rng > 0)
    written = read_label_png(out / "fused" / "00007_semantic.png")
    np.testing.assert_array_equal(np.where(written == 255, -1, written), np.asarray(direct.semantic))
    np.testing.assert_array_equal(np.load(out / "fused" / "00007_height.npy"), np.asarray(direct.height_m))
    scores = json.loads((out / "scores.json").read_text())
    assert scores["kind"] == "dataset" and 0.0 < scores["miou"]["ipm"] <= 1.0


def test_bev_errors_name_the_file(dataset, tmp_path):
    root, *_ = dataset
    result = CliRunner().invoke(app, ["bev", str(tmp_path), "--out", str(tmp_path / "o")])
    assert result.exit_code == 2 and "neither a capture" in result.output.replace("\n", "")
    result = CliRunner().invoke(app, ["bev", str(root), "--out", str(tmp_path / "o"), "--samples", "00008"])
    assert result.exit_code == 2 and "00008" in result.output.replace("\n", "")
    (root / "depth_maps" / "raw_data" / "00007_MVR.npy").rename(tmp_path / "moved.npy")
    try:
        result = CliRunner().invoke(app, ["bev", str(root), "--out", str(tmp_path / "o")])
        assert result.exit_code == 2 and "00007_MVR.npy" in result.output.replace("\n", "")
    finally:
        (tmp_path / "moved.npy").rename(root / "depth_maps" / "raw_data" / "00007_MVR.npy")
    target = root / "depth_maps" / "raw_data" / "00007_MVR.npy"
    good = target.read_bytes()
    target.write_bytes(b"garbage")  # a corrupt range map: one error line naming it, not a traceback
    try:
        result = CliRunner().invoke(app, ["bev", str(root), "--out", str(tmp_path / "o2")])
        text = result.output.replace("\n", "")
        assert result.exit_code == 2 and "00007_MVR.npy" in text and "not a readable .npy" in text, text
        assert not (tmp_path / "o2").exists()  # the samples before it are gone too, and the folders it made
    finally:
        target.write_bytes(good)
    (tmp_path / "o3" / "ipm" / "00007_semantic.png").mkdir(parents=True)  # a file that cannot be written
    result = CliRunner().invoke(app, ["bev", str(root), "--out", str(tmp_path / "o3")])
    text = result.output.replace("\n", "")
    assert result.exit_code == 2 and "00007_semantic.png" in text, text
    assert not [p for p in (tmp_path / "o3").rglob("*") if p.is_file()]  # nothing half-written


def test_miou_ignores_void_and_scores_truth_classes_and_json_has_no_nan(tmp_path, tmp_path_factory):
    from jaxfish.cli import _bev as cli_bev

    # Truth: classes 0 (void), 1, 2; prediction adds class 3 where the truth has 2.
    truth = np.array([0, 0, 1, 1, 2, 2])
    pred = np.array([3, 1, 1, 1, 2, 3])
    counts = cli_bev._truth_counts(truth, 5)
    s = bev.semantic_iou(pred, truth, num_classes=5)
    iou, mean = cli_bev._class_iou(s.intersection, s.union, counts)
    # By hand: class 1: 2 / 3 (a void pixel predicted 1), class 2: 1 / 2; classes 0, 3, 4 not scored.
    np.testing.assert_allclose(iou[1:3], [2 / 3, 1 / 2])
    assert np.isnan(iou[[0, 3, 4]]).all() and mean == pytest.approx((2 / 3 + 1 / 2) / 2)
    assert np.isnan(cli_bev._class_iou(s.intersection, s.union, cli_bev._truth_counts(np.zeros(6, int), 5))[1])
    # A sample whose truth is all void has no score: null in scores.json, never a bare NaN.
    zero = np.zeros(len(jf.groundtruth.SYNWOODSCAPE_CLASSES), np.int64)
    out = tmp_path / "o"
    out.mkdir()
    void_only = zero + (np.arange(len(zero)) == 0)
    counts = ((zero, zero, void_only), (zero, zero, void_only))
    cli_bev._report(tmp_path, "dataset", out, [{"sample": "x", "coverage_fused": 0.5, "coverage_ipm": 1.0,
                                                "miou_fused": float("nan"), "miou_ipm": float("nan"),
                                                "miou_fused_observed": float("nan"), "miou_ipm_observed": float("nan")}],
                    {"fused": [counts], "ipm": [counts]})

    def no_constants(c):
        raise AssertionError(f"invalid JSON constant {c}")

    scores = json.loads((out / "scores.json").read_text(), parse_constant=no_constants)
    assert scores["samples"][0]["miou_fused"] is None and scores["miou"] == {"fused": None, "ipm": None}
    assert scores["samples"][0]["miou_ipm_observed"] is None and scores["miou_observed"] == {"fused": None, "ipm": None}
    # --samples is for datasets: rejected for a capture (as --frames is for a dataset).
    cap = shared_bev_capture(tmp_path_factory)
    result = CliRunner().invoke(app, ["bev", str(cap), "--out", str(tmp_path / "o2"), "--samples", "00000"])
    assert result.exit_code == 2 and "--samples is for built datasets" in result.output.replace("\n", "")


def test_plane_tolerance_follows_the_cube_faces_the_ranges_were_resampled_from(tmp_path, tmp_path_factory):
    import math

    from jaxfish.cli import _bev as cli_bev
    from jaxfish.dataset import CaptureSource, rig_constants_of
    from jaxfish.pipeline import camera_maps
    from tests.bev.small_capture import FACE

    source = CaptureSource(shared_bev_capture(tmp_path_factory))
    cm = camera_maps(source.read(0, bev=False, sensors=False), rig_constants_of(source))
    maps = {"range_resolution_rad": cm.range_resolution_rad}
    assert maps["range_resolution_rad"] == pytest.approx(math.pi / 2 / FACE)
    assert cli_bev._height_tolerance_rad(maps) == pytest.approx(0.6 * math.pi / 2 / FACE)
    # ranges rendered per fisheye pixel (no cube faces recorded): the library default
    assert cli_bev._height_tolerance_rad({}) == bev.GATHER_HEIGHT_TOLERANCE_RAD
    assert cli_bev._height_tolerance_rad({"range_resolution_rad": 1e-5}) == bev.GATHER_HEIGHT_TOLERANCE_RAD
    (tmp_path / "dataset.json").write_text(json.dumps({"capture": {"face_size": 256}}))
    assert cli_bev._dataset_range_resolution(tmp_path) == pytest.approx(math.pi / 512)
    (tmp_path / "dataset.json").write_text(json.dumps({"capture": {"face_size": "big"}}))
    assert cli_bev._dataset_range_resolution(tmp_path) is None
    (tmp_path / "dataset.json").write_text("{not json")
    with pytest.raises(jf.JaxfishError, match="dataset.json"):
        cli_bev._dataset_range_resolution(tmp_path)
