"""The builder writes the recorded bytes: the SHA-256 of every file of the small build (serial and
on a 2-worker dask cluster) and of its backward-flow variant equal the checked-in manifests
(``tests/dataset/manifests/``, written by ``scripts/check_build_bytes.py --record``).

The bytes depend on XLA's CPU code generation and the library versions: on an environment other
than the recorded one (`environment`) the tests skip, naming the difference, rather than compare."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest

from jaxfish.dataset import BuildOptions, build_dataset

SCRIPT = Path(__file__).resolve().parents[2] / "scripts" / "check_build_bytes.py"


@pytest.fixture(scope="module")
def guard():
    spec = importlib.util.spec_from_file_location("check_build_bytes_script", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _manifest(guard, name: str) -> dict:
    """The manifest ``name``; skips on another environment, fails when its recipe is not this
    suite's (then it is stale: re-record it)."""
    manifest = guard.load_manifest(name)
    hint = guard.RECORD_HINT.format(name=name)
    differ = guard.environment_difference(manifest["environment"], guard.environment())
    if differ:
        pytest.skip(f"manifests/{name}.json was recorded in another environment ({'; '.join(differ)}): its "
                    f"hashes do not apply here; to check the bytes on this machine record them first on the code "
                    f"to compare against ({hint})")
    recipe = (guard.small_recipe({"backward_flow": True}) if name == "small_backward_flow" else guard.small_recipe())
    assert manifest["recipe"] == recipe, f"manifests/{name}.json is stale (recipe {manifest['recipe']}): {hint}"
    return manifest


def _assert_recorded(guard, manifest: dict, out: Path, what: str) -> None:
    here = guard.tree_hashes(out)
    diff = guard.tree_difference(manifest["files"], here)
    assert not any(diff.values()), (f"{what}: the files differ from manifests/{manifest['name']}.json "
                                    f"(first ones named):\n{guard.describe_difference(diff)}")


def test_manifests_are_complete_and_exclude_nothing(guard):
    """Each small manifest lists every file of the 2-sample layout, markers and dataset.json
    included, and excludes none."""
    for name in ("small", "small_backward_flow"):
        manifest = guard.load_manifest(name)
        files = manifest["files"]
        assert manifest["excluded"] == {} and guard.EXCLUDED == {}
        assert {".done/00000.json", ".done/00001.json", "dataset.json"} <= set(files)
        assert all(len(h) == 64 for h in files.values())
        # Recorded in this suite's JAX configuration (tests/conftest.py), or the tests below would always skip.
        assert manifest["environment"]["jax_enable_x64"] is True
        assert manifest["environment"]["jax_numpy_dtype_promotion"] == "strict"
    backward = guard.load_manifest("small_backward_flow")["files"]
    assert any(k.startswith("optical_flow_backward/") for k in backward)
    assert not any(k.startswith("optical_flow_backward/") for k in guard.load_manifest("small")["files"])


def test_serial_build_writes_the_recorded_bytes(guard, reference_build):
    manifest = _manifest(guard, "small")
    _assert_recorded(guard, manifest, reference_build[0], "serial build")


def test_dask_build_writes_the_recorded_bytes(guard, small_capture, tmp_path):
    pytest.importorskip("distributed")
    manifest = _manifest(guard, "small")
    # Thread workers, as tests/dataset/test_build.py's dask test: process workers would each compile afresh.
    report = build_dataset(small_capture, tmp_path / "dataset", workers=2, processes=False)
    assert report.ok, report.summary()
    _assert_recorded(guard, manifest, tmp_path / "dataset", "dask build (workers=2, threads)")


def test_backward_flow_build_writes_the_recorded_bytes(guard, small_capture, tmp_path):
    manifest = _manifest(guard, "small_backward_flow")
    report = build_dataset(small_capture, tmp_path / "dataset", options=BuildOptions(backward_flow=True))
    assert report.ok, report.summary()
    _assert_recorded(guard, manifest, tmp_path / "dataset", "backward-flow build")


def test_a_changed_file_is_named(guard, tmp_path):
    """The comparison names the changed, missing and extra files (what a failure shows)."""
    (tmp_path / "a").write_bytes(b"a")
    (tmp_path / "b").write_bytes(b"b")
    recorded = {"a": guard.tree_hashes(tmp_path)["a"], "b": "0" * 64, "c": "0" * 64}
    text = guard.describe_difference(guard.tree_difference(recorded, guard.tree_hashes(tmp_path)))
    assert text == "1 changed: b\n1 missing: c"


def test_environment_names_the_simd_level_and_versions(guard):
    env = guard.environment()
    assert {"python", "jax", "jaxlib", "numpy", "OpenImageIO", "backend", "jax_enable_x64", "jax_numpy_dtype_promotion",
            "XLA_FLAGS", "machine", "simd"} <= set(env)
    assert env["jax_enable_x64"] is True  # tests/conftest.py
    assert env["simd"] is None or set(env["simd"]) <= set(guard.SIMD_FLAGS)
    recorded = dict(env, simd=["avx2"])
    assert guard.environment_difference(recorded, env) == ([] if env["simd"] == ["avx2"] else
                                                          [f"simd: recorded ['avx2'], here {env['simd']!r}"])
