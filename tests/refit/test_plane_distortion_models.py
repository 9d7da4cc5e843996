"""The models mei, opencv, fov and fisheye624 in the registry: parameter vectors, the calibration JSON,
conversions (`convert_camera`, ``jaxfish convert --to KEY``) and refits."""

from __future__ import annotations

import json
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from typer.testing import CliRunner

import jaxfish as jf
from jaxfish.cli import _refit as _refit  # noqa: F401  (registers refit and convert)
from jaxfish.cli import app
from jaxfish.io import (
    camera_calibration_from_dict,
    camera_calibration_to_dict,
    load_camera_calibration,
    save_camera_calibration,
)
from jaxfish.refit import (
    PARAMETER_NAMES,
    camera_from_intrinsics,
    canonical_model_name,
    convert_camera,
    intrinsics_from_dict,
    intrinsics_to_dict,
    intrinsics_vector,
    parameter_names,
    refit,
    with_intrinsics,
)
from tests import tolerances as tol
from tests.refit.synthetic import scene

CAMERAS = {
    "mei": jf.MeiCamera(760.0, 765.0, 640.2, 481.7, 1.35, (-0.28, 0.07, 1.2e-3, -6e-4), width=1280, height=966),
    "opencv": jf.OpenCVPinhole(610.0, 612.0, 640.3, 360.8, (-0.31, 0.11, 1.1e-3, -6e-4, -0.02, 0.04, 0.01, -0.003,
                                                            1.5e-3, -2e-4, 8e-4, 1e-4), width=1280, height=720),
    "fov": jf.FieldOfView(300.0, 302.0, 640.2, 481.7, 1.9, width=1280, height=966),
    "fisheye624": jf.Fisheye624(330.0, 331.5, 640.2, 481.7, (0.02, -0.003, 0.001, -1e-4, 1e-5, -1e-6), (1e-3, -5e-4),
                                (1e-3, -1e-4, 5e-4, 2e-5), width=1280, height=966),
}
NAMES = {
    "mei": ("fx", "fy", "cx", "cy", "xi", "k1", "k2", "p1", "p2"),
    "opencv": ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6", "s1", "s2", "s3", "s4"),
    "fov": ("fx", "fy", "cx", "cy", "w"),
    "fisheye624": ("fx", "fy", "cx", "cy", "k0", "k1", "k2", "k3", "k4", "k5", "p0", "p1", "s0", "s1", "s2", "s3"),
}


@pytest.mark.parametrize("model", list(CAMERAS))
def test_parameter_vectors_follow_the_agreed_names(model):
    cam = CAMERAS[model]
    assert canonical_model_name(cam) == model and canonical_model_name(model.upper()) == model
    assert PARAMETER_NAMES[model] == NAMES[model] == parameter_names(cam)
    vec = np.asarray(intrinsics_vector(cam))
    named = dict(zip(NAMES[model], vec, strict=True))
    assert named["fx"] == float(cam.fx) and named["cy"] == float(cam.cy)
    if model == "opencv":  # OpenCV's own distCoeffs order
        np.testing.assert_array_equal([named[k] for k in NAMES[model][4:]], np.asarray(cam.distortion))
    if model == "mei":
        assert named["xi"] == float(cam.xi)
        np.testing.assert_array_equal([named[k] for k in ("k1", "k2", "p1", "p2")], np.asarray(cam.distortion))
    if model == "fisheye624":
        np.testing.assert_array_equal([named[f"k{i}"] for i in range(6)], np.asarray(cam.k))
        np.testing.assert_array_equal([named["p0"], named["p1"]], np.asarray(cam.p))
        np.testing.assert_array_equal([named[f"s{i}"] for i in range(4)], np.asarray(cam.s))
    rebuilt = camera_from_intrinsics(model, vec, width=cam.width, height=cam.height)
    assert type(rebuilt) is type(cam)
    np.testing.assert_array_equal(np.asarray(intrinsics_vector(rebuilt)), vec)
    moved = with_intrinsics(cam, jnp.asarray(vec) * 1.01)
    np.testing.assert_allclose(np.asarray(intrinsics_vector(moved)), vec * 1.01, rtol=1e-15)
    # Differentiable through the vector (what refit uses).
    g = jax.grad(lambda v: jnp.sum(with_intrinsics(cam, v).project(jnp.asarray([[0.1, -0.2, 1.0]]))[0]))(jnp.asarray(vec))
    assert np.isfinite(np.asarray(g)).all() and np.abs(np.asarray(g)).sum() > 0


def test_mei_is_its_own_model_not_an_alias_of_unified():
    assert canonical_model_name("mei") == "mei"
    assert jf.refit.MODEL_CLASSES["mei"] is jf.MeiCamera
    assert "mei" not in jf.refit.MODEL_ALIASES


@pytest.mark.parametrize("model", list(CAMERAS))
def test_calibration_json_round_trip(model, tmp_path):
    cam = CAMERAS[model]
    calib = jf.Calibration("FV", cam, jf.Pose.identity(dtype=jnp.float64))
    path = save_camera_calibration(calib, tmp_path / f"{model}.json")
    data = json.loads(path.read_text())
    assert data["intrinsic"]["model"] == model
    assert set(data["intrinsic"]) == set(NAMES[model]) | {"model", "width", "height"}
    back = load_camera_calibration(path, dtype=jnp.float64)
    assert type(back.camera) is type(cam) and back.camera.image_size == cam.image_size
    np.testing.assert_array_equal(np.asarray(intrinsics_vector(back.camera)), np.asarray(intrinsics_vector(cam)))
    again = camera_calibration_from_dict(camera_calibration_to_dict(back))
    np.testing.assert_array_equal(np.asarray(intrinsics_vector(again.camera)), np.asarray(intrinsics_vector(cam)))
    intr = intrinsics_to_dict(cam)
    missing = {k: v for k, v in intr.items() if k != NAMES[model][-1]}
    with pytest.raises(ValueError, match=rf"intrinsic\.{NAMES[model][-1]}': missing"):
        intrinsics_from_dict(missing, source="x.json")


@pytest.mark.parametrize(("model", "key", "value", "match"), [
    ("fov", "w", math.pi, "below pi"),
    ("fov", "w", -4.0, "below pi"),
    ("mei", "xi", -1.0, "above -1"),
    ("opencv", "fx", 0.0, "focal length must be positive"),
])
def test_calibration_json_refuses_useless_parameters(model, key, value, match):
    intr = intrinsics_to_dict(CAMERAS[model])
    intr[key] = value
    with pytest.raises(ValueError, match=match):
        intrinsics_from_dict(intr, source="x.json")


def test_nested_models_convert_exactly():
    """Kannala-Brandt is Fisheye624 with k4 = k5 = 0 and no tangential / prism terms; the UCM is Mei
    without distortion (ξ = α/(1-α), γ = f/(1-α)); each model converts to itself."""
    kb = jf.KannalaBrandt(330.0, 331.0, 640.2, 481.7, (0.02, -0.003, 0.001, -1e-4), width=1280, height=966)
    res = convert_camera(kb, "fisheye624")
    assert bool(res.converged) and int(res.num_target_invalid) == 0
    assert float(res.max_px) < tol.CONVERT_EXACT_PX
    np.testing.assert_allclose(np.asarray(res.camera.k)[:4], np.asarray(kb.k), atol=1e-8)
    ucm = jf.UnifiedCamera(290.0, 291.0, 640.5, 481.0, 0.58, width=1280, height=966)
    res = convert_camera(ucm, "mei", theta_max=math.radians(120))
    assert bool(res.converged) and float(res.max_px) < tol.CONVERT_EXACT_PX
    assert float(res.camera.xi) == pytest.approx(0.58 / 0.42, rel=1e-7)
    fov = CAMERAS["fov"]
    res = convert_camera(fov, "fov", theta_max=math.radians(150))
    assert float(res.max_px) < tol.CONVERT_EXACT_PX and float(res.camera.w) == pytest.approx(1.9, rel=1e-8)


def test_a_fisheye_converts_to_each_model_from_its_starting_point():
    """Starting points (`jaxfish.refit._initial`): Mei, FOV and Fisheye624 fit an equidistant-like
    fisheye to a fraction of a pixel over 80 degrees; OpenCV over 50 degrees."""
    kb = jf.KannalaBrandt(330.0, 331.0, 640.2, 481.7, (0.02, -0.003, 0.001, -1e-4), width=1280, height=966)
    for model, deg, bound in (("mei", 80, 1.0), ("fov", 80, 1.0), ("fisheye624", 80, 1e-6), ("opencv", 50, 0.5)):
        res = convert_camera(kb, model, theta_max=math.radians(deg))
        assert bool(res.converged) and int(res.num_target_invalid) == 0, model
        assert float(res.max_px) < bound, (model, float(res.max_px))


@pytest.mark.parametrize("model", list(CAMERAS))
def test_cli_convert_to_each_key_writes_a_readable_calibration(model, tmp_path):
    src = tmp_path / "kb.json"
    kb = jf.KannalaBrandt(330.0, 331.0, 640.2, 481.7, (0.02, -0.003, 0.001, -1e-4), width=1280, height=966)
    save_camera_calibration(jf.Calibration("FV", kb, jf.Pose.identity(dtype=jnp.float64)), src)
    out = tmp_path / f"{model}.json"
    result = CliRunner().invoke(app, ["convert", str(src), "--to", model, "-o", str(out), "--theta-max-deg", "50",
                                      "-r", str(tmp_path / "report.json")])
    assert result.exit_code == 0, result.output
    back = load_camera_calibration(out)
    assert canonical_model_name(back.camera) == model
    report = json.loads((tmp_path / "report.json").read_text())
    assert report["target_model"] == model and report["max_px"] < 1.0


@pytest.mark.parametrize("model", list(CAMERAS))
def test_noiseless_refit_recovers_each_model(model):
    truth = CAMERAS[model]
    if model == "opencv":  # the synthetic boards reach 70 degrees: a pinhole sees fewer of them
        truth = jf.OpenCVPinhole(610.0, 612.0, 640.3, 483.2, (-0.05, 0.01, 1.1e-3, -6e-4, 1e-3), width=1280, height=966)
    corr, _, poses, _ = scene(camera=truth)
    assert float(np.sum(np.asarray(corr.weight))) > 400
    start = with_intrinsics(truth, intrinsics_vector(truth) * jnp.asarray(
        [1.02, 0.98, 1.0, 1.0] + [0.9] * (len(NAMES[model]) - 4)) + jnp.asarray([0.0, 0.0, 3.0, -2.0] + [0.0] * (len(NAMES[model]) - 4)))
    fixed = ("k4", "k5", "k6", "s1", "s2", "s3", "s4") if model == "opencv" else None
    res = refit(start, corr, poses=poses, fit_pose=False, fixed=fixed)
    assert bool(res.converged)
    assert float(res.rms_px) < tol.REFIT_NOISELESS_PX
    np.testing.assert_allclose(np.asarray(intrinsics_vector(res.camera)), np.asarray(intrinsics_vector(truth)),
                               rtol=1e-6, atol=1e-8)
