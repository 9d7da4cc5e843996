"""Stopping a build: SIGINT or SIGTERM stops it cleanly (exit status 130, one ``interrupted:``
line, no traceback, the samples it cut off removed, complete samples kept, resume to the same
bytes); local dask workers end with the building process, even after ``kill -9`` of it.

Every wait here waits for an event (a file appears, a process exits); the time limits only guard
against a hang. The subprocess builds are gated: a dask worker preload makes the worker that
builds frame `GATED` (the first frame a worker builds: with the test run's compile cache the
driver builds the frames before it itself, `WARM_BATCHES`, and the workers load the programs it
compiled) stop for good in the middle of that sample (after its camera files, before its vehicle and lidar files)
while holding the GIL, so the build cannot end before the test stops it, a sample is cut off at
that moment, and only a kernel-level parent-death signal ends that worker."""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from jaxfish.dataset import BuildInterrupted, _build, build_dataset, is_complete, sample_id
from tests.helpers import TEST_JAX_ENV, assert_same_tree

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="parent-death signal: Linux only")

GATED = _build.WARM_BATCHES
"""The frame a gated worker stops in: the first one the driver leaves to its workers."""
DRIVER_SAMPLES = [sample_id(f) for f in range(GATED)]
CUT = sample_id(GATED)

HANG_GUARD_S = 1800.0
"""Only guards against a hang: a gated build compiles for minutes on a loaded 2-core machine."""


def _wait_for(condition, what: str, proc: subprocess.Popen | None = None, log: Path | None = None) -> None:
    """Wait until ``condition()``; fail when ``proc`` has exited first or after `HANG_GUARD_S`."""
    end = time.monotonic() + HANG_GUARD_S
    while not condition():
        if proc is not None and proc.poll() is not None:
            pytest.fail(f"exited ({proc.returncode}) before {what}: {log.read_text()[-3000:] if log else ''}")
        if time.monotonic() > end:
            pytest.fail(f"hang guard: no {what} after {HANG_GUARD_S} s")
        time.sleep(0.02)


def _ended(pid: int) -> bool:
    """Gone or a zombie (a zombie runs no code: it writes nothing more)."""
    import psutil

    try:
        return psutil.Process(pid).status() == psutil.STATUS_ZOMBIE
    except psutil.NoSuchProcess:
        return True


def _listing(root: Path) -> dict[str, tuple[int, int]]:
    return {p.relative_to(root).as_posix(): (p.stat().st_size, p.stat().st_mtime_ns)
            for p in sorted(root.rglob("*")) if p.is_file()}


def _files_of(out: Path, sample: str) -> list[str]:
    return sorted(p.relative_to(out).as_posix() for p in out.rglob(f"*{sample}*"))


def _half_written(out: Path) -> list[str]:
    return sorted(p.relative_to(out).as_posix() for p in out.rglob("*") if ".part" in p.name or p.name.startswith(".tmp"))


# ----------------------------------------------------------------------------- die with the parent
_MIDDLE = """
import subprocess, sys
child = subprocess.Popen([sys.executable, "-c", sys.argv[1], str(__import__("os").getpid())], stdout=sys.stdout)
child.wait()
"""

_CHILD = """
import ctypes, os, sys
from jaxfish.dataset._runtime import die_with_parent
die_with_parent(int(sys.argv[1]))
print(os.getpid(), flush=True)
pause = ctypes.PyDLL(None).pause  # a C call that keeps the GIL: no Python thread of this process runs again
while True:
    pause()
"""


def test_a_process_ends_with_its_parent_even_while_a_c_call_holds_the_gil(tmp_path):
    """`die_with_parent`: kill -9 of the parent ends the child, which is blocked in a C call that
    holds the GIL (no watchdog thread could run): the kernel's parent-death signal does it."""
    import psutil

    middle = subprocess.Popen([sys.executable, "-c", _MIDDLE, _CHILD], stdout=subprocess.PIPE, text=True)
    child = None
    try:
        child = int(middle.stdout.readline())  # printed once die_with_parent has returned
        assert psutil.Process(child).ppid() == middle.pid
        middle.kill()
        middle.wait()
        _wait_for(lambda: _ended(child), "end of the orphaned child")
    finally:
        middle.kill()
        middle.wait()
        middle.stdout.close()
        if child is not None and not _ended(child):
            os.kill(child, signal.SIGKILL)


def _worker_stop_settings() -> tuple[int, bool, bool]:
    """(parent-death signal, SIGINT ignored, SIGTERM ignored) of the calling process."""
    import ctypes

    sig = ctypes.c_int(0)
    ctypes.CDLL(None).prctl(2, ctypes.byref(sig), 0, 0, 0)  # PR_GET_PDEATHSIG
    return (sig.value, signal.getsignal(signal.SIGINT) is signal.SIG_IGN,
            signal.getsignal(signal.SIGTERM) is signal.SIG_IGN)


def test_local_cluster_workers_die_with_this_process_and_leave_signals_to_it(monkeypatch):
    """`local_cluster`'s process workers: SIGKILL when this process ends, SIGINT and SIGTERM
    ignored (a Ctrl-C reaching the process group stops them through the build), also when this
    process inherited another build's process id in its environment; thread workers leave this
    process's settings alone."""
    from distributed import Client

    from jaxfish.dataset import local_cluster
    from jaxfish.dataset._runtime import BUILD_PID_ENV

    monkeypatch.setenv(BUILD_PID_ENV, "1")  # e.g. started by a process that ran a local cluster
    before = _worker_stop_settings()
    with local_cluster(1) as cluster, Client(cluster) as client:
        settings = list(client.run(_worker_stop_settings).values())
        assert list(client.run(lambda: os.environ.get(BUILD_PID_ENV)).values()) == [str(os.getpid())]
    assert settings == [(signal.SIGKILL, True, True)]
    assert os.environ[BUILD_PID_ENV] == "1"  # this process's environment is left alone
    with local_cluster(1, processes=False) as cluster, Client(cluster) as client:
        client.submit(sum, [1]).result()
    assert _worker_stop_settings() == before


# --------------------------------------------------------------------------- gated subprocess builds
_GATE = '''
"""Dask worker preload of tests/dataset/test_stop.py: frame WARM_BATCHES stops for good half-way."""
import ctypes, os, pathlib
from jaxfish.dataset import _build

GATE = pathlib.Path(os.environ["JAXFISH_TEST_GATE"])
(GATE / f"worker-{os.getpid()}").touch()
_original = getattr(_build, "_ungated_sample_extras", _build._sample_extras)  # dask may import this twice
_build._ungated_sample_extras = _original


def _gated(reader, frame, out, sid):
    if frame == _build.WARM_BATCHES:  # the first frame the driver leaves to its workers
        (GATE / "reached").touch()
        pause = ctypes.PyDLL(None).pause  # holds the GIL: dask's own parent watch cannot run
        while True:
            pause()
    return _original(reader, frame, out, sid)


_build._sample_extras = _gated
'''

# Python's own Ctrl-C handler, whatever the test run inherited: a shell runs a background job with
# SIGINT ignored, and the build keeps an ignored SIGINT ignored.
_CLI = ("import signal, sys; signal.signal(signal.SIGINT, signal.default_int_handler); "
        "from jaxfish.cli import main; sys.argv[0] = 'jaxfish'; main()")


@pytest.fixture(scope="module")
def dask_capture(small_capture, tmp_path_factory):
    """The small capture with frames up to ``GATED + 1`` (copies of frames 0 and 1: the driver's,
    the gated one and one more), and its serial reference build."""
    root = tmp_path_factory.mktemp("stop_capture")
    cap = root / "capture"
    shutil.copytree(small_capture, cap)
    frames = list(range(GATED + 2))
    for dst in frames[2:]:
        shutil.copytree(cap / "frames" / f"{dst % 2:06d}", cap / "frames" / f"{dst:06d}")
    meta = json.loads((cap / "capture.json").read_text())
    meta["frames"] = frames
    (cap / "capture.json").write_text(json.dumps(meta))
    reference = root / "reference"
    report = build_dataset(cap, reference)
    assert report.ok, report.summary()
    return cap, reference


def _start_gated_build(cap: Path, tmp: Path) -> tuple[subprocess.Popen, Path, Path, Path]:
    """``jaxfish build CAP OUT --workers 2`` in its own process group, with the gate preloaded in
    its workers; returns once the driver's samples are complete and frame `GATED`'s worker is
    stopped half-way."""
    gate, out, log = tmp / "gate", tmp / "dataset", tmp / "stderr.txt"
    gate.mkdir()
    (tmp / "gate.py").write_text(_GATE)
    # The test run's compile cache (inherited): the driver and its workers load the programs this
    # process compiled for the reference build (the same JAX settings).
    env = dict(os.environ, **TEST_JAX_ENV, JAXFISH_TEST_GATE=str(gate),
               DASK_DISTRIBUTED__WORKER__PRELOAD=json.dumps([str(tmp / "gate.py")]))
    with open(log, "wb") as err:
        proc = subprocess.Popen([sys.executable, "-c", _CLI, "build", str(cap), str(out), "--workers", "2", "--processes"],
                                stdout=subprocess.DEVNULL, stderr=err, env=env, start_new_session=True)
    _wait_for(lambda: (gate / "reached").exists() and all(is_complete(out, s) for s in DRIVER_SAMPLES),
              "gate reached", proc, log)
    assert _files_of(out, CUT), "the gated frame stops after its camera files"
    return proc, gate, out, log


def _worker_pids(gate: Path) -> list[int]:
    pids = [int(p.name.split("-")[1]) for p in gate.glob("worker-*")]
    assert len(pids) == 2, pids
    return pids


def _stop_workers(pids: list[int]) -> None:
    for pid in pids:
        if not _ended(pid):
            os.kill(pid, signal.SIGKILL)


def test_ctrl_c_stops_a_dask_build_cleanly_and_it_resumes_to_the_same_bytes(dask_capture, tmp_path):
    """Ctrl-C (SIGINT to the whole process group, as a terminal sends it) while a worker is stopped
    half-way through sample `CUT`: exit 130, one ``interrupted:`` line, no traceback; the workers
    have ended when the build exits, nothing changes afterwards, sample `CUT`'s files are gone,
    the driver's samples stay; a resume gives the reference bytes."""
    cap, reference = dask_capture
    proc, gate, out, log = _start_gated_build(cap, tmp_path)
    pids = _worker_pids(gate)
    try:
        os.killpg(proc.pid, signal.SIGINT)
        _wait_for(lambda: proc.poll() is not None, "exit of the build")
        at_exit = _listing(out)
        assert all(_ended(pid) for pid in pids), "the build exited before its workers"
    finally:
        proc.kill()
        _stop_workers(pids)
    stderr = log.read_text()
    assert proc.returncode == 130, stderr[-3000:]
    assert "Traceback" not in stderr and "CancelledError" not in stderr, stderr[-3000:]
    assert not re.search(r" - (WARNING|ERROR|CRITICAL) - ", stderr), stderr[-3000:]  # no dask log line
    lines = [ln for ln in stderr.splitlines() if ln.startswith("interrupted:")]
    assert len(lines) == 1 and "resume" in lines[0], stderr[-3000:]
    assert _listing(out) == at_exit
    assert all(is_complete(out, s) for s in DRIVER_SAMPLES)
    assert not _files_of(out, CUT), "the cut-off sample is removed"
    assert not _half_written(out)
    samples = [sample_id(f) for f in range(GATED + 2)]
    complete = [s for s in samples if is_complete(out, s)]
    assert f"{len(complete)} of {len(samples)} sample(s) complete" in lines[0]

    report = build_dataset(cap, out)
    assert report.ok and set(report.skipped) == set(complete) and CUT in report.built
    assert_same_tree(reference, out)


def test_kill_9_of_a_dask_build_ends_its_workers_and_it_resumes_to_the_same_bytes(dask_capture, tmp_path):
    """kill -9 of the building process while a worker is stopped half-way through sample `CUT`
    holding the GIL (dask's own watch of the parent, a thread, cannot run there): both worker
    processes end (the kernel kills them) and a resume gives the reference bytes. (No listing is
    compared at the parent's exit: a worker killed inside a write system call completes that call.)"""
    cap, reference = dask_capture
    proc, gate, out, log = _start_gated_build(cap, tmp_path)
    pids = _worker_pids(gate)
    try:
        proc.kill()
        proc.wait()
        _wait_for(lambda: all(_ended(pid) for pid in pids), "end of the workers")
    finally:
        _stop_workers(pids)
    assert all(is_complete(out, s) for s in DRIVER_SAMPLES) and not is_complete(out, CUT)
    report = build_dataset(cap, out)
    assert report.ok and CUT in report.built
    assert_same_tree(reference, out)


# ------------------------------------------------------------------------------- in-process builds
class _Unhandled(BaseException):
    """Raised by the test's own signal handler: the code under test did not handle the signal."""


@pytest.fixture
def guarded_signals():
    """SIGINT and SIGTERM raise `_Unhandled` unless the code under test installs its handlers."""
    def unhandled(signum, _frame):
        raise _Unhandled(signal.Signals(signum).name)

    previous = {s: signal.signal(s, unhandled) for s in (signal.SIGINT, signal.SIGTERM)}
    yield
    for s, h in previous.items():
        signal.signal(s, h)


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
def test_a_signal_stops_a_serial_cli_build_cleanly(small_capture, reference_build, tmp_path, monkeypatch, capsys,
                                                    guarded_signals, signum):
    """The signal arrives while sample 00001's files are being written (by the write threads):
    exit status 130, one ``interrupted: 1 of 2`` line, no traceback, sample 00001 removed, 00000
    complete; a resume gives the reference bytes."""
    from jaxfish.cli import main
    original = _build._sample_extras

    def gated(reader, frame, out, sid):
        if frame == 1:
            os.kill(os.getpid(), signum)  # handled in the main thread, which waits for this writer
        return original(reader, frame, out, sid)

    monkeypatch.setattr(_build, "_sample_extras", gated)
    out = tmp_path / "dataset"
    monkeypatch.setattr(sys, "argv", ["jaxfish", "build", str(small_capture), str(out)])
    with pytest.raises(SystemExit) as exit_:
        main()
    err = capsys.readouterr().err
    assert exit_.value.code == 130, err[-3000:]
    assert "Traceback" not in err and "interrupted: 1 of 2 sample(s) complete" in err, err[-3000:]
    assert signal.getsignal(signum).__name__ == "unhandled"  # the CLI restored the previous handler
    assert is_complete(out, "00000") and not _files_of(out, "00001") and not _half_written(out)
    monkeypatch.setattr(_build, "_sample_extras", original)
    report = build_dataset(small_capture, out)
    assert report.ok and report.skipped == ["00000"] and report.built == ["00001"]
    assert_same_tree(reference_build[0], out)


def test_ctrl_c_stops_thread_workers_before_their_next_file(small_capture, reference_build, tmp_path, monkeypatch,
                                                            guarded_signals):
    """Thread workers (``processes=False``) share the building process: on Ctrl-C the sample they
    are writing stops before its next file and is removed; `build_dataset` raises
    `BuildInterrupted` once they have stopped."""
    original = _build._sample_extras
    signal.signal(signal.SIGINT, signal.default_int_handler)  # what a Python program has by default

    def gated(reader, frame, out, sid):
        if frame == 1:
            os.kill(os.getpid(), signal.SIGINT)
            assert _build._STOP.wait(HANG_GUARD_S), "hang guard: the build did not stop its thread workers"
        return original(reader, frame, out, sid)

    monkeypatch.setattr(_build, "_sample_extras", gated)
    out = tmp_path / "dataset"
    with pytest.raises(BuildInterrupted) as stopped:
        build_dataset(small_capture, out, workers=2, processes=False)
    assert threading.main_thread().is_alive()
    assert not _build._STOP.is_set()
    assert not [t for t in threading.enumerate() if t.name.startswith("jaxfish-build-")]  # no worker still runs
    assert not _files_of(out, "00001") and not _half_written(out)
    assert stopped.value.complete == [s for s in ("00000",) if is_complete(out, s)]
    monkeypatch.setattr(_build, "_sample_extras", original)
    report = build_dataset(small_capture, out)
    assert report.ok
    assert_same_tree(reference_build[0], out)


_THREAD_GATE = '''
import os, pathlib, time
from jaxfish.dataset import _build

GATE = pathlib.Path(os.environ["JAXFISH_TEST_GATE"])
_original = _build._sample_extras


def _gated(reader, frame, out, sid):
    if frame == 1:  # the first frame the building thread leaves to its thread workers
        (GATE / "reached").touch()
        while not _build._STOP.is_set():  # until the signal has reached the building thread
            time.sleep(0.01)
    return _original(reader, frame, out, sid)


_build._sample_extras = _gated
'''


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_a_signal_stops_the_default_thread_workers_of_jaxfish_build(dask_capture, tmp_path, sig):
    """``jaxfish build --workers 2`` (thread workers, the default for two), signalled while a thread
    is half-way through frame 1: exit 130, one ``interrupted:`` line, no traceback; frame 1's files
    are gone, frame 0 (the building thread's) stays complete, nothing is half-written; a resume
    gives the reference bytes."""
    cap, reference = dask_capture
    gate, out, log = tmp_path / "gate", tmp_path / "dataset", tmp_path / "stderr.txt"
    gate.mkdir()
    (tmp_path / "thread_gate.py").write_text(_THREAD_GATE)
    script = f"import sys; sys.path.insert(0, {str(tmp_path)!r}); import thread_gate; " + _CLI
    env = dict(os.environ, **TEST_JAX_ENV, JAXFISH_TEST_GATE=str(gate))
    with open(log, "wb") as err:
        proc = subprocess.Popen([sys.executable, "-c", script, "build", str(cap), str(out), "--workers", "2"],
                                stdout=subprocess.DEVNULL, stderr=err, env=env, start_new_session=True)
    try:
        _wait_for(lambda: (gate / "reached").exists(), "gate reached", proc, log)
        assert _files_of(out, sample_id(1)), "the gated frame stops after its camera files"
        os.killpg(proc.pid, sig)
        _wait_for(lambda: proc.poll() is not None, "exit of the build")
    finally:
        proc.kill()
    stderr = log.read_text()
    assert proc.returncode == 130, stderr[-3000:]
    assert "Traceback" not in stderr, stderr[-3000:]
    lines = [ln for ln in stderr.splitlines() if ln.startswith("interrupted:")]
    assert len(lines) == 1 and "resume" in lines[0], stderr[-3000:]
    assert is_complete(out, sample_id(0)) and not _files_of(out, sample_id(1))
    assert not _half_written(out)
    report = build_dataset(cap, out)
    assert report.ok and sample_id(1) in report.built
    assert_same_tree(reference, out)
