"""CarlaWideAngle against CARLA 0.9.16's wide-angle shader, transliterated below from
``Shaders/WideAngleLens.usf`` / ``CameraModelCommon.ush`` and ``Util/CameraModelUtil.cpp``
(``ComputeDistance``: the focal length; ``Center = Size / 2`` on integers), and its blueprint."""

from __future__ import annotations

import json
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxfish.cameras as jc
from jaxfish.refit import convert_camera, intrinsics_from_dict, intrinsics_to_dict
from tests import tolerances as tol
from tests.helpers import central_difference_jacobian, three_ways

W, H = 1281, 963  # odd sizes: the principal point is the integer W // 2, H // 2
N = 256
K = (0.08309221636708493, 0.01112126630599195, 0.008587261043925865, 0.0008542188930970716)  # CARLA's defaults
LENSES = [("perspective", 100.0), ("stereographic", 200.0), ("equidistant", 220.0), ("equisolid", 180.0),
          ("orthographic", 170.0), ("kannala-brandt", 190.0)]


def carla_compute_distance(model, angle, k=K):
    """``CameraModelCommon.ush`` ``ComputeDistance``: R(theta) in focal units."""
    if model == "perspective":
        return math.tan(angle)
    if model == "stereographic":
        return math.tan(angle * 0.5) * 2
    if model == "equidistant":
        return angle
    if model == "equisolid":
        return math.sin(angle * 0.5) * 2
    if model == "orthographic":
        return math.sin(angle)
    result, theta2, theta_n = 1.0, angle * angle, 1.0
    for c in k:
        theta_n *= theta2
        result += c * theta_n
    return result * angle


def carla_compute_angle(model, distance, k=K):
    """``ComputeAngle``: theta(R); kannala-brandt by the shader's 32 Newton iterations."""
    if model == "perspective":
        return math.atan(distance)
    if model == "stereographic":
        return math.atan(distance * 0.5) * 2
    if model == "equidistant":
        return distance
    if model == "equisolid":
        return math.asin(distance * 0.5) * 2
    if model == "orthographic":
        return math.asin(distance)
    theta = distance
    for _ in range(32):
        n = distance - carla_compute_distance(model, theta, k)
        a, t2, tn, dd = 3.0, theta * theta, theta * theta, 1.0
        for c in k:
            dd += a * c * tn
            a += 2.0
            tn *= t2
        theta -= n / -dd
    return theta


def carla_focal(model, fov_deg, height, k=K):
    """``CameraModelUtil::ComputeDistance`` (C++): F = (H / 2) / R(fov / 2) (vertical fov)."""
    return height * 0.5 / carla_compute_distance(model, math.radians(fov_deg) * 0.5, k)


def carla_ray(model, fov_deg, i, j, k=K):
    """``WideAngleLens.usf`` ``MainCS`` for the pixel (i, j): the ray in jaxfish's (OpenCV) frame.
    The shader's direction is in Unreal's frame (x forward, y right, z up)."""
    f = carla_focal(model, fov_deg, H, k)
    uv = ((i - W // 2) / f, (j - H // 2) / f)
    alpha = carla_compute_angle(model, math.hypot(*uv), k)
    phi = math.pi / 2 - alpha
    theta = math.atan2(uv[1], uv[0])
    d = np.array([math.sin(phi), math.cos(phi) * math.cos(theta), -math.cos(phi) * math.sin(theta)])
    d /= np.linalg.norm(d)
    return np.array([d[1], -d[2], d[0]])  # Unreal (forward, right, up) -> OpenCV (right, down, forward)


def _camera(model, fov, dtype=jnp.float64):
    attrs = {"camera_model": model, "fov": repr(fov), "image_size_x": str(W), "image_size_y": str(H)}
    return jc.CarlaWideAngle.from_blueprint(attrs, dtype=dtype)


@pytest.mark.parametrize("model,fov", LENSES)
def test_unproject_is_the_shader_and_project_inverts_it(model, fov, jit_project, jit_unproject):
    cam = _camera(model, fov)
    assert cam.principal_point == (640, 481)
    assert float(cam.focal_length()) == pytest.approx(carla_focal(model, fov, H), rel=1e-14)
    rng = np.random.default_rng(0)
    ij = np.stack([rng.integers(0, W, N), rng.integers(0, H, N)], -1).astype(np.float64)
    rays, valid = jit_unproject(cam, jnp.asarray(ij))
    ok = np.asarray(valid)
    assert ok.mean() > 0.5
    ref = np.stack([carla_ray(model, fov, i, j) for i, j in ij[ok]])
    np.testing.assert_allclose(np.asarray(rays)[ok], ref, rtol=0, atol=1e-12)
    back, ok2 = jit_project(cam, rays * 4.0)
    assert (np.asarray(ok2)[ok]).all()
    np.testing.assert_allclose(np.asarray(back)[ok], ij[ok], rtol=0, atol=tol.ROUNDTRIP_PX_F64)


@pytest.mark.parametrize("model,fov", LENSES)
def test_float32_round_trip(model, fov, jit_project, jit_unproject):
    cam = _camera(model, fov, jnp.float32)
    u, v = np.meshgrid(np.linspace(-0.5, W - 0.5, 16), np.linspace(-0.5, H - 0.5, N // 16))
    grid = jnp.asarray(np.stack([u, v], -1).reshape(-1, 2), jnp.float32)
    rays, ok = jit_unproject(cam, grid)
    back, ok2 = jit_project(cam, rays)
    okv = np.asarray(ok & ok2)
    assert rays.dtype == jnp.float32 and okv.any()
    np.testing.assert_allclose(np.asarray(back)[okv], np.asarray(grid)[okv], rtol=0, atol=tol.MODEL_PX_F32)


@pytest.mark.parametrize("model,edge", [("perspective", math.pi / 2), ("orthographic", math.pi / 2),
                                        ("stereographic", math.pi), ("equisolid", math.pi)])
def test_domain_edges(model, edge, jit_project, jit_unproject):
    cam = _camera(model, 90.0)
    near = np.array([edge - 1e-3, edge - 2e-6, edge + 1e-6, edge + 1e-3])
    pts = np.tile(np.stack([np.sin(near), np.zeros(4), np.cos(near)], -1), (N // 4, 1))
    if edge == math.pi:  # nothing lies beyond pi: the ray straight behind has no azimuth (invalid)
        pts[2:4] = [0.0, 0.0, -1.0]
    uv, valid = jit_project(cam, jnp.asarray(pts))
    assert np.asarray(valid)[:4].tolist() == [True, True, False, False]
    assert np.isfinite(np.asarray(uv)).all()
    rays, ok = jit_unproject(cam, uv)
    okv = np.asarray(ok & valid)
    np.testing.assert_allclose(np.asarray(rays)[okv], pts[okv], rtol=0, atol=1e-7)
    if model in ("orthographic", "equisolid"):  # pixels beyond the lens circle have no ray
        radius = float(cam.focal_length()) * (1.0 if model == "orthographic" else 2.0)
        far = np.tile([[W // 2 + radius * 1.01, H // 2]], (N, 1))
        r, okf = jit_unproject(cam, jnp.asarray(far))
        assert not np.asarray(okf).any() and np.isfinite(np.asarray(r)).all()


def test_kannala_brandt_lens_matches_the_kannala_brandt_camera(jit_project):
    cam = _camera("kannala-brandt", 190.0)
    f = float(cam.focal_length())
    kb = jc.KannalaBrandt(f, f, W // 2, H // 2, K, width=W, height=H)
    assert float(cam.theta_max()) == pytest.approx(float(kb.theta_max()))
    rng = np.random.default_rng(3)
    pts = rng.normal(size=(N, 3))
    a, va = jit_project(cam, jnp.asarray(pts))
    b, vb = jit_project(kb, jnp.asarray(pts))
    assert (np.asarray(va) == np.asarray(vb)).all()
    np.testing.assert_allclose(np.asarray(a)[np.asarray(va)], np.asarray(b)[np.asarray(va)], rtol=0, atol=1e-9)


def test_blueprint_defaults_round_trip_and_errors():
    default = jc.CarlaWideAngle.from_blueprint({})
    assert (default.camera_model, float(default.fov), default.width, default.height) == ("perspective", 90.0, 800, 600)
    kb = jc.CarlaWideAngle.from_blueprint({"camera_model": "kannala-brandt", "role_name": "front"}, 640, 480)
    np.testing.assert_array_equal(np.asarray(kb.k), K)
    again = jc.CarlaWideAngle.from_blueprint(kb.to_blueprint())
    assert again.to_blueprint() == kb.to_blueprint() and again.image_size == (640, 480)
    cases = [
        ({"camera_model": "fisheye"}, "camera_model"),
        ({"fov": "wide"}, "'fov'"),
        ({"fov": "inf"}, "'fov'"),
        ({"camera_model": "orthographic", "fov": "200"}, "'fov'"),
        ({"camera_model": "perspective", "fov": "180"}, "'fov'"),
        ({"focal_length": "300"}, "focal_length"),
        ({"equirectangular": "true"}, "equirectangular"),
        ({"image_size_x": "1280"}, "image_size_x"),
        ({"image_size_y": "-4"}, "image_size_y"),
        ({"camera_model": "kannala-brandt", "k2": "x"}, "'k2'"),
    ]
    for attrs, field in cases:
        with pytest.raises(ValueError, match=field):
            jc.CarlaWideAngle.from_blueprint(attrs, 640, 480)


def test_gradients_finite_and_match_finite_differences():
    cam = _camera("kannala-brandt", 190.0)
    for fn in (lambda c: c.project(jnp.asarray([0.0, 0.0, 2.0]))[0],
               lambda c: c.unproject(jnp.asarray([W // 2, H // 2], jnp.float64))[0]):
        g = jax.jacfwd(fn)(cam)
        assert all(np.isfinite(np.asarray(x)).all() for x in jax.tree_util.tree_leaves(g))

    def f(x):  # (fov, k0, X, Y, Z) -> ray of a pixel and pixel of a point
        c = jc.CarlaWideAngle("kannala-brandt", x[0], jnp.asarray(K).at[0].set(x[1]), width=W, height=H)
        return jnp.concatenate([c.project(x[2:])[0], c.unproject(jnp.asarray([900.0, 100.0]))[0]])

    x0 = np.array([190.0, K[0], 0.7, -0.4, -0.2])
    fwd = np.asarray(jax.jacfwd(f)(jnp.asarray(x0)))
    rev = np.asarray(jax.jacrev(f)(jnp.asarray(x0)))
    np.testing.assert_allclose(fwd, rev, rtol=0, atol=tol.JAC_FWD_REV * np.abs(fwd).max())
    num = central_difference_jacobian(lambda x: f(jnp.asarray(x)), x0, eps=1e-6)
    np.testing.assert_allclose(fwd, num, rtol=tol.JAC_FINITE_DIFF_REL, atol=1e-6 * np.abs(fwd).max())


def test_eager_jit_vmap_agree():
    cam = _camera("equisolid", 180.0)
    pts = jnp.asarray(np.array([[0.3, -0.2, 1.0], [1.0, 0.5, -0.2]]))
    outs = three_ways(lambda c, p: c.project(p), cam, pts)
    for uv, _ in outs[1:]:
        np.testing.assert_allclose(uv, outs[0][0], rtol=0, atol=tol.MODEL_PX_F64)


def test_calibration_json_round_trip():
    for model, fov in LENSES:
        cam = _camera(model, fov)
        d = json.loads(json.dumps(intrinsics_to_dict(cam)))
        assert d["model"] == "carla_wide_angle" and d["camera_model"] == model and d["fov"] == fov
        back = intrinsics_from_dict(d)
        assert back.camera_model == model and back.image_size == (W, H)
        np.testing.assert_array_equal(np.asarray(back.k), np.asarray(cam.k))
    d = intrinsics_to_dict(_camera("equidistant", 200.0))
    for bad, field in (({"camera_model": "fisheye"}, "camera_model"), ({"camera_model": 3}, "camera_model"),
                       ({"fov": 400.0}, "fov")):
        with pytest.raises(ValueError, match=rf"calib.json: field 'intrinsic\.{field}'"):
            intrinsics_from_dict(dict(d, **bad), source="calib.json")
    missing = {k: v for k, v in d.items() if k != "camera_model"}
    with pytest.raises(ValueError, match=r"intrinsic\.camera_model': missing"):
        intrinsics_from_dict(missing, source="calib.json")


def test_convert_a_centred_kannala_brandt_camera_exactly():
    f = 300.0
    source = jc.KannalaBrandt(f, f, W // 2, H // 2, (0.03, -0.004, 0.0006, -0.00004), width=W, height=H)
    result = convert_camera(source, "carla_wide_angle", fov="image", n_theta=48, n_phi=8)
    assert bool(result.converged) and result.camera.camera_model == "kannala-brandt"
    assert float(result.max_px) < tol.CONVERT_EXACT_PX
    assert float(result.camera.focal_length()) == pytest.approx(f, rel=1e-9)
