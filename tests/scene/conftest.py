"""Shared small scene fixtures: one street frame, a small rig, small renders (compiled once)."""

from __future__ import annotations

import jax.numpy as jnp
import pytest

import jaxfish as jf
from jaxfish.scene import CaptureConfig, generate_street, render_cube_faces

FACE = 48


@pytest.fixture(scope="session")
def small_rig():
    """jaxfish's default rig at 160 x 121 pixels (float32)."""
    return {k: v.resize(160, 121).astype(jnp.float32) for k, v in jf.default_rig().items()}


@pytest.fixture(scope="session")
def street(small_rig):
    """Frame 0 of seed 0 with the small rig's ego body."""
    return generate_street(0, rig=small_rig)


@pytest.fixture(scope="session")
def small_config():
    """A tiny capture configuration."""
    return CaptureConfig(face_size=FACE, bev_size=32, front_width=32, front_height=24, lidar_channels=8,
                         lidar_points_per_channel=64, radar_points=64, dvs_substeps=2)


@pytest.fixture(scope="session")
def faces_t(street, small_rig):
    """Every camera's five faces at t, ``{camera: {face: RenderBuffers}}``."""
    return {name: render_cube_faces(street, calib, FACE, time=1.0) for name, calib in small_rig.items()}
