"""Synthetic calibration scenes shared by the refit tests (board views seen by a known camera)."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

import jaxfish as jf
from jaxfish.refit import Correspondences, rotation_from_vector
from jaxfish.refit._fit import jit_project

#: 5 views x 20 x 20 corners: N = 2000 correspondences (weight 0 where a corner is off the image).
N_VIEWS = 5
BOARD = 20
SQUARE_M = 0.06


def truth_camera() -> jf.WoodScapeFisheye:
    return jf.WoodScapeFisheye([336.0, -30.5, 47.0, -7.0], width=1280, height=966, cx_offset=3.5, cy_offset=-2.75,
                               aspect_ratio=1.0015)


def board_points() -> np.ndarray:
    g = np.stack(np.meshgrid(np.arange(BOARD), np.arange(BOARD)), -1).reshape(-1, 2) * SQUARE_M
    g = g - g.mean(axis=0)
    return np.c_[g, np.zeros(len(g))]


def truth_poses() -> jf.Pose:
    """Board -> camera poses: boards 0.5-0.9 m away, tilted, some far off-axis (beyond 70 degrees)."""
    omegas = np.array([[0.1, -0.2, 0.05], [0.5, 0.3, -0.2], [-0.4, 0.6, 0.3], [0.2, -0.7, 0.1], [-0.6, -0.3, -0.4]])
    ts = np.array([[0.0, 0.0, 0.6], [-0.5, 0.1, 0.45], [0.6, -0.3, 0.5], [0.2, 0.5, 0.35], [-0.3, -0.4, 0.55]])
    return jf.Pose(rotation_from_vector(jnp.asarray(omegas)), jnp.asarray(ts))


def scene(noise_px: float = 0.0, outlier_fraction: float = 0.0, seed: int = 0, camera=None):
    """(correspondences, true camera, true poses, clean pixels)."""
    cam = truth_camera() if camera is None else camera
    poses = truth_poses()
    board = board_points()
    pts = np.tile(board, (N_VIEWS, 1))
    view = np.repeat(np.arange(N_VIEWS), len(board))
    pc = jnp.einsum("nij,nj->ni", poses.rotation_matrix[view], jnp.asarray(pts)) + poses.translation[view]
    uv, valid = jit_project(cam, pc)  # the compiled projection refit itself uses
    valid = valid & cam.contains(uv)
    clean = np.asarray(uv)
    rng = np.random.default_rng(seed)
    pixels = clean + rng.normal(size=clean.shape) * noise_px
    if outlier_fraction:
        out = rng.random(len(pixels)) < outlier_fraction
        pixels[out] += rng.choice([-1, 1], size=(out.sum(), 2)) * rng.uniform(15, 40, (out.sum(), 2))
    weight = np.asarray(valid, dtype=np.float64)
    return Correspondences(pts, pixels, view, weight), cam, poses, clean


def initial_camera() -> jf.WoodScapeFisheye:
    """A poor start: an equidistant lens with a 5 % focal error, centred principal point."""
    return jf.WoodScapeFisheye([336.0 * 1.05, 0.0, 0.0, 0.0], width=1280, height=966)
