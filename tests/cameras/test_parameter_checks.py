"""Cameras built from concrete parameters outside their model's domain are refused, naming the model
and the field; traced parameters are not inspected; calibration files name the file and the field."""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxfish as jf
from jaxfish.calibration import crop_fisheye
from jaxfish.cameras import parameter_problem
from jaxfish.io import read_calibration_file

W, H = 64, 48

REFUSED = {
    "pinhole_fx_0": (lambda: jf.Pinhole(0.0, 20.0, 31.5, 23.5, width=W, height=H), "Pinhole: the focal length fx"),
    "pinhole_fy_negative": (lambda: jf.Pinhole(20.0, -20.0, 31.5, 23.5, width=W, height=H), "focal length fy"),
    "kb_fx_inf": (lambda: jf.KannalaBrandt(math.inf, 20.0, 31.5, 23.5, width=W, height=H), "KannalaBrandt: fx must be finite"),
    "kb_k_nan": (lambda: jf.KannalaBrandt(20.0, 20.0, 31.5, 23.5, (0.1, math.nan, 0.0, 0.0), width=W, height=H),
                 "k must be finite"),
    "opencv_cx_nan": (lambda: jf.OpenCVPinhole(20.0, 20.0, math.nan, 23.5, width=W, height=H), "cx must be finite"),
    "ucm_alpha_above_1": (lambda: jf.UnifiedCamera(20.0, 20.0, 31.5, 23.5, 1.2, width=W, height=H),
                          r"alpha must lie in \[0, 1\]"),
    "ucm_alpha_negative": (lambda: jf.UnifiedCamera(20.0, 20.0, 31.5, 23.5, -0.3, width=W, height=H),
                           r"alpha must lie in \[0, 1\]"),
    "eucm_beta_negative": (lambda: jf.ExtendedUnifiedCamera(300.0, 300.0, 320.0, 240.0, 0.6, -1.0, width=640, height=480),
                           r"ExtendedUnifiedCamera: beta must lie in \(0, inf\)"),
    "eucm_beta_0": (lambda: jf.ExtendedUnifiedCamera(300.0, 300.0, 320.0, 240.0, 0.6, 0.0, width=640, height=480),
                    "beta must lie"),
    "eucm_alpha_above_1": (lambda: jf.ExtendedUnifiedCamera(20.0, 20.0, 31.5, 23.5, 1.2, 1.0, width=W, height=H),
                           "alpha must lie"),
    "ds_alpha_above_1": (lambda: jf.DoubleSphere(20.0, 20.0, 31.5, 23.5, 0.3, 1.2, width=W, height=H),
                         "DoubleSphere: alpha must lie"),
    "mei_fx_0": (lambda: jf.MeiCamera(0.0, 20.0, 31.5, 23.5, 0.5, width=W, height=H), "MeiCamera: the focal length fx"),
    "fov_fy_0": (lambda: jf.FieldOfView(20.0, 0.0, 31.5, 23.5, 0.5, width=W, height=H), "focal length fy"),
    "fisheye624_s_inf": (lambda: jf.Fisheye624(20.0, 20.0, 31.5, 23.5, s=(0.0, 0.0, math.inf, 0.0), width=W, height=H),
                         "s must be finite"),
    "ftheta_singular_affine": (lambda: jf.FTheta(31.5, 23.5, [0.05], c=1.0, d=2.0, e=0.5, width=W, height=H),
                               r"FTheta: the affine matrix \[\[c, d\], \[e, 1\]\] must be invertible"),
    "ocamcalib_singular_affine": (lambda: jf.OCamCalib([-30.0, 0.0, 0.001], xc=23.5, yc=31.5, c=0.0, d=1.0, e=0.0,
                                                       width=W, height=H), "OCamCalib: the affine matrix"),
    "woodscape_aspect_0": (lambda: jf.WoodScapeFisheye((30.0, 0.0, 0.0, 0.0), width=W, height=H, aspect_ratio=0.0),
                           "aspect_ratio must lie"),
    "orthographic_scale_0": (lambda: jf.Orthographic(0.0, width=W, height=H), "metres_per_pixel must lie"),
    "cylindrical_f_negative": (lambda: jf.Cylindrical(width=W, height=H, f=-10.0), "Cylindrical: f must lie"),
    "carla_fov_nan": (lambda: jf.CarlaWideAngle("equidistant", fov=math.nan, width=W, height=H), "fov must be finite"),
}


@pytest.mark.parametrize("name", sorted(REFUSED))
def test_a_camera_outside_its_domain_is_refused(name):
    make, message = REFUSED[name]
    with pytest.raises(ValueError, match=message):
        make()


ACCEPTED = {  # the ends of the documented domains, and degenerate values whose pixels are all masked
    "ucm_alpha_0": lambda: jf.UnifiedCamera(20.0, 20.0, 31.5, 23.5, 0.0, width=W, height=H),
    "ucm_alpha_1": lambda: jf.UnifiedCamera(20.0, 20.0, 31.5, 23.5, 1.0, width=W, height=H),
    "eucm_alpha_1": lambda: jf.ExtendedUnifiedCamera(20.0, 20.0, 31.5, 23.5, 1.0, 1e-6, width=W, height=H),
    "ds_xi_-1": lambda: jf.DoubleSphere(20.0, 20.0, 31.5, 23.5, -1.0, 0.5, width=W, height=H),
    "mei_xi_-1.5": lambda: jf.MeiCamera(20.0, 20.0, 31.5, 23.5, -1.5, width=W, height=H),
    "fov_w_beyond_pi": lambda: jf.FieldOfView(20.0, 20.0, 31.5, 23.5, 3.5, width=W, height=H),
    "ftheta_sheared": lambda: jf.FTheta(31.5, 23.5, [0.05], c=1.0, d=0.2, e=0.5, width=W, height=H),
}


@pytest.mark.parametrize("name", sorted(ACCEPTED))
def test_the_domain_ends_are_accepted(name):
    assert parameter_problem(ACCEPTED[name]()) is None


@pytest.mark.parametrize("dtype", [jnp.int32, jnp.bool_, jnp.complex64, jnp.float16, "not a dtype"])
@pytest.mark.parametrize("make", [
    lambda dtype: jf.KannalaBrandt(330.7, 331.2, 640.6, 483.4, (0.02, -0.003, 0.001, -1e-4), width=1280, height=966,
                                   dtype=dtype),
    lambda dtype: jf.Pinhole(500.0, 500.0, 320.0, 240.0, width=640, height=480, dtype=dtype),
    lambda dtype: jf.CubeRig(16, dtype=dtype),
], ids=["kannala_brandt", "pinhole", "cube_rig"])
def test_a_dtype_other_than_float32_or_float64_is_refused(make, dtype):
    with pytest.raises(TypeError, match="float32 or float64"):
        make(dtype)


def test_traced_parameters_are_not_inspected():
    @jax.jit
    def build(alpha):
        cam = jf.UnifiedCamera(20.0, 20.0, 31.5, 23.5, alpha, width=W, height=H)
        assert parameter_problem(cam) is None  # nothing concrete to inspect
        return cam.project(jnp.asarray([0.1, 0.2, 1.0]))

    uv, ok = build(0.5)
    assert bool(ok) and np.isfinite(np.asarray(uv)).all()


def test_a_batch_of_cameras_is_checked_element_by_element():
    good = jf.UnifiedCamera(jnp.asarray([20.0, 21.0]), 20.0, 31.5, 23.5, jnp.asarray([0.2, 0.4]), width=W, height=H)
    assert parameter_problem(good) is None
    with pytest.raises(ValueError, match=r"alpha must lie in \[0, 1\], got \[0.2 1.4\]"):
        jf.UnifiedCamera(jnp.asarray([20.0, 21.0]), 20.0, 31.5, 23.5, jnp.asarray([0.2, 1.4]), width=W, height=H)


def test_replacing_a_field_is_not_construction():
    """`eqx.tree_at` (as refit does with its parameter vector) bypasses the constructor; `parameter_problem`
    still reports the result."""
    cam = eqx.tree_at(lambda c: c.alpha, jf.UnifiedCamera(20.0, 20.0, 31.5, 23.5, 0.5, width=W, height=H),
                      jnp.asarray(1.5))
    assert "alpha must lie" in parameter_problem(cam)


def test_crop_fisheye_refuses_a_non_finite_offset():
    cam = jf.WoodScapeFisheye((330.0, -20.0, 30.0, -5.0), width=W, height=H)
    with pytest.raises(ValueError, match="crop_fisheye: x0 must be a finite pixel offset"):
        crop_fisheye(cam, math.nan, 0, 32, 32)


@pytest.mark.parametrize(("intrinsics", "field"), [
    ("[0.6, -1.0, 300, 300, 320, 240]", "intrinsic.beta"),
    ("[1.3, 1.0, 300, 300, 320, 240]", "intrinsic.alpha"),
])
def test_a_kalibr_file_outside_the_domain_names_the_field(tmp_path, intrinsics, field):
    path = tmp_path / "camchain.yaml"
    path.write_text(f"cam0:\n  camera_model: eucm\n  intrinsics: {intrinsics}\n  distortion_model: none\n"
                    "  distortion_coeffs: []\n  resolution: [640, 480]\n")
    with pytest.raises(ValueError, match=rf"camchain.yaml.*field '{field}'"):
        read_calibration_file(path)


TRACED_OUTSIDE = {
    "ucm_alpha_above_1": lambda v: jf.UnifiedCamera(20.0, 20.0, 31.5, 23.5, 1.0 + v, width=W, height=H),
    "eucm_beta_negative": lambda v: jf.ExtendedUnifiedCamera(20.0, 20.0, 31.5, 23.5, 0.6, -v, width=W, height=H),
    "eucm_alpha_negative": lambda v: jf.ExtendedUnifiedCamera(20.0, 20.0, 31.5, 23.5, -v, 1.0, width=W, height=H),
    "ds_alpha_above_1": lambda v: jf.DoubleSphere(20.0, 20.0, 31.5, 23.5, 0.3, 1.0 + v, width=W, height=H),
    "ftheta_singular_affine": lambda v: jf.FTheta(31.5, 23.5, [0.05], c=1.0, d=2.0 * v, e=0.5 / v, width=W, height=H),
    "ocamcalib_singular_affine": lambda v: jf.OCamCalib([-30.0, 0.0, 0.001], xc=23.5, yc=31.5, c=v, d=1.0, e=1.0,
                                                        width=W, height=H),
}


@pytest.mark.parametrize("name", sorted(TRACED_OUTSIDE))
def test_traced_parameters_outside_the_domain_mask_every_pixel(name):
    """Under `jax.jit` nothing is refused, so nothing may be valid either (a fit stepping outside the
    domain sees no residuals it could trust)."""
    make = TRACED_OUTSIDE[name]

    @jax.jit
    def images(v):
        cam = make(v)
        th = jnp.linspace(0.0, 1.5, 16)
        points = jnp.stack([jnp.sin(th), 0.3 * jnp.sin(th), jnp.cos(th)], axis=-1)
        pixels = jnp.stack(jnp.meshgrid(jnp.linspace(0.0, W - 1.0, 9), jnp.linspace(0.0, H - 1.0, 7)), axis=-1)
        return cam.project(points), cam.unproject(pixels)

    (uv, ok), (rays, ok2) = images(jnp.asarray(1.0))
    assert not np.asarray(ok).any() and not np.asarray(ok2).any()
    assert np.isfinite(np.asarray(uv)).all() and np.isfinite(np.asarray(rays)).all()
