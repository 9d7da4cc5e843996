"""WoodScapeFisheye against the reference math, cv2.fisheye, and its own laws."""

from __future__ import annotations

import textwrap

import cv2
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxfish as jf
from tests import tolerances as tol
from tests.cameras.woodscape_reference import load_reference_intrinsics, reference_project, reference_unproject
from tests.helpers import central_difference_jacobian, run_python, three_ways


def _random_points(n: int, seed: int = 0) -> np.ndarray:
    """Directions over the whole sphere (incl. behind the camera) at distances 0.1-50 m."""
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    return d * rng.uniform(0.1, 50.0, size=(n, 1))


def _image_pixels(cam: jf.WoodScapeFisheye, n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.stack([rng.uniform(-0.5, cam.width - 0.5, n), rng.uniform(-0.5, cam.height - 0.5, n)], axis=-1)


def test_project_matches_reference(real_calibration_path, jit_project):
    cam = jf.load_calibration(real_calibration_path).camera
    ref = load_reference_intrinsics(real_calibration_path)
    pts = _random_points(4000)
    uv, valid = jit_project(cam, jnp.asarray(pts))
    assert bool(jnp.all(valid)), "rho is increasing on [0, pi] for the real calibrations: all points valid"
    np.testing.assert_allclose(np.asarray(uv), reference_project(pts, ref), rtol=0, atol=tol.PROJECT_PX_F64)


def test_unproject_matches_np_roots(real_calibration_path, jit_unproject):
    cam = jf.load_calibration(real_calibration_path).camera
    ref = load_reference_intrinsics(real_calibration_path)
    uv = _image_pixels(cam, 300)
    rays, valid = jit_unproject(cam, jnp.asarray(uv))
    assert bool(jnp.all(valid))
    expected = reference_unproject(uv, ref)
    cos = np.clip(np.sum(np.asarray(rays) * expected, axis=-1), -1, 1)
    angle = np.arctan2(np.linalg.norm(np.cross(np.asarray(rays), expected), axis=-1), cos)
    assert angle.max() < tol.UNPROJECT_RAD_F64
    np.testing.assert_allclose(np.linalg.norm(np.asarray(rays), axis=-1), 1.0, atol=1e-14)


def test_roundtrip_whole_image_float64(real_calibration_path, jit_project, jit_unproject):
    cam = jf.load_calibration(real_calibration_path).camera
    grid = cam.pixel_grid(jnp.float64)
    rays, valid = jit_unproject(cam, grid)
    assert bool(jnp.all(valid))
    uv, valid2 = jit_project(cam, rays)
    assert bool(jnp.all(valid2))
    assert float(jnp.max(jnp.abs(uv - grid))) < tol.ROUNDTRIP_PX_F64


@pytest.mark.parametrize("dtype", [jnp.float64, jnp.float32])
def test_fast_theta_solves_real_lenses_and_agrees_with_the_bisection(real_calibration_path, dtype):
    """The seeded Newton pass alone passes its residual check on the whole domain of a real lens
    (so full frames never take the slow retry), and agrees with the certain bisection."""
    from jaxfish.cameras._woodscape import _bisect, _fast_theta, rho_of_theta

    cam = jf.load_calibration(real_calibration_path).camera.astype(dtype)
    k, theta_max = cam.k, cam.theta_max(dtype)
    rho = jnp.linspace(0.0, float(rho_of_theta(k, theta_max)), 20001, dtype=dtype)
    fast = jax.jit(_fast_theta)(k, rho, theta_max)
    assert bool(jnp.all(fast >= 0)), f"{int(jnp.sum(fast < 0))} radii failed the residual check"
    slow = jax.jit(_bisect)(k, rho, theta_max)
    bound = 4e-14 if dtype == jnp.float64 else 2e-6  # radians: a few ulp of pi
    assert float(jnp.max(jnp.abs(fast - slow))) < bound


def test_lens_that_needs_the_retry_still_solves_every_pixel():
    """A lens whose rho flattens before pi: the seeded Newton pass fails near theta_max, the
    bisection retry takes over and every in-domain radius round-trips."""
    from jaxfish.cameras._woodscape import _fast_theta, rho_of_theta, solve_theta

    cam = _camera_with_stationary_point()
    k, theta_max = cam.k, cam.theta_max()
    rho = jnp.linspace(0.0, float(rho_of_theta(k, theta_max)), 4001)
    assert bool(jnp.any(jax.jit(_fast_theta)(k, rho, theta_max) < 0)), "the case under test"
    theta, converged = jax.jit(solve_theta)(k, rho, theta_max)
    assert bool(jnp.all(converged))
    np.testing.assert_allclose(np.asarray(rho_of_theta(k, theta)), np.asarray(rho), rtol=0, atol=1e-9)


def test_full_frame_float32_temporaries_stay_under_the_mmap_threshold(real_calibration_path):
    """The float32 full-frame program's temporaries (one arena) stay below glibc's 32 MiB mmap
    threshold, so their pages are reused from call to call instead of faulted afresh (compiled
    only, never timed). The retry's bisection keeps one plane of state for this."""
    cam = jf.load_calibration(real_calibration_path).camera.astype(jnp.float32)
    compiled = jax.jit(lambda c, g: c.unproject(g)).lower(cam, cam.pixel_grid(jnp.float32)).compile()
    assert compiled.memory_analysis().temp_size_in_bytes < 32 * 2**20


def test_ray_at_theta_pi_is_valid_and_a_degenerate_lens_gives_finite_invalid_rays():
    """The validity rides in the sign bit of sin(theta)/rho: the ray of theta = pi (where that is
    0, or a rounding below it) stays valid, and a lens whose rays overflow gives invalid, finite
    placeholders."""
    cam = jf.WoodScapeFisheye(np.array([300.0, 0.0, 0.0, 0.0]), width=1280, height=966)
    cx, cy = np.asarray(cam.principal_point)
    uv = jnp.asarray([[cx + 300.0 * np.pi, cy], [cx, cy - 300.0 * np.pi], [cx + 10.0, cy]])
    rays, valid = jax.jit(lambda c, q: c.unproject(q))(cam, uv)
    np.testing.assert_array_equal(np.asarray(valid), [True, True, True])
    np.testing.assert_allclose(np.asarray(rays[:2]), [[0.0, 0.0, -1.0], [0.0, 0.0, -1.0]], atol=1e-12)
    tiny = jf.WoodScapeFisheye(np.array([1e-310, 0.0, 0.0, 0.0]), width=64, height=48)
    rays, valid = jax.jit(lambda c, q: c.unproject(q))(tiny, tiny.pixel_grid(jnp.float64))
    assert not bool(jnp.any(valid)) and bool(jnp.all(jnp.isfinite(rays)))


def test_roundtrip_whole_image_float32(real_calibration_path, jit_project, jit_unproject):
    cam = jf.load_calibration(real_calibration_path).camera.astype(jnp.float32)
    grid = cam.pixel_grid(jnp.float32)
    rays, valid = jit_unproject(cam, grid)
    assert rays.dtype == jnp.float32
    assert bool(jnp.all(valid)), "float32 Newton must converge everywhere (tolerances in radians)"
    uv, _ = jit_project(cam, rays)
    assert float(jnp.max(jnp.abs(uv - grid))) < tol.ROUNDTRIP_PX_F32


def _odd_camera() -> jf.WoodScapeFisheye:
    # rho = k1 θ + k3 θ³ is cv2.fisheye's model with fx = fy = k1, d = (k3 / k1, 0, 0, 0).
    return jf.WoodScapeFisheye(np.array([330.0, 0.0, 21.0, 0.0]), width=1280, height=966, cx_offset=3.25, cy_offset=-2.5)


def test_cv2_fisheye_project_oracle(jit_project):
    cam = _odd_camera()
    k = np.asarray(cam.k)
    cx, cy = np.asarray(cam.principal_point)
    rng = np.random.default_rng(1)
    theta = rng.uniform(0.01, np.radians(73), 500)
    phi = rng.uniform(-np.pi, np.pi, 500)
    pts = np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)], -1) * 3.0
    kmat = np.array([[k[0], 0, cx], [0, k[0], cy], [0, 0, 1]])
    dist = np.array([k[2] / k[0], 0.0, 0.0, 0.0])
    expected, _ = cv2.fisheye.projectPoints(pts[:, None, :], np.zeros(3), np.zeros(3), kmat, dist)
    uv, valid = jit_project(cam, jnp.asarray(pts))
    assert bool(jnp.all(valid))
    np.testing.assert_allclose(np.asarray(uv), expected[:, 0, :], atol=tol.CV2_PROJECT_PX)


def test_cv2_fisheye_unproject_oracle(jit_unproject):
    cam = _odd_camera()
    k = np.asarray(cam.k)
    cx, cy = np.asarray(cam.principal_point)
    rng = np.random.default_rng(2)
    r = rng.uniform(1.0, float(cam.rho(np.radians(73.0))), 500)
    phi = rng.uniform(-np.pi, np.pi, 500)
    uv = np.stack([cx + r * np.cos(phi), cy + r * np.sin(phi)], -1)
    kmat = np.array([[k[0], 0, cx], [0, k[0], cy], [0, 0, 1]])
    dist = np.array([k[2] / k[0], 0.0, 0.0, 0.0])
    crit = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 100, 1e-15)
    und = cv2.fisheye.undistortPoints(uv[:, None, :], kmat, dist, criteria=crit)[:, 0, :]
    expected = np.concatenate([und, np.ones((len(und), 1))], -1)
    expected /= np.linalg.norm(expected, axis=-1, keepdims=True)
    rays, valid = jit_unproject(cam, jnp.asarray(uv))
    assert bool(jnp.all(valid))
    np.testing.assert_allclose(np.asarray(rays), expected, atol=tol.CV2_UNPROJECT_RAD)


@pytest.fixture(scope="module")
def cam64() -> jf.WoodScapeFisheye:
    return jf.default_rig()["FV"].camera


def test_eager_jit_vmap_agree(cam64):
    pts = jnp.asarray(_random_points(64, seed=3))
    uv = jnp.asarray(_image_pixels(cam64, 64, seed=3))
    for fn, arg in ((lambda p: cam64.project(p), pts), (lambda q: cam64.unproject(q), uv)):
        eager, jitted, batched = three_ways(fn, arg)
        for a, b in ((eager, jitted), (eager, batched)):
            np.testing.assert_allclose(a[0], b[0], rtol=0, atol=1e-12)
            np.testing.assert_array_equal(a[1], b[1])


def test_vmap_equals_loop(cam64):
    uv = jnp.asarray(_image_pixels(cam64, 5, seed=4))
    batched, _ = jax.vmap(cam64.unproject)(uv)
    looped = np.stack([np.asarray(cam64.unproject(q)[0]) for q in uv])
    np.testing.assert_allclose(np.asarray(batched), looped, rtol=0, atol=1e-13)


def test_vmap_over_a_batch_of_cameras(real_calibration_path):
    cams = [jf.load_calibration(real_calibration_path).camera, jf.default_rig()["MVL"].camera]
    stacked = jax.tree_util.tree_map(lambda *xs: jnp.stack(xs), *cams)
    uv = jnp.asarray(_image_pixels(cams[0], 16, seed=5))
    rays, valid = jax.vmap(lambda c: c.unproject(uv))(stacked)
    for i, cam in enumerate(cams):
        np.testing.assert_allclose(np.asarray(rays[i]), np.asarray(cam.unproject(uv)[0]), atol=1e-13)
    assert bool(jnp.all(valid))


@pytest.mark.parametrize("shape", [(), (1,), (3, 1, 2)])
def test_batch_shapes(cam64, shape):
    rng = np.random.default_rng(6)
    uv = jnp.asarray(rng.uniform(100, 800, size=shape + (2,)))
    rays, valid = jax.jit(lambda c, x: c.unproject(x))(cam64, uv)
    assert rays.shape == shape + (3,) and valid.shape == shape
    uv2, valid2 = jax.jit(lambda c, x: c.project(x))(cam64, rays)
    assert uv2.shape == shape + (2,) and valid2.shape == shape
    np.testing.assert_allclose(np.asarray(uv2), np.asarray(uv), atol=tol.ROUNDTRIP_PX_F64)
    g_un = jax.jit(jax.grad(lambda x: cam64.unproject(x)[0].sum()))(uv)
    g_pr = jax.jit(jax.grad(lambda x: cam64.project(x)[0].sum()))(rays)
    for g, arg in ((g_un, uv), (g_pr, rays)):
        assert g.shape == arg.shape and bool(jnp.all(jnp.isfinite(g)))


def _check_jacobians(fn, x):
    fn = jax.jit(fn)
    jf_ = np.asarray(jax.jit(jax.jacfwd(fn))(jnp.asarray(x)))
    jr = np.asarray(jax.jit(jax.jacrev(fn))(jnp.asarray(x)))
    assert np.all(np.isfinite(jf_)) and np.all(np.isfinite(jr))
    np.testing.assert_allclose(jf_, jr, rtol=0, atol=tol.JAC_FWD_REV)
    fd = central_difference_jacobian(lambda y: np.asarray(fn(jnp.asarray(y))), np.asarray(x))
    np.testing.assert_allclose(jf_.reshape(fd.shape), fd, rtol=tol.JAC_FINITE_DIFF_REL, atol=tol.JAC_FINITE_DIFF_REL * np.abs(fd).max())


def test_jacobians_wrt_points_and_pixels(cam64):
    _check_jacobians(lambda p: cam64.project(p)[0], np.array([0.7, -0.4, 1.3]))
    _check_jacobians(lambda p: cam64.project(p)[0], np.array([0.7, -0.4, -1.3]))  # behind the image plane
    _check_jacobians(lambda q: cam64.unproject(q)[0], np.array([903.25, 211.5]))


def test_jacobians_wrt_intrinsics(cam64):
    uv = jnp.asarray([[903.25, 211.5], [100.0, 850.0]])
    pts = jnp.asarray([[0.7, -0.4, 1.3], [-2.0, 0.5, -0.3]])

    def unproj(params):
        cam = jf.WoodScapeFisheye(params[:4], width=1280, height=966, cx_offset=params[4], cy_offset=params[5], aspect_ratio=params[6])
        return cam.unproject(uv)[0].ravel()

    def proj(params):
        cam = jf.WoodScapeFisheye(params[:4], width=1280, height=966, cx_offset=params[4], cy_offset=params[5], aspect_ratio=params[6])
        return cam.project(pts)[0].ravel()

    params = np.concatenate([np.asarray(cam64.k), [float(cam64.cx_offset), float(cam64.cy_offset), 1.0002]])
    _check_jacobians(unproj, params)
    _check_jacobians(proj, params)


def test_principal_point_and_optical_axis_are_finite(cam64):
    pp = cam64.principal_point
    ray, valid = cam64.unproject(pp)
    assert bool(valid)
    np.testing.assert_allclose(np.asarray(ray), [0.0, 0.0, 1.0], atol=1e-15)
    uv, valid = cam64.project(jnp.asarray([0.0, 0.0, 2.0]))
    assert bool(valid)
    np.testing.assert_allclose(np.asarray(uv), np.asarray(pp), atol=1e-12)
    j_un = jax.jacfwd(lambda q: cam64.unproject(q)[0])(pp)
    j_un_rev = jax.jacrev(lambda q: cam64.unproject(q)[0])(pp)
    k1 = float(cam64.k[0])
    expected = np.array([[1 / k1, 0], [0, 1 / (k1 * float(cam64.aspect_ratio))], [0, 0]])
    np.testing.assert_allclose(np.asarray(j_un), expected, atol=1e-12)
    np.testing.assert_allclose(np.asarray(j_un_rev), expected, atol=1e-12)
    j_pr = jax.jacrev(lambda p: cam64.project(p)[0])(jnp.asarray([0.0, 0.0, 2.0]))
    np.testing.assert_allclose(np.asarray(j_pr), [[k1 / 2, 0, 0], [0, k1 / 2 * float(cam64.aspect_ratio), 0]], atol=1e-9)
    # Gradients with respect to every intrinsic at the principal point.
    g = jax.grad(lambda c: c.unproject(c.principal_point)[0].sum() + c.project(jnp.asarray([0.0, 0.0, 1.0]))[0].sum())(cam64)
    for leaf in jax.tree_util.tree_leaves(g):
        assert bool(jnp.all(jnp.isfinite(leaf)))
    # The camera centre itself: invalid, but finite values and gradients.
    uv0, valid0 = cam64.project(jnp.zeros(3))
    assert not bool(valid0) and bool(jnp.all(jnp.isfinite(uv0)))
    assert bool(jnp.all(jnp.isfinite(jax.jacrev(lambda p: cam64.project(p)[0])(jnp.zeros(3)))))


def _camera_with_stationary_point() -> jf.WoodScapeFisheye:
    # rho'(θ) = 300 - 2*60 θ + 3*(-10) θ² + 0 -> zero at θ ≈ 1.667 rad (< pi): a lens whose image
    # radius stops growing; pixels beyond rho(theta_max) have no ray.
    return jf.WoodScapeFisheye(np.array([300.0, -60.0, -10.0, 0.0]), width=1280, height=966)


def test_theta_max_domain_and_invalid_pixels():
    cam = _camera_with_stationary_point()
    tmax = float(cam.theta_max())
    roots = np.roots([3 * -10.0, 2 * -60.0, 300.0])
    stationary = float(np.min(roots[(roots.real > 0) & (np.abs(roots.imag) < 1e-12)].real))
    assert tmax == pytest.approx(stationary - jf.cameras.THETA_MAX_MARGIN_RAD, abs=1e-12)
    rho_max = float(cam.rho_max())
    cx, cy = np.asarray(cam.principal_point)
    radii = np.array([0.0, 10.0, 0.5 * rho_max, rho_max - 1e-6, rho_max + 1e-3, rho_max + 50.0, 5000.0])
    uv = jnp.asarray(np.stack([cx + radii, np.full_like(radii, cy)], -1))
    rays, valid = jax.jit(lambda c, x: c.unproject(x))(cam, uv)
    np.testing.assert_array_equal(np.asarray(valid), [True, True, True, True, False, False, False])
    assert bool(jnp.all(jnp.isfinite(rays)))
    g = jax.jit(jax.jacrev(lambda q: cam.unproject(q)[0]))(uv)
    assert bool(jnp.all(jnp.isfinite(g))), "no NaN in gradients, even for invalid pixels"
    # Valid pixels round-trip; the invalid ones are not silently mapped to the optical axis.
    back, pvalid = cam.project(rays[:4])
    assert bool(jnp.all(pvalid))
    np.testing.assert_allclose(np.asarray(back), np.asarray(uv[:4]), atol=1e-6)
    # Points beyond theta_max do not project.
    behind = jnp.asarray([[np.sin(tmax + 0.05), 0.0, np.cos(tmax + 0.05)]])
    assert not bool(cam.project(behind)[1][0])


def test_project_validity_cases(cam64):
    pts = jnp.asarray([[0.0, 0.0, 0.0], [0.0, 0.0, -3.0], [1e-3, 0.0, -3.0], [1.0, 2.0, -0.5]])
    uv, valid = cam64.project(pts)
    np.testing.assert_array_equal(np.asarray(valid), [False, False, True, True])
    assert bool(jnp.all(jnp.isfinite(uv)))


def test_float32_and_mixed_dtypes(cam64):
    cam32 = cam64.astype(jnp.float32)
    uv = jnp.asarray([[640.0, 480.0], [10.0, 20.0]], dtype=jnp.float32)
    rays, valid = cam32.unproject(uv)
    assert rays.dtype == jnp.float32 and bool(jnp.all(valid))
    # A float64 camera computes in the dtype of the coordinates it is given.
    rays64cam, _ = cam64.unproject(uv)
    assert rays64cam.dtype == jnp.float32


def test_shape_errors(cam64):
    with pytest.raises(ValueError, match=r"\(\.\.\., 3\)"):
        cam64.project(jnp.zeros((4, 2)))
    with pytest.raises(ValueError, match=r"\(\.\.\., 2\)"):
        cam64.unproject(jnp.zeros((4, 3)))
    with pytest.raises(ValueError, match="positive"):
        jf.WoodScapeFisheye(np.ones(4), width=0, height=10)


def test_public_api_without_x64(tmp_path):
    """The README example works with JAX's default float32 (no x64) in a fresh interpreter."""
    code = textwrap.dedent(
        """
        import warnings; warnings.simplefilter("error")
        import jax.numpy as jnp, jaxfish as jf
        calib = jf.default_rig()["FV"]
        cam = calib.camera
        uv, valid = cam.project(jnp.array([[1.0, 0.5, 2.0], [0.0, 0.0, 1.0]]))
        rays, valid2 = cam.unproject(uv)
        p = calib.camera_to_vehicle.apply(rays)
        assert uv.dtype == jnp.float32 and rays.dtype == jnp.float32 and p.shape == (2, 3)
        assert bool(valid.all()) and bool(valid2.all())
        assert float(abs(cam.project(rays)[0] - uv).max()) < 1e-3
        print("ok")
        """
    )
    out = run_python(["-c", code])  # no time limit but a guard against a hang
    assert out.returncode == 0 and "ok" in out.stdout, out.stderr
