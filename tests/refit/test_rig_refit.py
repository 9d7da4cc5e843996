"""Joint rig refit (`jaxfish.refit.refit_rig`, ``jaxfish refit --rig``) on a synthetic rig: three
fisheye cameras of the default rig's mounting (FV, MVL, MVR) observing four ground boards, each
seen by two cameras."""

from __future__ import annotations

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxfish as jf
from jaxfish.calibration import Calibration
from jaxfish.refit import Correspondences, intrinsics_vector, refit_rig, rotation_from_vector, with_intrinsics
from jaxfish.refit._fit import jit_project

jax.config.update("jax_enable_x64", True)

NAMES = ("FV", "MVL", "MVR")
CENTRES = np.array([[3.9, 1.7, 0.0], [3.9, -1.7, 0.0], [4.6, 0.8, 0.2], [4.6, -0.8, 0.2]])
"""Board centres in the vehicle frame (metres): front-left and front-right of the car, on the ground."""


def truth_rig() -> list[Calibration]:
    rig = jf.default_rig(dtype=jnp.float64)
    out = []
    for i, n in enumerate(NAMES):
        cam = jf.KannalaBrandt(330.0 + i, 330.5 + i, 640.0 + 2 * i, 481.0 - i, np.array([0.02, 0.02, -0.006, 0.0006]),
                               width=1280, height=966, dtype=jnp.float64)
        out.append(Calibration(n, cam, rig[n].camera_to_vehicle))
    return out


def board() -> np.ndarray:
    g = np.stack(np.meshgrid(np.arange(6), np.arange(6)), -1).reshape(-1, 2) * 0.15
    return np.c_[g - g.mean(0), np.zeros(len(g))]


def target_poses() -> jf.Pose:
    omegas = np.random.default_rng(1).normal(size=(len(CENTRES), 3)) * 0.25
    return jf.Pose(rotation_from_vector(jnp.asarray(omegas)), jnp.asarray(CENTRES))


def observe(truth, noise_px: float = 0.0, seed: int = 0, poses: jf.Pose | None = None) -> list[Correspondences]:
    """Each camera's view of every board (weight 0 where a corner is off its image)."""
    poses = target_poses() if poses is None else poses
    rng = np.random.default_rng(seed)
    b = board()
    obs = []
    for c in truth:
        pts = np.tile(b, (len(CENTRES), 1))
        view = np.repeat(np.arange(len(CENTRES)), len(b))
        pv = jnp.einsum("nij,nj->ni", poses.rotation_matrix[view], jnp.asarray(pts)) + poses.translation[view]
        uv, ok = jit_project(c.camera, c.camera_to_vehicle.inverse().apply(pv))
        ok = np.asarray(ok & c.camera.contains(uv))
        px = np.where(ok[:, None], np.asarray(uv), 0.0) + rng.normal(size=(len(pts), 2)) * noise_px
        obs.append(Correspondences(pts, px, view, ok.astype(np.float64), n_views=len(CENTRES)))
    return obs


def perturbed(truth, *, move_reference: bool = False) -> list[Calibration]:
    """Start values: focal lengths off by 2-3 %, principal points by 4-5 px, k1 by 0.01; every
    mounting but the reference's turned by ~1.5 degrees and moved by 2-3 cm."""
    out = []
    for i, c in enumerate(truth):
        p = np.asarray(intrinsics_vector(c.camera)) * np.array([1.03, 0.98, 1, 1, 1, 1, 1, 1]) \
            + np.array([0, 0, 5, -4, 0.01, 0, 0, 0])
        m = c.camera_to_vehicle
        if i > 0 or move_reference:
            m = jf.Pose(rotation_from_vector(jnp.asarray([0.02, -0.015, 0.01])) @ m.rotation_matrix,
                        m.translation + jnp.asarray([0.03, -0.02, 0.01]))
        out.append(Calibration(c.name, with_intrinsics(c.camera, jnp.asarray(p)), m))
    return out


def test_every_board_is_seen_by_two_cameras():
    counts = np.array([[int(np.asarray(o.weight)[np.asarray(o.view) == v].sum()) for v in range(len(CENTRES))]
                       for o in observe(truth_rig())])
    assert ((counts >= 10).sum(axis=0) >= 2).all(), counts


def test_recovers_intrinsics_and_extrinsics_with_the_first_camera_as_gauge():
    truth = truth_rig()
    start = perturbed(truth)
    res = refit_rig(start, observe(truth))
    assert bool(res.converged) and res.determined
    assert float(res.rms_px) < 1e-6
    for fit, t in zip(res.calibrations, truth, strict=True):
        np.testing.assert_allclose(np.asarray(intrinsics_vector(fit.camera)), np.asarray(intrinsics_vector(t.camera)),
                                   rtol=1e-7, atol=1e-8)
        np.testing.assert_allclose(np.asarray(fit.camera_to_vehicle.translation),
                                   np.asarray(t.camera_to_vehicle.translation), atol=1e-8)
        np.testing.assert_allclose(np.asarray(fit.camera_to_vehicle.rotation_matrix),
                                   np.asarray(t.camera_to_vehicle.rotation_matrix), atol=1e-9)
    # The gauge: the reference camera's mounting is exactly its start value, and it has no parameters.
    assert np.array_equal(np.asarray(res.calibrations[0].camera_to_vehicle.translation),
                          np.asarray(start[0].camera_to_vehicle.translation))
    assert "FV.tx" not in res.parameter_names and "MVL.tx" in res.parameter_names
    np.testing.assert_allclose(np.asarray(res.target_poses.translation), CENTRES, atol=1e-8)
    assert res.calibration("MVR").name == "MVR"


def test_covariance_matches_the_monte_carlo_spread():
    """Predicted standard deviations against the spread of fits to 10 noise draws (0.5 px)."""
    truth = truth_rig()
    start = perturbed(truth)
    names = ("FV.fx", "MVL.cx", "MVL.tx", "MVL.rz", "MVR.k1", "MVR.ty")
    fits, predicted = [], None
    for seed in range(10):
        res = refit_rig(start, observe(truth, 0.5, seed))
        assert bool(res.converged) and res.determined
        if predicted is None:
            predicted = np.array([res.standard_deviation(n) for n in names])
        values = {f"{c.name}.{k}": v for c in res.calibrations
                  for k, v in zip(jf.refit.parameter_names(c.camera), np.asarray(intrinsics_vector(c.camera)), strict=True)}
        for c in res.calibrations:
            t = np.asarray(c.camera_to_vehicle.translation)
            values.update({f"{c.name}.tx": t[0], f"{c.name}.ty": t[1], f"{c.name}.tz": t[2]})
            # rz: the vehicle-frame rotation vector from the truth, z component
            r = np.asarray(c.camera_to_vehicle.rotation_matrix) @ np.asarray(
                truth[NAMES.index(c.name)].camera_to_vehicle.rotation_matrix).T
            values[f"{c.name}.rz"] = 0.5 * (r[1, 0] - r[0, 1])
        fits.append([values[n] for n in names])
    spread = np.asarray(fits).std(axis=0, ddof=1)
    ratio = spread / predicted
    assert np.all((ratio > 0.45) & (ratio < 2.2)), dict(zip(names, ratio, strict=True))
    # Unbiased: the mean error is within 3 standard errors of the mean.
    truth_values = {"FV.fx": 330.0, "MVL.cx": 642.0, "MVR.k1": 0.02}
    for n, tv in truth_values.items():
        k = names.index(n)
        assert abs(np.mean(np.asarray(fits)[:, k]) - tv) < 3 * predicted[k] / np.sqrt(len(fits)) + 1e-9, n


def test_mountings_estimated_from_shared_views_when_the_start_knows_none():
    """kalibr's initialisation: every mounting but the reference's starts at the vehicle origin,
    looking forward; the shared board views place them, and the fit recovers the truth."""
    truth = truth_rig()
    start = [c if i == 0 else Calibration(c.name, c.camera, jf.Pose.identity(dtype=jnp.float64))
             for i, c in enumerate(perturbed(truth))]
    res = refit_rig(start, observe(truth), estimate_mountings=True)
    assert bool(res.converged) and float(res.rms_px) < 1e-6
    for fit, t in zip(res.calibrations, truth, strict=True):
        np.testing.assert_allclose(np.asarray(fit.camera_to_vehicle.translation),
                                   np.asarray(t.camera_to_vehicle.translation), atol=1e-8)


def test_known_targets_fix_the_gauge_in_the_vehicle_frame():
    """Points surveyed in the vehicle frame (target poses known): every mounting is fitted, the
    reference camera's too."""
    truth = truth_rig()
    start = perturbed(truth, move_reference=True)
    poses = target_poses()
    res = refit_rig(start, observe(truth, poses=poses), target_poses=poses, fit_targets=False, reference=None)
    assert res.determined and "FV.tx" in res.parameter_names
    for fit, t in zip(res.calibrations, truth, strict=True):
        np.testing.assert_allclose(np.asarray(fit.camera_to_vehicle.translation),
                                   np.asarray(t.camera_to_vehicle.translation), atol=1e-8)


def test_a_free_gauge_is_refused_and_fixed_intrinsics_are_held():
    truth = truth_rig()
    with pytest.raises(ValueError, match="gauge"):
        refit_rig(truth, observe(truth), reference=None)
    start = perturbed(truth)
    res = refit_rig(start, observe(truth), fixed=("MVL.k4", "k3"), reference="FV")
    assert "MVL.k4" not in res.parameter_names and "FV.k3" not in res.parameter_names and "FV.k4" in res.parameter_names
    assert float(res.calibration("MVL").camera.k[3]) == float(start[1].camera.k[3])


def test_cli_rig_refit_from_a_kalibr_camchain(tmp_path):
    """``jaxfish refit --rig camchain.yaml``: a rig correspondences file, the initial rig as a
    kalibr camchain, one calibration JSON per camera and a report with standard deviations."""
    from typer.testing import CliRunner

    from jaxfish.cli import app
    from jaxfish.io import RigCorrespondences, load_camera_calibration, save_rig_correspondences
    from jaxfish.io._formats import export_calibrations

    truth = truth_rig()
    obs = observe(truth, 0.2, 3)
    save_rig_correspondences(RigCorrespondences("board", tuple(f"t{v}" for v in range(len(CENTRES))),
                                                dict(zip(NAMES, obs, strict=True))), tmp_path / "corr.json")
    export_calibrations(perturbed(truth), "kalibr", tmp_path / "camchain.yaml")
    data = json.loads((tmp_path / "corr.json").read_text())
    assert {v["camera"] for v in data["views"]} == set(NAMES)
    r = CliRunner().invoke(app, ["refit", str(tmp_path / "corr.json"), "--rig", str(tmp_path / "camchain.yaml"),
                                 "--out", str(tmp_path / "out"), "--report", str(tmp_path / "report.json"),
                                 "--estimate-mountings"])
    assert r.exit_code == 0, r.output
    report = json.loads((tmp_path / "report.json").read_text())
    assert report["reference"] == "FV" and report["cameras"]["MVL"]["camera_to_vehicle"]["std"]["tx"] > 0
    assert report["rms_px"] < 0.4
    for c in truth:
        fit = load_camera_calibration(tmp_path / "out" / f"{c.name}.json", dtype=np.float64)
        np.testing.assert_allclose(np.asarray(fit.camera_to_vehicle.translation),
                                   np.asarray(c.camera_to_vehicle.translation), atol=0.03)
        fx = report["cameras"][c.name]["intrinsics"]["fx"]
        assert fx["value"] == float(fit.camera.fx) and abs(fx["value"] - float(c.camera.fx)) < 4 * fx["std"]


def test_a_camera_without_observations_keeps_its_calibration():
    truth = truth_rig()
    start = perturbed(truth)
    obs = dict(zip(NAMES, observe(truth), strict=True))
    del obs["MVR"]
    res = refit_rig(start, obs)
    assert res.determined and not any(n.startswith("MVR.") for n in res.parameter_names)
    assert np.array_equal(np.asarray(intrinsics_vector(res.calibration("MVR").camera)),
                          np.asarray(intrinsics_vector(start[2].camera)))
    assert np.array_equal(np.asarray(res.calibration("MVR").camera_to_vehicle.translation),
                          np.asarray(start[2].camera_to_vehicle.translation))
    np.testing.assert_allclose(np.asarray(res.calibration("MVL").camera_to_vehicle.translation),
                               np.asarray(truth[1].camera_to_vehicle.translation), atol=1e-8)
    with pytest.raises(ValueError, match="unknown camera"):
        refit_rig(start, {"RV": obs["FV"]})


def test_cli_rig_refit_with_points_surveyed_in_the_vehicle_frame(tmp_path):
    """``frame: "vehicle"``: no target pose is fitted and every mounting is, the first camera's too."""
    from typer.testing import CliRunner

    from jaxfish.cli import app
    from jaxfish.io import (
        RigCorrespondences,
        load_camera_calibration,
        save_camera_calibration,
        save_rig_correspondences,
    )

    truth = truth_rig()
    poses = target_poses()
    obs = []
    for o in observe(truth, poses=poses):
        pv = jnp.einsum("nij,nj->ni", poses.rotation_matrix[o.view], o.points) + poses.translation[o.view]
        obs.append(Correspondences(pv, o.pixels, o.view, o.weight, n_views=len(CENTRES)))
    save_rig_correspondences(RigCorrespondences("vehicle", tuple(f"t{v}" for v in range(len(CENTRES))),
                                                dict(zip(NAMES, obs, strict=True))), tmp_path / "corr.json")
    (tmp_path / "rig").mkdir()
    for c in perturbed(truth, move_reference=True):
        save_camera_calibration(c, tmp_path / "rig" / f"{c.name}.json")
    r = CliRunner().invoke(app, ["refit", str(tmp_path / "corr.json"), "--rig", str(tmp_path / "rig"),
                                 "--out", str(tmp_path / "out"), "--report", str(tmp_path / "report.json")])
    assert r.exit_code == 0, r.output
    assert json.loads((tmp_path / "report.json").read_text())["reference"] is None
    for c in truth:
        fit = load_camera_calibration(tmp_path / "out" / f"{c.name}.json", dtype=np.float64)
        np.testing.assert_allclose(np.asarray(fit.camera_to_vehicle.translation),
                                   np.asarray(c.camera_to_vehicle.translation), atol=1e-7)
