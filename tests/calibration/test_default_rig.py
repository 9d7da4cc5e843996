"""jaxfish's own default rig: valid lenses, sensible mounting, exact resizing."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest

import jaxfish as jf


def test_default_rig_cameras_and_poses():
    rig = jf.default_rig()
    assert tuple(rig) == jf.CAMERA_NAMES
    looks = {"FV": (1, 0), "RV": (-1, 0), "MVL": (0, 1), "MVR": (0, -1)}
    for name, calib in rig.items():
        cam = calib.camera
        assert (cam.width, cam.height) == (1280, 966)
        assert float(cam.theta_max()) == np.pi, "rho strictly increasing on [0, pi]"
        r = np.asarray(calib.camera_to_vehicle.rotation_matrix)
        np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-12)
        assert np.linalg.det(r) == np.float64(1.0) or abs(np.linalg.det(r) - 1) < 1e-12
        axis = np.asarray(calib.camera_to_vehicle.rotate(jnp.asarray([0.0, 0.0, 1.0])))
        expected = looks[name]
        assert np.dot(axis[:2] / np.linalg.norm(axis[:2]), expected) > 0.99
        assert axis[2] < 0, "tilted towards the ground"
        t = np.asarray(calib.camera_to_vehicle.translation)
        assert 0.3 < t[2] < 1.5
        # Covers the ground around the car: the whole image is valid and wider than 190 degrees.
        rays, valid = cam.unproject(jnp.asarray([[-0.5, cam.height / 2], [cam.width - 0.5, cam.height / 2]]))
        assert bool(jnp.all(valid))
        assert np.degrees(np.arccos(float(rays[0, 2]))) > 95


def test_default_rig_resized():
    small = jf.default_rig(width=320, height=240)
    full = jf.default_rig()
    for name in small:
        assert (small[name].camera.width, small[name].camera.height) == (320, 240)
        # The same ray lands on the resized pixel ((u + 0.5) s - 0.5).
        p = jnp.asarray([0.3, -0.2, 1.0])
        uv_full, _ = full[name].camera.project(p)
        uv_small, _ = small[name].camera.project(p)
        s = np.array([320 / 1280, 240 / 966])
        np.testing.assert_allclose(np.asarray(uv_small), (np.asarray(uv_full) + 0.5) * s - 0.5, atol=1e-9)


def test_resize_needs_a_woodscape_camera():
    calib = jf.Calibration("X", jf.Pinhole.from_fov(64, 48), jf.Pose.identity())
    with pytest.raises(TypeError, match="WoodScapeFisheye"):
        calib.resize(32, 24)
