"""Test helpers: run one body eager, jitted and vmapped; finite differences; wait for a subprocess's
events without a deadline."""

from __future__ import annotations

import os
import select
import subprocess
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

TEST_JAX_ENV = {"JAX_ENABLE_X64": "1", "JAX_NUMPY_DTYPE_PROMOTION": "strict"}
"""tests/conftest.py's JAX settings as environment variables, for the processes a test starts (a
CLI subprocess, dask workers): the same programs as the test process, so that they load its
compiled programs from the run's compile cache."""


def three_ways(fn, *args):
    """``fn(*args)`` eager, under ``jax.jit``, and ``jax.vmap`` over a leading axis of size 1 (then
    squeezed): returns the three results (pytrees of numpy arrays). The batched program is
    compiled whole (``jax.jit(jax.vmap(fn))``): under ``vmap`` the values are tracers either way,
    and op-by-op dispatch of a batched program would only compile each operation on its own."""
    eager = fn(*args)
    jitted = jax.jit(fn)(*args)
    batched = jax.jit(jax.vmap(fn))(*[jax.tree_util.tree_map(lambda x: jnp.asarray(x)[None], a) for a in args])
    batched = jax.tree_util.tree_map(lambda x: x[0], batched)
    to_np = lambda t: jax.tree_util.tree_map(np.asarray, t)  # noqa: E731
    return to_np(eager), to_np(jitted), to_np(batched)


def central_difference_jacobian(fn, x: np.ndarray, eps: float = 1e-6) -> np.ndarray:
    """Jacobian of ``fn: (n,) -> (m,)`` by central differences in float64."""
    x = np.asarray(x, dtype=np.float64)
    cols = []
    for i in range(x.size):
        dx = np.zeros_like(x)
        dx.flat[i] = eps
        cols.append((np.asarray(fn(x + dx)) - np.asarray(fn(x - dx))).ravel() / (2 * eps))
    return np.stack(cols, axis=-1)


# ------------------------------------------------------------------ waiting on subprocesses
HANG_GUARD_S = 1800.0
"""Seconds a test waits on a subprocess before it gives up: a guard against a hang only, never a
speed limit. Tests wait for events (a line on a pipe, the process's exit); on a loaded machine
those may take minutes where an idle one takes seconds, and that must not fail a test."""


def _hung(what: str) -> str:
    return (f"{what} for {HANG_GUARD_S:.0f} s, so it hangs (tests.helpers.HANG_GUARD_S guards against a hang "
            "only; a slow or loaded machine never gets near it)")


def run_python(args, **kwargs) -> subprocess.CompletedProcess:
    """``subprocess.run([sys.executable, *args], capture_output=True, text=True, **kwargs)``: waits
    for the interpreter to exit, failing the test only when it hangs (`HANG_GUARD_S`)."""
    try:
        return subprocess.run([sys.executable, *map(str, args)], capture_output=True, text=True,
                              timeout=HANG_GUARD_S, **kwargs)
    except subprocess.TimeoutExpired:
        pytest.fail(_hung(f"python {' '.join(map(str, args))[:200]}: no exit"))


def wait_for_line(proc: subprocess.Popen, prefix: str | tuple[str, ...]) -> str | None:
    """Read ``proc``'s stdout (a pipe) until a line that starts with ``prefix`` (or one of them);
    return that line (without its newline), or None when the pipe closes first (the process
    ended). Waits as long as the process keeps the pipe open, failing the test only when it hangs
    (no line for `HANG_GUARD_S`)."""
    fd, buf = proc.stdout.fileno(), b""
    while True:
        while b"\n" in buf:
            line, buf = buf.split(b"\n", 1)
            text = line.decode(errors="replace")
            if text.startswith(prefix):
                return text
        ready, _, _ = select.select([fd], [], [], HANG_GUARD_S)
        if not ready:
            pytest.fail(_hung(f"process {proc.pid}: no line on its stdout (waiting for one starting {prefix!r})"))
        chunk = os.read(fd, 65536)
        if not chunk:
            return None
        buf += chunk


def tree_bytes(root: Path) -> dict[str, bytes]:
    """``{relative path: bytes}`` of every file under ``root``."""
    return {p.relative_to(root).as_posix(): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def assert_same_tree(a: Path, b: Path) -> None:
    """The folders ``a`` and ``b`` hold the same files with the same bytes."""
    ta, tb = tree_bytes(a), tree_bytes(b)
    assert sorted(ta) == sorted(tb)
    differ = [k for k in ta if ta[k] != tb[k]]
    assert not differ, f"files differ: {describe_differences(a, b, differ)}"


def describe_differences(a: Path, b: Path, names: list[str], limit: int = 10) -> list[str]:
    """What differs between the files ``names`` (relative paths) of ``a`` and ``b``: for images
    and arrays that decode to the same shape, how many elements differ and a few of them (the
    failure message of a byte comparison; a bare file name says too little to find a cause)."""
    from jaxfish.io import read_image

    out = []
    for name in names[:limit]:
        pa, pb = a / name, b / name
        try:
            if name.endswith(".npy"):
                xa, xb = np.load(pa, allow_pickle=False), np.load(pb, allow_pickle=False)
            elif name.endswith((".png", ".exr")):
                xa, xb = np.asarray(read_image(pa)), np.asarray(read_image(pb))
            else:
                out.append(f"{name}: {pa.stat().st_size} / {pb.stat().st_size} bytes")
                continue
        except Exception as e:  # noqa: BLE001 - a description, never the failure itself
            out.append(f"{name}: not decoded ({type(e).__name__}: {e})")
            continue
        if xa.shape != xb.shape or xa.dtype != xb.dtype:
            out.append(f"{name}: {xa.dtype}{xa.shape} / {xb.dtype}{xb.shape}")
            continue
        diff = np.argwhere(xa != xb) if xa.dtype.names is None else np.argwhere(xa.view(np.uint8) != xb.view(np.uint8))
        where = [tuple(int(i) for i in d) for d in diff[:3]]
        out.append(f"{name}: {len(diff)} of {xa.size} elements differ, first at {where}: "
                   f"{[xa[w].tolist() for w in where]} / {[xb[w].tolist() for w in where]}"
                   if xa.dtype.names is None else f"{name}: {len(diff)} bytes differ")
    return out + ([f"... and {len(names) - limit} more"] if len(names) > limit else [])
