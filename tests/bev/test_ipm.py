"""IPM against float64 ray casting of the analytic scene: exact for the ground, and wrong for raised
objects exactly as the closed form says (a point at height h seen from height H at ground distance
d lands at d H / (H - h))."""

from __future__ import annotations

import jax
import numpy as np
import pytest

from jaxfish import bev
from tests.bev.conftest import BEV_MPP, cell_centres, render

PLATE = (6.0, 7.5, -0.75, 0.75, 0.15, 10)  # a low box in front of FV: its top is seen from 0.62 m


@pytest.fixture(scope="module")
def jit_ipm():
    return jax.jit(bev.ipm_semantics)


def _camera(calib):
    r = np.asarray(calib.camera_to_vehicle.rotation_matrix, np.float64)
    return r, np.asarray(calib.camera_to_vehicle.translation, np.float64), float(calib.camera.k[0])


def _expected(centre, k1, boxes):
    """Ray-cast class along the ray from the camera centre through each cell's ground point, and
    whether it is the same class over the cell's sampling uncertainty (nearest fisheye pixel:
    0.71 px, i.e. 0.71 / k1 rad, times 2 for the polynomial's slope at large angles)."""
    x, y = cell_centres()
    g = np.stack([x, y, np.zeros_like(x)], -1)
    dist = np.linalg.norm(g - centre, axis=-1)
    margin = 2.0 * 0.71 / k1 * dist / (centre[2] / dist) + BEV_MPP / 2  # ground footprint of the angle error
    ref = None
    same = margin < 0.3  # samples 0.3 m apart cannot step over a 0.7 m checker square

    for dx in (-1.0, 0.0, 1.0):
        for dy in (-1.0, 0.0, 1.0):
            p = g + np.stack([dx * margin, dy * margin, np.zeros_like(x)], -1)
            d = (p - centre) / np.linalg.norm(p - centre, axis=-1, keepdims=True)
            cls = render(d, centre, boxes)[1]
            ref = cls if ref is None else ref
            same &= cls == ref
    return ref, same, dist


def test_ipm_is_exact_for_the_ground(rig, jit_ipm):
    out = jit_ipm(rig.cameras, rig.poses, rig.semantic_ground, rig.bev_camera, rig.bev_pose)
    sem, idx = np.asarray(out.semantic), np.asarray(out.camera_index)
    seen = idx >= 0
    assert seen.mean() > 0.95  # the four fisheyes see the ground all around the car
    checked = 0
    for i, calib in enumerate(rig.calibs.values()):
        r, t, k1 = _camera(calib)
        ref, same, _ = _expected(t, k1, ())
        cells = (idx == i) & same
        np.testing.assert_array_equal(sem[cells], ref[cells])
        checked += cells.sum()
    assert checked > 0.1 * seen.sum()


def test_blending_picks_the_smallest_incidence_angle(rig, jit_ipm):
    out = jit_ipm(rig.cameras, rig.poses, rig.semantic_ground, rig.bev_camera, rig.bev_pose)
    x, y = cell_centres()
    g = np.stack([x, y, np.zeros_like(x)], -1)
    thetas = []
    for calib in rig.calibs.values():
        r, t, _ = _camera(calib)
        d = g - t
        thetas.append(np.arccos(np.clip((d @ r[:, 2]) / np.linalg.norm(d, axis=-1), -1, 1)))
    thetas = np.stack(thetas)
    srt = np.sort(thetas, axis=0)
    clear = (srt[0] < 1.3) & (srt[1] - srt[0] > 1e-3)  # well inside every lens, no near-tie
    assert clear.mean() > 0.8
    np.testing.assert_array_equal(np.asarray(out.camera_index)[clear], np.argmin(thetas, axis=0)[clear])
    np.testing.assert_allclose(np.asarray(out.incidence_rad)[clear], srt[0][clear], atol=1e-4)


def test_ipm_stretches_raised_objects_by_the_closed_form(rig, jit_ipm):
    fv = rig.calibs["FV"]
    r, t, k1 = _camera(fv)
    ray, ok = (np.asarray(a[0], np.float64) for a in rig.rays)
    rng, cls = render(ray @ r.T, t, (PLATE,))
    sem = np.where(ok > 0, cls, -1).astype(np.int32)[None]
    out = jit_ipm([fv.camera], [fv.camera_to_vehicle], sem, rig.bev_camera, rig.bev_pose)
    ipm = np.asarray(out.semantic)
    ref, same, _ = _expected(t, k1, (PLATE,))
    cells = same & (np.asarray(out.camera_index) == 0)
    np.testing.assert_array_equal(ipm[cells], ref[cells])
    # Along the camera's axis (y = 0) the plate's far top edge x1 lands at d H / (H - h) from the nadir.
    x, y = cell_centres()
    x0, x1, *_, h, c = PLATE
    column = np.argmin(np.abs(y[0]))
    on_plate = x[:, column][ipm[:, column] == c]
    far = t[0] + (x1 - t[0]) * t[2] / (t[2] - h)
    assert abs(on_plate.max() - far) <= BEV_MPP + 2.0 * 0.71 / k1 * (far - t[0]) ** 2 / t[2]
    assert abs(on_plate.min() - x0) <= BEV_MPP  # the base stays where it is
    assert on_plate.max() > x1 + 1.0  # ... so the top is predictably wrong by (far - x1)


def test_bad_inputs_raise_clear_errors(rig):
    with pytest.raises(ValueError, match=r"semantic must be integer \(N=4"):
        bev.ipm_semantics(rig.cameras, rig.poses, rig.semantic[:2], rig.bev_camera, rig.bev_pose)
    with pytest.raises(ValueError, match="do not match the cameras' images"):
        bev.ipm_semantics(rig.cameras, rig.poses, rig.semantic[:, :5], rig.bev_camera, rig.bev_pose)
    with pytest.raises(ValueError, match="valid must be"):
        bev.ipm_semantics(rig.cameras, rig.poses, rig.semantic, rig.bev_camera, rig.bev_pose, valid=np.ones(3, bool))
