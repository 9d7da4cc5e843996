"""Refused arguments of the refit API: `Correspondences` with non-finite or oversized points,
pixels or weights, negative weights (the correspondence files' rules), and `convert_camera` sample
counts too small to determine the target model."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxfish as jf
from jaxfish.refit import MAX_CORRESPONDENCE_VALUE, Correspondences, convert_camera, refit
from jaxfish.refit._convert import MIN_AZIMUTHS

PTS = np.random.default_rng(0).normal(size=(12, 3)) * [1, 1, 0.3] + [0, 0, 1.5]
UV = np.random.default_rng(1).uniform(0, 600, size=(12, 2))


def _with(a: np.ndarray, index, value) -> np.ndarray:
    a = np.array(a, dtype=np.float64)
    a[index] = value
    return a


@pytest.mark.parametrize("field", ["points", "pixels"])
@pytest.mark.parametrize("value", [np.inf, -np.inf, np.nan])
def test_non_finite_points_and_pixels_are_refused(field, value):
    pts, uv = (_with(PTS, (5, 1), value), UV) if field == "points" else (PTS, _with(UV, (5, 0), value))
    with pytest.raises(ValueError, match=rf"Correspondences: {field}: values must be finite \(row 5"):
        Correspondences(pts, uv)
    with pytest.raises(ValueError, match="values must be finite"):  # even at weight 0
        Correspondences(pts, uv, weight=_with(np.ones(12), 5, 0.0))


def test_values_beyond_the_file_limit_are_refused_where_the_weight_is_positive():
    with pytest.raises(ValueError, match=r"Correspondences: points: values must be at most 1e\+07 in magnitude, "
                                         r"got 2e\+07 in row 0"):
        Correspondences(_with(PTS, (0, 2), 2 * MAX_CORRESPONDENCE_VALUE), UV)
    with pytest.raises(ValueError, match=r"Correspondences: pixels: values must be at most .* in row 3"):
        Correspondences(PTS, _with(UV, (3, 1), -1e300))
    with pytest.raises(ValueError, match=r"Correspondences: weight: values must be at most .* in row 2"):
        Correspondences(PTS, UV, weight=_with(np.ones(12), 2, 1e8))
    # A dropped point (weight 0) may hold a camera's large finite placeholder projection.
    c = Correspondences(PTS, _with(UV, (3, 1), -1e19), weight=_with(np.ones(12), 3, 0.0))
    assert float(c.pixels[3, 1]) == -1e19


@pytest.mark.parametrize("value,says", [(-1.0, "expected 12 non-negative numbers, got -1 at index 4"),
                                        (np.nan, "values must be finite"), (np.inf, "values must be finite")])
def test_negative_and_non_finite_weights_are_refused(value, says):
    with pytest.raises(ValueError, match=f"Correspondences: weight: {says}"):
        Correspondences(PTS, UV, weight=_with(np.ones(12), 4, value))


def test_valid_correspondences_and_traced_weights_still_work():
    c = Correspondences(PTS, UV, weight=_with(np.ones(12), 3, 0.0))
    assert c.size == 12 and float(c.weight[3]) == 0.0
    summed = jax.jit(lambda w: jnp.sum(Correspondences(PTS, UV, weight=w).weight))
    assert float(summed(jnp.ones(12))) == 12.0
    with pytest.raises((RuntimeError, ValueError), match="Correspondences: weight: values must be finite"):  # jax raises either
        jax.block_until_ready(summed(jnp.asarray(_with(np.ones(12), 0, -1.0))))


def test_refit_with_an_infinite_point_is_refused_not_biased():
    cam = jf.KannalaBrandt(290.0, 290.0, 320.0, 240.0, width=640, height=480)
    with pytest.raises(ValueError, match="points: values must be finite"):
        refit(cam, Correspondences(_with(PTS, (5, 2), np.inf), UV), fit_pose=False)


KB = jf.KannalaBrandt(300.0, 300.0, 320.0, 240.0, (0.02, 0.0, 0.0, 0.0), width=640, height=480)


@pytest.mark.parametrize("kw,error,says", [
    (dict(n_theta=0), ValueError, "n_theta must be >= 1"),
    (dict(n_phi=0), ValueError, "n_phi must be >= 1"),
    (dict(n_theta=2.7), TypeError, "n_theta must be an integer"),
    (dict(n_phi=True), TypeError, "n_phi must be an integer"),
    (dict(n_theta=7), ValueError, "n_theta=7 incidence angles cannot determine the 8 free parameters of kannala_brandt"),
    (dict(n_theta=7, theta_max=1.0), ValueError, "n_theta=7 incidence angles cannot determine"),
    (dict(n_phi=MIN_AZIMUTHS - 1), ValueError, "n_phi=2 azimuths lie in one plane"),
    (dict(fov="image", n_theta=1, n_phi=1), ValueError, "the source projects 4 of the 4 sampled rays, too few"),
])
def test_sample_counts_too_small_to_determine_the_target_are_refused(kw, error, says):
    with pytest.raises(error, match=f"convert_camera: {says}"):
        convert_camera(KB, "kb", **kw)


def test_fixed_parameters_need_fewer_incidence_angles():
    with pytest.raises(ValueError, match="n_theta=3 incidence angles cannot determine the 4 free parameters"):
        convert_camera(KB, "kb", n_theta=3, fixed=("k1", "k2", "k3", "k4"))


def test_no_correspondences_is_still_a_valid_empty_set():
    c = Correspondences(np.zeros((0, 3)), np.zeros((0, 2)), np.zeros(0, np.int32), np.zeros(0), n_views=2)
    assert c.size == 0 and c.n_views == 2
