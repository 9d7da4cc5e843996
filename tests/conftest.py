"""Shared test configuration: float64, strict dtype promotion, one compile cache per run, shared data, compiled functions."""

from __future__ import annotations

import jax

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_dtype_promotion", "strict")

import os  # noqa: E402
import shutil  # noqa: E402
import tempfile  # noqa: E402
from pathlib import Path  # noqa: E402

import pytest  # noqa: E402

TEST_COMPILE_CACHE_ENV = "JAXFISH_TEST_COMPILE_CACHE"
"""The compile cache folder of one test run. The first process of a run (pytest, or its xdist
controller) makes a new empty folder and names it here; its workers and every process a test starts
(the CLI in a subprocess, dask workers) inherit the variable, so that a program compiled by any of
them is loaded, not compiled again, by the others. The folder is removed when the run ends; the
suite never reads or fills the user's cache folder. A loaded program is the compiled program itself:
bytes do not depend on it (tests/dataset/test_compile_cache.py)."""

_OWN_COMPILE_CACHE = TEST_COMPILE_CACHE_ENV not in os.environ
if _OWN_COMPILE_CACHE:
    os.environ[TEST_COMPILE_CACHE_ENV] = tempfile.mkdtemp(prefix="jaxfish_test_xla_")
os.environ["JAXFISH_COMPILE_CACHE"] = os.environ[TEST_COMPILE_CACHE_ENV]

SHARED = Path(__file__).resolve().parents[1].parent / "shared"
REAL_CALIBRATIONS = ("woodscape/FV", "synwoodscape/FV", "synwoodscape/MVL", "synwoodscape/MVR", "synwoodscape/RV")


def pytest_configure(config):
    # pyproject's filterwarnings = error makes every warning a failure; dask.distributed warns when
    # creating a server's scratch directory took over 1 s, which says how busy the machine is, not
    # that anything is wrong (tests/dataset/test_busy_machine.py).
    config.addinivalue_line(
        "filterwarnings", "ignore:Creating scratch directories is taking a surprisingly long time:UserWarning")
    from jaxfish.dataset import use_compile_cache

    use_compile_cache(True)  # this process too: the folder of $JAXFISH_COMPILE_CACHE


def pytest_unconfigure(config):
    if _OWN_COMPILE_CACHE:
        shutil.rmtree(os.environ[TEST_COMPILE_CACHE_ENV], ignore_errors=True)


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


@pytest.fixture(scope="session")
def small_capture():
    """The suite's small capture (`tests.dataset.small_capture`: the demo's settings at scale 0.05,
    fisheyes 64 x 48, BEV 51 px, 2 frames), rendered once per session."""
    from tests.dataset.small_capture import small_capture_dir

    return small_capture_dir()


@pytest.fixture(scope="session")
def reference_build(small_capture, tmp_path_factory):
    """One serial default-options build of `small_capture`: ``(dataset folder, BuildReport)``. Shared
    by every test that reads a built dataset; tests that modify a dataset copy it first."""
    from jaxfish.dataset import build_dataset

    out = tmp_path_factory.mktemp("dataset_reference") / "dataset"
    report = build_dataset(small_capture, out)
    assert report.ok, report.summary()
    return out, report


MAPPINGS_BUDGET = 30000
"""Memory mappings of the test process beyond which compiled programs are dropped after a test.
Every compiled XLA:CPU program keeps memory mappings of its own; a suite that compiles thousands of
programs in one process would pass the kernel's ``vm.max_map_count`` (65530 by default), and the
next compilation then fails inside LLVM (an abort or a segmentation fault, not a Python error)."""


def _mappings() -> int:
    try:
        with open("/proc/self/maps", "rb") as fh:
            return sum(1 for _ in fh)
    except OSError:  # not Linux: no such limit to keep under
        return 0


@pytest.fixture(autouse=True)
def _bounded_compiled_programs():
    """After a test, drop every compiled program (`jax.clear_caches`) when the process holds more
    than `MAPPINGS_BUDGET` memory mappings; they are compiled again when used."""
    yield
    if _mappings() > MAPPINGS_BUDGET:
        import gc

        jax.clear_caches()
        gc.collect()
