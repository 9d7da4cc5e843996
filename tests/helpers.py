"""Test helpers: run one body eager, jitted and vmapped; finite differences."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np


def three_ways(fn, *args):
    """``fn(*args)`` eager, under ``jax.jit``, and ``jax.vmap`` over a leading axis of size 1 (then
    squeezed): returns the three results (pytrees of numpy arrays)."""
    eager = fn(*args)
    jitted = jax.jit(fn)(*args)
    batched = jax.vmap(fn)(*[jax.tree_util.tree_map(lambda x: jnp.asarray(x)[None], a) for a in args])
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
