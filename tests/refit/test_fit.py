"""refit: recovery of known intrinsics and poses, robust loss, fixed masks, gradients, errors."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxfish as jf
from jaxfish.refit import (
    Correspondences,
    estimate_pose,
    intrinsics_vector,
    parameter_names,
    refit,
    reprojection_residuals,
    robust_rho,
    rotation_from_vector,
    with_intrinsics,
)
from jaxfish.refit._fit import jit_project
from tests import tolerances as tol
from tests.helpers import central_difference_jacobian
from tests.refit.synthetic import initial_camera, scene, truth_camera


def _pose_error(a: jf.Pose, b: jf.Pose) -> tuple[float, float]:
    r = np.einsum("nji,njk->nik", np.asarray(a.rotation_matrix), np.asarray(b.rotation_matrix))
    ang = np.arccos(np.clip((np.trace(r, axis1=1, axis2=2) - 1) / 2, -1, 1))
    return float(ang.max()), float(np.abs(np.asarray(a.translation) - np.asarray(b.translation)).max())


def test_recovers_intrinsics_and_poses_from_noisy_board_views():
    noise = 0.3
    corr, truth, poses, _ = scene(noise_px=noise)
    result = refit(initial_camera(), corr)
    assert bool(result.converged)
    names = parameter_names(truth)
    fitted, expected = np.asarray(intrinsics_vector(result.camera)), np.asarray(intrinsics_vector(truth))
    std = np.asarray(result.standard_deviations[: len(names)])
    assert result.parameter_names[: len(names)] == names
    assert np.all(std > 0)
    z = np.abs(fitted - expected) / std
    assert z.max() < tol.REFIT_SIGMA_BOUND, dict(zip(names, z, strict=True))
    # 2-D residuals of N points with P parameters: E|r|² = 2 σ² (1 - P / 2N).
    n = float(np.sum(np.asarray(corr.weight) > 0))
    expected_rms = noise * np.sqrt(2 * (1 - len(result.parameter_names) / (2 * n)))
    assert abs(float(result.rms_px) - expected_rms) < tol.REFIT_RMS_NOISE_REL * expected_rms
    ang, trans = _pose_error(result.poses, poses)
    assert ang < 2e-3 and trans < 2e-3
    cov = np.asarray(result.covariance)
    np.testing.assert_allclose(cov, cov.T, atol=1e-12 * np.abs(cov).max())
    assert np.linalg.eigvalsh(cov).min() > -1e-12 * np.abs(cov).max()
    assert result.residuals.shape == (corr.size, 2) and result.per_view_rms_px.shape == (5,)
    assert result.standard_deviation("k1") == pytest.approx(float(std[0]))


def test_noiseless_fit_is_exact_and_fixed_parameters_stay():
    corr, truth, poses, _ = scene()
    start = eqx_replace_aspect(initial_camera(), float(truth.aspect_ratio))
    result = refit(start, corr, fixed=("aspect_ratio",))
    assert bool(result.converged)
    assert float(result.rms_px) < tol.REFIT_NOISELESS_PX
    assert float(result.camera.aspect_ratio) == float(truth.aspect_ratio)
    assert "aspect_ratio" not in result.parameter_names
    np.testing.assert_allclose(np.asarray(result.camera.k), np.asarray(truth.k), rtol=1e-7)
    # The same by boolean mask (True = fixed), with the poses given and held.
    mask = [False] * 6 + [True]
    again = refit(start, corr, poses=poses, fixed=mask)
    assert float(again.rms_px) < tol.REFIT_NOISELESS_PX
    assert len(again.parameter_names) == 6 + 30


def eqx_replace_aspect(cam, aspect):
    import equinox as eqx

    return eqx.tree_at(lambda c: c.aspect_ratio, cam, jnp.asarray(aspect, dtype=jnp.float64))


def test_robust_loss_resists_outliers():
    corr, truth, _, _ = scene(noise_px=0.2, outlier_fraction=0.05, seed=1)
    robust = refit(initial_camera(), corr, loss="huber", loss_scale_px=1.0)
    assert bool(robust.converged)
    err = np.abs(np.asarray(intrinsics_vector(robust.camera)) - np.asarray(intrinsics_vector(truth)))
    # Measured with loss="linear" on the same data: k1 off by 2.5 px, cx_offset by 2.2 px.
    assert err[0] < 0.5 and err[4] < 0.1 and err[5] < 0.1, err


def test_objective_gradients_match_finite_differences():
    corr, truth, poses, _ = scene(noise_px=0.5)
    p0 = intrinsics_vector(truth) * 1.01

    @jax.jit
    def objective(p, omega, loss_scale):
        pose = jf.Pose(rotation_from_vector(omega) @ poses.rotation_matrix, poses.translation)
        r = reprojection_residuals(with_intrinsics(truth, p), corr, pose, loss="cauchy", loss_scale_px=loss_scale)
        return jnp.sum(r * r)

    omega0 = jnp.zeros((5, 3))
    gp, gw = jax.grad(objective, argnums=(0, 1))(p0, omega0, 2.0)
    num_p = central_difference_jacobian(lambda p: objective(jnp.asarray(p), omega0, 2.0), np.asarray(p0), eps=1e-6)
    np.testing.assert_allclose(np.asarray(gp), num_p.ravel(), rtol=1e-5, atol=1e-4)
    num_w = central_difference_jacobian(lambda w: objective(p0, jnp.asarray(w).reshape(5, 3), 2.0),
                                        np.zeros(15), eps=1e-7)
    np.testing.assert_allclose(np.asarray(gw).ravel(), num_w.ravel(), rtol=1e-5, atol=1e-3)


def test_robust_losses():
    s = jnp.linspace(0.0, 25.0, 11)
    np.testing.assert_allclose(np.asarray(robust_rho(s, "linear", 2.0)), np.asarray(s))
    h = np.asarray(robust_rho(s, "huber", 2.0))
    np.testing.assert_allclose(h, np.where(s <= 4, s, 4 * np.sqrt(s) - 4), rtol=1e-14)
    np.testing.assert_allclose(np.asarray(robust_rho(s, "cauchy", 2.0)), 4 * np.log1p(np.asarray(s) / 4), rtol=1e-14)
    # The residual scaling realises rho: |r'|² = rho(|r|²).
    rng = np.random.default_rng(0)
    res = rng.normal(size=(64, 2)) * 5
    corr = Correspondences(np.c_[rng.normal(size=(64, 2)), np.ones(64)], np.zeros((64, 2)))
    cam = jf.Pinhole(1.0, 1.0, 0.0, 0.0, width=10, height=10)
    corr = Correspondences(corr.points, -res + np.asarray(corr.points[:, :2]))  # unit focal, z = 1
    residuals = jax.jit(reprojection_residuals, static_argnames="loss")
    for loss in ("linear", "huber", "cauchy", "soft_l1"):
        r = np.asarray(residuals(cam, corr, loss=loss, loss_scale_px=2.0))
        np.testing.assert_allclose(np.sum(r * r, -1), np.asarray(robust_rho(jnp.sum(jnp.asarray(res) ** 2, -1), loss, 2.0)),
                                   rtol=1e-12)
    with pytest.raises(ValueError, match="loss"):
        robust_rho(s, "tukey", 1.0)


@pytest.mark.parametrize("planar", [True, False])
def test_estimate_pose_is_exact_without_noise(planar):
    cam = truth_camera()
    rng = np.random.default_rng(3)
    pts = rng.uniform(-1, 1, (2000, 3))  # the refit scene's size: the compiled unprojection is shared
    if planar:
        pts[:, 2] = 0.0
    truth = jf.Pose(rotation_from_vector(jnp.asarray([0.3, -1.2, 0.4])), jnp.asarray([0.2, -0.1, 0.3]))
    pc = np.asarray(truth.apply(pts))
    uv, valid = jit_project(cam, jnp.asarray(pc))
    assert bool(jnp.all(valid)) and (pc[:, 2] < 0).any(), "some points beyond 90 degrees"
    est = estimate_pose(cam, pts, uv)
    np.testing.assert_allclose(np.asarray(est.rotation_matrix), np.asarray(truth.rotation_matrix), atol=1e-8)
    np.testing.assert_allclose(np.asarray(est.translation), np.asarray(truth.translation), atol=1e-8)


def test_input_errors():
    corr, truth, _, _ = scene()
    with pytest.raises(ValueError, match="unknown parameter"):
        refit(truth, corr, fixed=("k9",))
    with pytest.raises(ValueError, match="loss"):
        refit(truth, corr, loss="tukey")
    with pytest.raises(ValueError, match="fixed mask"):
        refit(truth, corr, fixed=[True, False])
    few = Correspondences(np.ones((3, 3)), np.ones((3, 2)))
    with pytest.raises(ValueError, match="cannot determine"):
        refit(truth, few, fit_pose=False)
    centre = Correspondences(np.zeros((60, 3)), np.full((60, 2), 100.0))  # no point projects: not "rms 0"
    with pytest.raises(ValueError, match="only 0 of 60 correspondences project validly"):
        refit(truth, centre, fit_pose=False)
    with pytest.raises(ValueError, match="shape"):
        Correspondences(np.ones((3, 2)), np.ones((3, 2)))
    with pytest.raises(ValueError, match="unknown lens model"):
        parameter_names("no_such_lens")


def test_copies_of_one_correspondence_are_degenerate():
    """Twenty copies of one correspondence determine no lens: the covariance and the standard
    deviations are NaN (not the 0 or finite numbers a singular inverse happens to give) and
    `determined` is False; a full board set stays determined."""
    corr, _, _, _ = scene()
    i = int(np.argmax(np.asarray(corr.weight) > 0))
    pts, pix = np.asarray(corr.points)[i], np.asarray(corr.pixels)[i]
    copies = Correspondences(np.tile(pts, (20, 1)) + [0.0, 0.0, 0.5], np.tile(pix, (20, 1)), None, np.ones(20))
    result = refit(initial_camera(), copies, fit_pose=False)
    assert not result.determined
    assert np.all(np.isnan(np.asarray(result.covariance))) and np.all(np.isnan(np.asarray(result.standard_deviations)))
    assert refit(initial_camera(), corr).determined
