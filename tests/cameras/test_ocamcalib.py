"""OCamCalib against the toolbox's C functions (cam2world / world2cam, transliterated below), its
file format, and its own laws (round trips, domain edge, gradients)."""

from __future__ import annotations

import json
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxfish.cameras as jc
from jaxfish.io import load_ocamcalib, save_ocamcalib
from jaxfish.io._correspondences import camera_calibration_from_dict, camera_calibration_to_dict
from jaxfish.refit import convert_camera, intrinsics_from_dict, intrinsics_to_dict
from tests import tolerances as tol
from tests.helpers import central_difference_jacobian, three_ways

# A calib_results.txt-like fisheye (1280 x 1024, ~185 degrees): a0 < 0, a1 = 0 as OCamCalib writes.
POL = (-3.3797e2, 0.0, 1.1107e-3, -7.3917e-7, 7.3525e-10)
CENTRE = dict(xc=478.95, yc=639.83)  # row, column
AFFINE = dict(c=1.0004, d=0.0021, e=-0.0013)
W, H = 1280, 1024
N = 256


def _camera(dtype=jnp.float64, pol=POL) -> jc.OCamCalib:
    cam = jc.OCamCalib(np.asarray(pol), (), **CENTRE, **AFFINE, width=W, height=H, dtype=dtype)
    return cam.with_fitted_inverse()


def cam2world(point2d, pol, xc, yc, c, d, e):
    """OCamCalib's C ``cam2world`` (ocam_functions.cpp), line for line: point2d = (row, column);
    returns the unit vector in OCamCalib's frame."""
    invdet = 1 / (c - d * e)
    xp = invdet * ((point2d[0] - xc) - d * (point2d[1] - yc))
    yp = invdet * (-e * (point2d[0] - xc) + c * (point2d[1] - yc))
    r = math.sqrt(xp * xp + yp * yp)
    zp = pol[0]
    r_i = 1.0
    for i in range(1, len(pol)):
        r_i *= r
        zp += r_i * pol[i]
    invnorm = 1 / math.sqrt(xp * xp + yp * yp + zp * zp)
    return np.array([invnorm * xp, invnorm * yp, invnorm * zp])


def world2cam(point3d, invpol, xc, yc, c, d, e):
    """OCamCalib's C ``world2cam`` (the inverse polynomial: an approximation), line for line:
    point3d in OCamCalib's frame; returns (row, column)."""
    norm = math.sqrt(point3d[0] ** 2 + point3d[1] ** 2)
    theta = math.atan(point3d[2] / norm)
    rho = invpol[0]
    t_i = 1.0
    for i in range(1, len(invpol)):
        t_i *= theta
        rho += t_i * invpol[i]
    x = point3d[0] / norm * rho
    y = point3d[1] / norm * rho
    return np.array([x * c + y * d + xc, x * e + y + yc])


def _to_ocam(p):
    """jaxfish (OpenCV) frame -> OCamCalib's frame: (X, Y, Z) -> (Y, X, -Z)."""
    return np.stack([p[..., 1], p[..., 0], -p[..., 2]], -1)


def _pixels(n, seed=0):
    rng = np.random.default_rng(seed)
    return np.stack([rng.uniform(-0.5, W - 0.5, n), rng.uniform(-0.5, H - 0.5, n)], -1)


def test_unproject_is_cam2world(jit_unproject):
    cam = _camera()
    uv = _pixels(N)
    rays, valid = jit_unproject(cam, jnp.asarray(uv))
    assert bool(jnp.all(valid))
    ref = np.stack([cam2world((v, u), POL, **CENTRE, **AFFINE) for u, v in uv])  # (row, column) = (v, u)
    np.testing.assert_allclose(_to_ocam(np.asarray(rays)), ref, rtol=0, atol=tol.MODEL_RAY_F64)


def test_project_is_the_exact_inverse_of_cam2world_and_close_to_world2cam(jit_project):
    cam = _camera()
    uv = _pixels(N, seed=1)
    rays = np.stack([cam2world((v, u), POL, **CENTRE, **AFFINE) for u, v in uv])  # OCamCalib frame
    points = np.stack([rays[:, 1], rays[:, 0], -rays[:, 2]], -1) * 7.5  # back to jaxfish's frame
    got, valid = jit_project(cam, jnp.asarray(points))
    assert bool(jnp.all(valid))
    np.testing.assert_allclose(np.asarray(got), uv, rtol=0, atol=tol.MODEL_PX_F64)
    # The toolbox's own world2cam with the fitted inverse polynomial agrees to its design accuracy
    # (findinvpoly: 0.01 px), which pins the row/column and frame conventions.
    invpol = np.asarray(cam.invpol)
    approx = np.stack([world2cam(r, invpol, **CENTRE, **AFFINE)[::-1] for r in rays])  # (row, col) -> (u, v)
    assert np.abs(approx - uv).max() < 0.02


@pytest.mark.parametrize("dtype,atol", [(jnp.float64, tol.ROUNDTRIP_PX_F64), (jnp.float32, tol.MODEL_PX_F32)])
def test_pixel_ray_pixel_over_the_image(dtype, atol, jit_project, jit_unproject):
    cam = _camera(dtype)
    u, v = np.meshgrid(np.linspace(-0.5, W - 0.5, 16), np.linspace(-0.5, H - 0.5, N // 16))
    grid = jnp.asarray(np.stack([u, v], -1).reshape(-1, 2), dtype)
    rays, ok = jit_unproject(cam, grid)
    assert rays.dtype == dtype and bool(jnp.all(ok))
    back, ok2 = jit_project(cam, rays * 3)
    assert bool(jnp.all(ok2))
    np.testing.assert_allclose(np.asarray(back), np.asarray(grid), rtol=0, atol=atol)


def test_domain_edge_is_the_first_stationary_point(jit_project, jit_unproject):
    # A polynomial whose alpha(rho) turns back inside the image diagonal.
    pol = (-300.0, 0.0, 1.0e-3, 0.0, -1.0e-9)
    cam = _camera(pol=pol)
    rho = np.linspace(0.0, math.hypot(W, H), 200001)
    p = np.polynomial.polynomial.polyval(rho, pol)
    alpha = np.arctan2(rho, -p)
    first = int(np.argmax(np.diff(alpha) <= 0))
    assert 0 < first < len(rho) - 2, "the test lens must fold inside the diagonal"
    assert float(cam.rho_max()) == pytest.approx(rho[first] - 1e-3 * math.hypot(W, H) / math.pi, abs=0.02)
    tm = float(cam.theta_max())
    near = np.array([tm - 1e-6, tm - 1e-9, tm + 1e-9, tm + 1e-6])
    pts = np.stack([np.sin(near), np.zeros(4), np.cos(near)], -1)
    pts = np.tile(pts, (N // 4, 1))
    uv, valid = jit_project(cam, jnp.asarray(pts))
    assert np.asarray(valid)[:4].tolist() == [True, True, False, False]
    assert np.isfinite(np.asarray(uv)).all()
    rays, ok = jit_unproject(cam, uv)
    okv = np.asarray(ok & valid)
    np.testing.assert_allclose(np.asarray(rays)[okv], pts[okv], rtol=0, atol=1e-9)
    # Pixels beyond rho_max: invalid, finite.
    far = np.tile([[CENTRE["yc"], CENTRE["xc"] + float(cam.rho_max()) + 5.0]], (N, 1))
    r2, ok3 = jit_unproject(cam, jnp.asarray(far))
    assert not np.asarray(ok3).any() and np.isfinite(np.asarray(r2)).all()


def test_special_inputs_are_invalid_not_nan(jit_project, jit_unproject):
    cam = _camera()
    pts = np.zeros((N, 3))
    pts[1] = [0, 0, -1.0]  # straight behind
    pts[2] = [np.nan, 0, 1]
    pts[3] = [0, 0, 1.0]  # the axis: valid, at the centre
    uv, valid = jit_project(cam, jnp.asarray(pts))
    assert np.asarray(valid)[:4].tolist() == [False, False, False, True]
    np.testing.assert_allclose(np.asarray(uv)[3], [CENTRE["yc"], CENTRE["xc"]], atol=1e-12)
    assert np.isfinite(np.asarray(uv)).all()
    bad = np.full((N, 2), np.inf)
    rays, ok = jit_unproject(cam, jnp.asarray(bad))
    assert not np.asarray(ok).any() and np.isfinite(np.asarray(rays)).all()
    # a0 >= 0: no lens.
    flat = jc.OCamCalib(np.asarray([1.0, 0.0, 1e-3]), **CENTRE, width=W, height=H)
    assert not bool(flat.project(jnp.asarray([0.1, 0.0, 1.0]))[1])


def test_gradients_finite_and_match_finite_differences():
    cam = _camera()
    p_axis = jnp.asarray([0.0, 0.0, 2.0])
    for fn in (lambda c: c.project(p_axis)[0], lambda c: c.unproject(jnp.asarray([CENTRE["yc"], CENTRE["xc"]]))[0]):
        g = jax.jacfwd(fn)(cam)
        assert all(np.isfinite(np.asarray(x)).all() for x in jax.tree_util.tree_leaves(g))
    point = np.array([0.9, -0.4, 0.35])

    def f(x):  # (a0, a2, a3, xc, c, X, Y, Z) -> pixel
        pol = jnp.asarray(POL).at[0].set(x[0]).at[2].set(x[1] * 1e-3).at[3].set(x[2] * 1e-7)
        c = jc.OCamCalib(pol, xc=x[3], yc=CENTRE["yc"], c=x[4], d=AFFINE["d"], e=AFFINE["e"], width=W, height=H)
        return c.project(x[5:])[0]

    x0 = np.array([POL[0], POL[2] * 1e3, POL[3] * 1e7, CENTRE["xc"], AFFINE["c"], *point])
    fwd = np.asarray(jax.jacfwd(f)(jnp.asarray(x0)))
    rev = np.asarray(jax.jacrev(f)(jnp.asarray(x0)))
    np.testing.assert_allclose(fwd, rev, rtol=0, atol=tol.JAC_FWD_REV * np.abs(fwd).max())
    num = central_difference_jacobian(lambda x: f(jnp.asarray(x)), x0, eps=1e-6)
    np.testing.assert_allclose(fwd, num, rtol=tol.JAC_FINITE_DIFF_REL, atol=1e-6 * np.abs(fwd).max())


def test_eager_jit_vmap_agree():
    cam = _camera()
    pts = jnp.asarray(np.array([[0.3, -0.2, 1.0], [1.0, 0.5, -0.3]]))
    outs = three_ways(lambda c, p: c.project(p), cam, pts)
    for uv, _ in outs[1:]:
        np.testing.assert_allclose(uv, outs[0][0], rtol=0, atol=tol.MODEL_PX_F64)


def test_calibration_json_round_trip():
    cam = _camera()
    d = json.loads(json.dumps(intrinsics_to_dict(cam)))
    assert d["model"] == "ocamcalib" and d["xc"] == CENTRE["xc"] and d["a0"] == POL[0]
    back = intrinsics_from_dict(d)
    assert isinstance(back, jc.OCamCalib)
    for a, b in zip(jax.tree_util.tree_leaves(cam), jax.tree_util.tree_leaves(back), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    calib = {"name": "FV", "extrinsic": {"quaternion": [0, 0, 0, 1], "translation": [1.0, 0.0, 0.5]}, "intrinsic": d}
    again = camera_calibration_to_dict(camera_calibration_from_dict(json.loads(json.dumps(calib))))
    assert again["intrinsic"] == d
    bad = dict(d, a0=5.0)
    with pytest.raises(ValueError, match=r"intrinsic\.a0"):
        intrinsics_from_dict(bad, source="calib.json")


TXT = """#polynomial coefficients for the DIRECT mapping function (ocam_model.ss in MATLAB). These are used by cam2world

5 -3.379700e+02 0.000000e+00 1.110700e-03 -7.391700e-07 7.352500e-10

#polynomial coefficients for the inverse mapping function (ocam_model.invpol in MATLAB). These are used by world2cam

3 5.0e+02 3.0e+02 2.0e+01

#center: "row" and "column", starting from 0 (C convention)

478.950000 639.830000

#affine parameters "c", "d", "e"

1.000400 0.002100 -0.001300

#image size: "height" and "width"

1024 1280
"""


def test_calib_results_txt_reader_and_writer(tmp_path):
    path = tmp_path / "calib_results.txt"
    path.write_text(TXT)
    cam = load_ocamcalib(path)
    assert (cam.width, cam.height) == (W, H)
    np.testing.assert_array_equal(np.asarray(cam.pol)[:5], POL)
    assert float(cam.xc) == CENTRE["xc"] and float(cam.yc) == CENTRE["yc"] and float(cam.d) == AFFINE["d"]
    np.testing.assert_array_equal(np.asarray(cam.invpol)[:4], [500.0, 300.0, 20.0, 0.0])
    # Projection does not depend on the (poor) inverse polynomial: exact all the same.
    ref = _camera()
    pts = jnp.asarray(np.array([[0.3, -0.2, 1.0], [1.0, 0.5, -0.3]]))
    np.testing.assert_allclose(np.asarray(cam.project(pts)[0]), np.asarray(ref.project(pts)[0]), atol=tol.MODEL_PX_F64)
    out = save_ocamcalib(ref, tmp_path / "out.txt")
    back = load_ocamcalib(out)
    for a, b in zip(jax.tree_util.tree_leaves(ref), jax.tree_util.tree_leaves(back), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    # Older files have no image size: the caller gives it.
    old = tmp_path / "old.txt"
    old.write_text(TXT.rsplit("#image size", 1)[0])
    assert load_ocamcalib(old, W, H).width == W


@pytest.mark.parametrize("edit,args,field", [
    (lambda t: t.replace("5 -3.3797", "5 -3.3x97"), {}, r"pol\[0\]"),
    # A missing number shifts the rest, as OCamCalib's fscanf reads them: the file ends early.
    (lambda t: t.replace("1.000400 0.002100 -0.001300", "1.000400 0.002100"), {}, "image size width"),
    (lambda t: t.rsplit("#image size", 1)[0], {}, "image size width"),
    (lambda t: t, {"width": 640, "height": 1024}, "image size width"),
    (lambda t: t.replace("5 -3.3797", "12 -3.3797").replace("7.352500e-10", "7.3525e-10 1 2 3 4 5 6 7"), {},
     "pol length"),
    (lambda t: t.replace("5 -3.3797", "5 3.3797"), {}, r"pol\[0\]"),
    (lambda t: t.replace("1.000400 0.002100 -0.001300", "0.0 1.0 0.0"), {}, "affine c"),
    (lambda t: t.replace("1024 1280", "1024 1280 7"), {}, "image size"),
    (lambda t: t.replace("478.950000", "nan"), {}, r"center xc \(row\)"),
    (lambda t: t.replace("3 5.0e+02", "2.5 5.0e+02"), {}, "invpol length"),
])
def test_malformed_calib_results_name_the_file_and_field(tmp_path, edit, args, field):
    path = tmp_path / "calib_results.txt"
    path.write_text(edit(TXT))
    with pytest.raises(ValueError, match=f"calib_results.txt: field '{field}'"):
        load_ocamcalib(path, **args)


def test_missing_and_non_regular_files(tmp_path):
    with pytest.raises(FileNotFoundError, match="nope.txt"):
        load_ocamcalib(tmp_path / "nope.txt", W, H)
    with pytest.raises(ValueError, match=str(tmp_path)):
        load_ocamcalib(tmp_path, W, H)


def test_convert_a_fisheye_to_ocamcalib():
    source = jc.KannalaBrandt(330.0, 331.0, 640.2, 511.7, (0.02, -0.004, 0.0005, -0.00003), width=W, height=H)
    result = convert_camera(source, "ocamcalib", fov="image", n_theta=48, n_phi=8)
    assert bool(result.converged) and int(result.num_target_invalid) == 0
    assert float(result.max_px) < 0.5 and float(result.rms_px) < 0.1  # two model families: close, not exact
    # The refilled inverse polynomial is a good start (world2cam within its design accuracy).
    cam = result.camera
    assert np.abs(np.asarray(cam.invpol)).max() > 0


def test_refit_holds_the_inverse_polynomial_fixed():
    from jaxfish.refit import Correspondences, refit

    truth = _camera()
    uv = _pixels(N, seed=5)
    rays, ok = truth.unproject(jnp.asarray(uv))
    assert bool(jnp.all(ok))
    start = jc.OCamCalib(np.asarray(POL) * np.array([1.01, 1, 0.98, 1, 1]), truth.invpol, xc=CENTRE["xc"] + 3.0,
                         yc=CENTRE["yc"] - 2.0, **AFFINE, width=W, height=H)
    corr = Correspondences(rays * 5.0, jnp.asarray(uv))
    result = refit(start, corr, fit_pose=False, fixed=("a1", "a5", "a6", "a7", "c", "d", "e"))
    assert not any(n.startswith("invpol") for n in result.parameter_names)  # they move no pixel
    assert np.isfinite(np.asarray(result.standard_deviations)).all()
    assert float(result.rms_px) < 1e-6
    np.testing.assert_array_equal(np.asarray(result.camera.invpol), np.asarray(truth.invpol))
    assert float(result.camera.xc) == pytest.approx(CENTRE["xc"], abs=1e-6)
