"""Shared fixtures of the reprojection tests: small cameras, small cube rigs, compiled kernels."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxfish as jf
from jaxfish.reprojection import CubeRig, build_lut, resample_bilinear, resample_depth, resample_nearest

#: Small fisheye used by most tests (jaxfish's own front camera, resized).
FISHEYE_W, FISHEYE_H = 160, 120
FACE_SIZE = 64


@pytest.fixture(scope="session")
def small_fisheye():
    """jaxfish's default front fisheye resized to 160x120, float64 parameters."""
    cam = jf.default_rig()["FV"].camera
    return jf.resize_fisheye(cam, FISHEYE_W, FISHEYE_H).astype(jnp.float64)


@pytest.fixture(scope="session")
def small_rig():
    """A five-face cube rig of 64-px faces (float64)."""
    return CubeRig(FACE_SIZE, dtype=jnp.float64)


@pytest.fixture(scope="session")
def jit_build_lut():
    """``build_lut`` compiled (cameras as arguments; supersample and dtype static)."""
    return jax.jit(build_lut, static_argnames=("supersample", "dtype"))


@pytest.fixture(scope="session")
def cube_lut(jit_build_lut, small_rig, small_fisheye):
    """float64 LUT from the small rig to the small fisheye (one sample per pixel)."""
    return jit_build_lut(small_rig, small_fisheye, dtype=jnp.float64)


@pytest.fixture(scope="session")
def jit_kernels():
    """The three kernels, jitted once for the session."""
    return {
        "bilinear": jax.jit(resample_bilinear),
        "nearest": jax.jit(resample_nearest, static_argnames=("reduce",)),
        "depth": jax.jit(resample_depth, static_argnames=("planar",)),
    }


def face_rays(rig: CubeRig) -> np.ndarray:
    """Unit rays (rig frame, float64) of every face pixel centre: ``(F, S, S, 3)``."""
    s = rig.width
    uu, vv = np.meshgrid(np.arange(s, dtype=np.float64), np.arange(s, dtype=np.float64), indexing="xy")
    uv = np.stack([uu, vv], axis=-1)
    out = []
    for i in range(len(rig.faces)):
        rays, _ = rig.unproject_faces(jnp.full((s, s), i), jnp.asarray(uv))
        out.append(np.asarray(rays, dtype=np.float64))
    return np.stack(out)


def smooth_function(rays: np.ndarray) -> np.ndarray:
    """A smooth 3-channel function of unit ray directions (the analytic cube's content)."""
    x, y, z = rays[..., 0], rays[..., 1], rays[..., 2]
    return np.stack([x + 0.5 * y * z, np.sin(2.0 * y) + 0.25 * x * x, np.cos(1.5 * z) - 0.3 * x], axis=-1)
