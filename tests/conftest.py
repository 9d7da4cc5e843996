"""Shared test configuration: float64, strict dtype promotion, shared data, compiled functions."""

from __future__ import annotations

import jax

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_dtype_promotion", "strict")

from pathlib import Path  # noqa: E402

import pytest  # noqa: E402

SHARED = Path(__file__).resolve().parents[1].parent / "shared"
REAL_CALIBRATIONS = ("woodscape/FV", "synwoodscape/FV", "synwoodscape/MVL", "synwoodscape/MVR", "synwoodscape/RV")


def pytest_configure(config):
    # pyproject's filterwarnings = error makes every warning a failure; dask.distributed warns when
    # creating a server's scratch directory took over 1 s, which says how busy the machine is, not
    # that anything is wrong (tests/dataset/test_busy_machine.py).
    config.addinivalue_line(
        "filterwarnings", "ignore:Creating scratch directories is taking a surprisingly long time:UserWarning")


def shared_path(relative: str) -> Path:
    """A file of ``../shared`` (test data, read at run time); skips the test when absent."""
    path = SHARED / relative
    if not path.exists():
        pytest.skip(f"{path} not found: the real WoodScape/SynWoodScape test data lives in ../shared beside the checkout")
    return path


@pytest.fixture(params=REAL_CALIBRATIONS)
def real_calibration_path(request) -> Path:
    """Each real calibration file of ``../shared/calibration`` in turn."""
    return shared_path(f"calibration/{request.param}.json")


@pytest.fixture(scope="session")
def jit_project():
    """``jax.jit(lambda cam, p: cam.project(p))``, compiled once per shape for the session."""
    return jax.jit(lambda cam, p: cam.project(p))


@pytest.fixture(scope="session")
def jit_unproject():
    """``jax.jit(lambda cam, uv: cam.unproject(uv))``, compiled once per shape for the session."""
    return jax.jit(lambda cam, uv: cam.unproject(uv))
