"""``jaxfish show DATASET SAMPLE --out PNG`` on the suite's small built dataset (fisheyes 64 x 48)
and the contact sheet's legend (flow colour wheel, depth scale)."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

import jaxfish as jf
from jaxfish.cli._show import BOX_2D_COLOR, BOX_COLORS, OTHER_BOX_COLOR
from jaxfish.io import read_image
from jaxfish.pipeline import depth_to_color
from tests.hostile.corpus import run_cli


@pytest.fixture(scope="module")
def dataset(reference_build, tmp_path_factory):
    """A copy of the suite's small reference build without its lidar sweeps (``lidar_vehicle/``):
    the tests below draw the sheet without lidar, then with a hand-written sweep."""
    out = tmp_path_factory.mktemp("show") / "dataset"
    shutil.copytree(reference_build[0], out)
    shutil.rmtree(out / "lidar_vehicle")
    return out


def test_show_writes_the_sheet_and_one_camera(dataset, tmp_path, capsys):
    code, out, err = run_cli(["show", str(dataset), "0", "--out", str(tmp_path / "s.png")], capsys)
    assert code == 0, err
    assert f"wrote {tmp_path / 's.png'}" in out
    assert "no lidar" in err and "lidar_vehicle/00000.npy" in err  # this copy has none
    sheet = read_image(tmp_path / "s.png")
    assert sheet.shape == (2 * 48, 2 * 64, 3) and sheet.dtype == np.uint8
    code, out, err = run_cli(["show", str(dataset), "00000", "--camera", "RV", "--out", str(tmp_path / "rv.png")], capsys)
    assert code == 0, err
    rv = read_image(tmp_path / "rv.png")
    rgb = read_image(dataset / "rgb_images" / "00000_RV.png")
    assert rv.shape == rgb.shape == (48, 64, 3)
    assert (sheet[:48, 64:] == rv).all()  # the sheet's top right tile is RV
    # Changed pixels are overlay colours: the wireframes of this sample's boxes and its 2D boxes.
    changed = np.any(rv != rgb, axis=-1)
    boxes = json.loads((dataset / "box_3d_annotations_ext" / "00000.json").read_text())["boxes"]
    assert changed.sum() > 20 and any(b["class_id"] != 24 for b in boxes)
    palette = {tuple(c) for c in BOX_COLORS.values()} | {OTHER_BOX_COLOR, BOX_2D_COLOR}
    assert {tuple(p) for p in rv[changed].tolist()} <= palette


def test_show_draws_lidar_points_at_their_pixels(dataset, tmp_path, capsys):
    """A hand-written ``lidar_vehicle`` sweep (no boxes in this copy): every point is drawn at its
    projected pixel in `depth_to_color`'s colour of its range; every other pixel is the RGB image."""
    ds = tmp_path / "ds"
    shutil.copytree(dataset, ds)
    (ds / "box_3d_annotations_ext" / "00000.json").write_text(json.dumps({"boxes": []}))
    (ds / "box_2d_annotations" / "00000_FV.txt").write_text("")
    calib = jf.load_calibration(ds / "calibration_data" / "FV.json")
    pix = np.array([[5.0, 7.0], [32.0, 24.0], [60.0, 40.0]], np.float32)
    rng = np.array([2.0, 9.0, 60.0], np.float32)
    rays, ok = calib.camera.unproject(pix)
    assert np.asarray(ok).all()
    pts = np.asarray(calib.camera_to_vehicle.apply(np.asarray(rays) * rng[:, None]))
    behind = np.asarray(calib.camera_to_vehicle.apply(np.array([[0.0, 0.0, -5.0]], np.float32)))
    lidar = np.concatenate([np.concatenate([pts, behind]), np.ones((4, 1))], axis=1).astype(np.float32)
    (ds / "lidar_vehicle").mkdir()
    np.save(ds / "lidar_vehicle" / "00000.npy", lidar)
    code, out, err = run_cli(["show", str(ds), "0", "--camera", "FV", "--out", str(tmp_path / "fv.png")], capsys)
    assert code == 0, err
    assert "no lidar" not in err
    fv = read_image(tmp_path / "fv.png")
    rgb = read_image(ds / "rgb_images" / "00000_FV.png")
    changed = np.argwhere(np.any(fv != rgb, axis=-1))
    expected = np.rint(pix[:, ::-1]).astype(int)
    assert {tuple(p) for p in changed.tolist()} <= {tuple(p) for p in expected.tolist()}
    assert (fv[expected[:, 0], expected[:, 1]] == depth_to_color(rng)).all()


def test_the_contact_sheet_has_a_flow_wheel_and_a_depth_scale(dataset):
    from jaxfish.dataset import contact_sheet
    from jaxfish.dataset._contact import flow_wheel_tile, legend_layout
    from jaxfish.groundtruth import flow_to_color
    from jaxfish.pipeline import DEPTH_COLOR_RANGE_M

    th = 40
    plain = contact_sheet(dataset, "00000", tile_height=th, labels=False, legend=False)
    sheet = contact_sheet(dataset, "00000", tile_height=th, labels=False)
    assert sheet.shape == (plain.shape[0] + th + 4, plain.shape[1], 3)
    assert (sheet[: plain.shape[0]] == plain).all()
    widths = [53, 53, 40, 53, 53]  # 64 x 48 fisheyes and the square BEV at 40 px high
    g = legend_layout(th, widths, labels=False)
    # The wheel: the centre is white (no flow); east, south, west, north have flow_to_color's hues.
    r = g.wheel_radius
    assert sheet[g.wheel_cy, g.wheel_cx].tolist() == [255, 255, 255]
    wheel, disk = flow_wheel_tile(r)
    assert disk.sum() > 3 * r * r
    for du, dv in ((1, 0), (0, 1), (-1, 0), (0, -1)):
        got = sheet[g.wheel_cy + dv * r, g.wheel_cx + du * r].astype(int)
        want = np.asarray(flow_to_color(np.array([[[float(du), float(dv)]]], np.float32), max_radius=1.0))[0, 0]
        assert np.abs(got - want.astype(int)).max() <= 1, (du, dv, got, want)
    assert sheet[g.wheel_cy, g.wheel_cx + r, 0] > 200 and sheet[g.wheel_cy, g.wheel_cx - r, 2] > 200  # red east, blue west
    # The depth scale: near (left) to far (right) on depth_to_color's ramp.
    lo, hi = DEPTH_COLOR_RANGE_M
    row = sheet[(g.bar_y0 + g.bar_y1) // 2, g.bar_x0:g.bar_x1]
    assert (row[0] == depth_to_color(np.float32([lo]))[0]).all() and (row[-1] == depth_to_color(np.float32([hi]))[0]).all()
    mid = (g.bar_x1 - g.bar_x0 - 1) / 2
    assert (row[int(mid)] == depth_to_color(np.float32([lo * (hi / lo) ** (int(mid) / (2 * mid))]))[0]).all()
    assert row[0].sum() > row[-1].sum()  # near bright, far dark


def test_show_draws_the_builds_own_lidar(reference_build, tmp_path, capsys):
    """A build's own ``lidar_vehicle`` sweep is read: no "no lidar" line."""
    code, out, err = run_cli(["show", str(reference_build[0]), "0", "--camera", "FV", "--out", str(tmp_path / "a.png")],
                             capsys)
    assert code == 0, err
    assert "no lidar" not in err
