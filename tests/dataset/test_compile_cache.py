"""The compile cache (`jaxfish.dataset.use_compile_cache`, ``BuildOptions.compile_cache``,
``jaxfish build --compile-cache DIR``): a process loads what another process compiled into the
folder, the builder's bytes with the cache (cold and warm) are the recorded ones, entries are
written atomically (concurrent writers and readers never see part of an entry), a corrupt entry
is removed and its program compiled again, and an unusable folder warns and builds uncached."""

from __future__ import annotations

import subprocess
import sys
import threading
from pathlib import Path

import jax
import pytest
from jax import monitoring

from jaxfish.dataset import (
    COMPILE_CACHE_ENV,
    BuildOptions,
    CompileCacheWarning,
    DatasetError,
    build_dataset,
    compile_cache_folder,
    default_compile_cache,
    use_compile_cache,
)
from tests.helpers import TEST_JAX_ENV

from .test_build_bytes import _assert_recorded, guard  # noqa: F401 - the guard fixture

ROOT = Path(__file__).resolve().parents[2]

# One tiny program, compiled in a fresh process with the cache folder of $JAXFISH_COMPILE_CACHE;
# prints how many cache hits JAX recorded and the cache folder in use.
_CHILD = """
import jax, jax.numpy as jnp
from jax import monitoring
from jaxfish.dataset import use_compile_cache
hits = []
monitoring.register_event_listener(lambda name, **kw: hits.append(name) if name.endswith("/cache_hits") else None)
folder = use_compile_cache()
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0)  # the tiny program compiles fast
print(float(jax.jit(lambda x: jnp.sin(x) * 3.0 + jnp.cos(x))(jnp.arange(7.0)).sum()))
print(len(hits), folder)
"""


def _child(folder: Path) -> tuple[int, str, str]:
    env = {**__import__("os").environ, COMPILE_CACHE_ENV: str(folder), "JAX_PLATFORMS": "cpu"}
    done = subprocess.run([sys.executable, "-c", _CHILD], cwd=ROOT, env=env, capture_output=True, text=True, check=True)
    value, last = done.stdout.strip().splitlines()[-2:]
    hits, where = last.split(" ", 1)
    return int(hits), where, value


@pytest.fixture
def cache_off():
    """Give this process back the test run's cache folder after the test (the test's folder is
    deleted). The programs in memory stay: they are the same programs whichever folder holds them."""
    yield
    use_compile_cache(True)


def test_a_second_process_loads_the_program_the_first_one_compiled(tmp_path):
    folder = tmp_path / "xla"
    hits, where, first = _child(folder)
    entries = sorted(p.name for p in folder.glob("*-cache"))
    assert hits == 0 and Path(where) == folder.resolve() and entries  # compiled and written
    hits, _, second = _child(folder)
    assert hits >= 1 and second == first  # loaded, not compiled: no new entry, the same result
    assert sorted(p.name for p in folder.glob("*-cache")) == entries
    assert not [p for p in folder.iterdir() if p.name.endswith(".tmp")]


def test_the_setting_names_the_folder(tmp_path, monkeypatch):
    monkeypatch.setenv(COMPILE_CACHE_ENV, str(tmp_path / "mine"))
    assert default_compile_cache() == tmp_path / "mine"
    assert compile_cache_folder(True) == tmp_path / "mine" and compile_cache_folder(False) is None
    assert compile_cache_folder(tmp_path / "x") == tmp_path / "x"
    monkeypatch.setenv(COMPILE_CACHE_ENV, "")
    assert default_compile_cache() is None
    monkeypatch.delenv(COMPILE_CACHE_ENV)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert default_compile_cache() == tmp_path / "xdg" / "jaxfish" / "xla"
    assert BuildOptions(compile_cache=tmp_path).to_dict() == BuildOptions().to_dict()  # bytes: not shaped by it
    with pytest.raises(DatasetError, match="compile_cache"):
        BuildOptions(compile_cache=3)


def test_builds_with_a_cold_and_a_warm_cache_write_the_uncached_bytes(guard, small_capture, reference_build,  # noqa: F811
                                                                        tmp_path, cache_off):
    from jaxfish.dataset._build import clear_worker_cache

    folder = tmp_path / "xla"
    jax.clear_caches()  # compile now, into the folder
    cold = build_dataset(small_capture, tmp_path / "cold", options=BuildOptions(compile_cache=folder))
    assert cold.ok, cold.summary()
    written = sorted(folder.glob("*-cache"))
    assert written, "the build's programs were not written to the cache"
    jax.clear_caches()  # the in-memory programs are gone: the warm build loads them from the folder
    clear_worker_cache()
    hits: list[str] = []

    def count(name: str, **_kw) -> None:
        if name.endswith("/cache_hits"):
            hits.append(name)

    monitoring.register_event_listener(count)
    try:
        warm = build_dataset(small_capture, tmp_path / "warm", options=BuildOptions(compile_cache=folder))
    finally:
        monitoring.unregister_event_listener(count)
    assert warm.ok, warm.summary()
    assert len(hits) >= len(written)  # as many programs loaded as the cold build wrote
    # The bytes of a build without the cache (test_build_bytes.py checks those against the manifest).
    uncached = {"files": guard.tree_hashes(reference_build[0]), "name": "the uncached build"}
    _assert_recorded(guard, uncached, tmp_path / "cold", "build with a cold compile cache")
    _assert_recorded(guard, uncached, tmp_path / "warm", "build with a warm compile cache")


def _twice_plus_one():
    """A new function object each call, the same program (named ``jit_twice_plus_one``): the next
    call compiles it, or loads it from the compile cache, instead of finding it in memory (where
    `jax.clear_caches` would also drop every other test's programs)."""

    def twice_plus_one(x):
        return x * 2.0 + 1.0

    return jax.jit(twice_plus_one)


def test_a_corrupt_entry_is_removed_and_compiled_again(tmp_path, cache_off):
    import numpy as np

    folder = tmp_path / "xla"
    use_compile_cache(folder)
    x = jax.device_put(np.arange(5.0))
    expected = np.asarray(_twice_plus_one()(x))
    (entry,) = folder.glob("jit_twice_plus_one-*-cache")
    whole = entry.read_bytes()
    entry.write_bytes(whole[: len(whole) // 2])  # a writer killed half-way (by another writer than ours)
    with pytest.warns(CompileCacheWarning, match="corrupt compile-cache entry removed"):
        again = np.asarray(_twice_plus_one()(x))
    assert (again == expected).all()
    from jax._src import compilation_cache as internal

    internal.decompress_executable(entry.read_bytes())  # compiled again and written whole
    hits: list[str] = []

    def count(name: str, **_kw) -> None:
        if name.endswith("/cache_hits"):
            hits.append(name)

    monitoring.register_event_listener(count)
    try:  # loaded, without a warning (warnings are errors here)
        assert (np.asarray(_twice_plus_one()(x)) == expected).all()
    finally:
        monitoring.unregister_event_listener(count)
    assert hits


def test_concurrent_writers_and_readers_see_no_entry_or_the_whole_entry(tmp_path, cache_off):
    from jax._src import compilation_cache as internal

    use_compile_cache(tmp_path)
    cache = internal._cache
    value = internal.compress_executable(bytes(range(256)) * 4000)
    seen: list[bytes | None] = []
    start = threading.Barrier(8)

    def writer() -> None:
        start.wait()
        for _ in range(20):
            cache.put("k" * 40, value)

    def reader() -> None:
        start.wait()
        for _ in range(200):
            seen.append(cache.get("k" * 40))

    threads = [threading.Thread(target=writer) for _ in range(4)] + [threading.Thread(target=reader) for _ in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert all(v is None or v == value for v in seen)
    assert cache.get("k" * 40) == value
    assert [p.name for p in tmp_path.iterdir() if not p.name.endswith("-cache")] == []  # no temporary file left


def test_an_unusable_folder_warns_and_the_build_goes_on(small_capture, reference_build, tmp_path, cache_off):
    (tmp_path / "file").write_text("not a folder")
    with pytest.warns(CompileCacheWarning, match="cannot be used as the compile cache"):
        report = build_dataset(small_capture, tmp_path / "out", options=BuildOptions(compile_cache=tmp_path / "file" / "xla"))
    assert report.ok, report.summary()
    assert jax.config.jax_compilation_cache_dir is None
    assert guard is not None
    ref = {p.relative_to(reference_build[0]) for p in reference_build[0].rglob("*") if p.is_file()}
    assert {p.relative_to(tmp_path / "out") for p in (tmp_path / "out").rglob("*") if p.is_file()} == ref


def test_the_driver_of_local_process_workers_builds_the_first_samples_into_the_cache(small_capture, reference_build,
                                                                                      tmp_path, monkeypatch):
    """With a compile cache, the driver builds the first `WARM_BATCHES` samples itself (compiling
    into the cache) and the process workers build the rest. The cache is the test run's: this
    process has compiled the small capture's programs into it already (``reference_build``), so
    that the workers load them (a cold folder is `test_builds_with_a_cold_and_a_warm_cache...`)."""
    pytest.importorskip("distributed")
    from jaxfish.dataset import _build

    monkeypatch.setattr(_build, "WARM_BATCHES", 1)  # the small capture has two frames
    # The workers run this process's JAX settings (conftest.py), so that they load its programs.
    for name, value in TEST_JAX_ENV.items():
        monkeypatch.setenv(name, value)
    built_here: list[int] = []
    write = _build._write_sample

    def written_here(source, out, truth, options, record):  # this process's only: workers import the module afresh
        built_here.append(truth.index)
        return write(source, out, truth, options, record)

    monkeypatch.setattr(_build, "_write_sample", written_here)
    folder = use_compile_cache(True)
    report = build_dataset(small_capture, tmp_path / "out", workers=2, processes=True,
                           options=BuildOptions(compile_cache=True))
    assert report.ok, report.summary()
    assert report.built == ["00000", "00001"] and built_here == [0]  # frame 1 on a worker
    assert folder is not None and list(folder.glob("*-cache"))
