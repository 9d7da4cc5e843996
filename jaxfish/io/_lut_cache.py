"""LUTs on disk: save / load `Lut`s as ``.npz`` and cache them keyed by the calibration (edge I/O).

The cache key is a SHA-256 of everything the LUT depends on: the source and target cameras
(model type, static fields such as image sizes and cube faces, every parameter's exact bytes), the
rotation, the supersampling, the dtype and this file format's version. Any change of calibration
therefore builds (and stores) a new LUT; nothing stale is ever returned.
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from .._errors import JaxfishError
from ..cameras import AbstractCamera
from ..reprojection import Lut, compiled_build_lut
from ._atomic import atomic_path

LUT_FORMAT_VERSION = 1
"""Version of the ``.npz`` LUT layout, part of every cache key; bumped when the layout or the LUT
semantics change, so outdated cache files are rebuilt."""
_ARRAYS = ("face", "uv", "valid", "z_to_range", "tap_index", "tap_frac", "nearest_index", "ring_index", "ring_frac", "ring_valid")
_OPTIONAL = ("border_pixel", "border_fits")
_STATIC = ("num_faces", "source_width", "source_height", "pad", "supersample")


def _hash_tree(h, tree) -> None:
    leaves, treedef = jax.tree_util.tree_flatten(tree)
    h.update(str(treedef).encode())
    for leaf in leaves:
        a = np.asarray(leaf)
        h.update(f"{a.dtype.str}{a.shape}".encode())
        h.update(np.ascontiguousarray(a).tobytes())


def lut_cache_key(
    source: AbstractCamera,
    target: AbstractCamera,
    *,
    target_to_source=None,
    supersample: int = 1,
    dtype=jnp.float32,
) -> str:
    """Hex SHA-256 identifying the LUT `build_lut` would return for these arguments."""
    h = hashlib.sha256()
    h.update(f"jaxfish-lut-v{LUT_FORMAT_VERSION}|{type(source).__name__}|{type(target).__name__}".encode())
    _hash_tree(h, source)
    _hash_tree(h, target)
    r = None if target_to_source is None else np.asarray(target_to_source, np.float64)
    h.update(b"none" if r is None else r.tobytes())
    h.update(f"|{int(supersample)}|{np.dtype(jnp.dtype(dtype)).str}".encode())
    return h.hexdigest()


def save_lut(lut: Lut, path: str | os.PathLike) -> Path:
    """Write a (possibly camera-batched) LUT to ``path`` (``.npz``), atomically."""
    path = Path(path)
    arrays = {name: np.asarray(getattr(lut, name)) for name in _ARRAYS}
    arrays.update({name: np.asarray(getattr(lut, name)) for name in _OPTIONAL if getattr(lut, name) is not None})
    meta = {name: int(getattr(lut, name)) for name in _STATIC}
    meta["format"] = LUT_FORMAT_VERSION
    arrays["meta"] = np.frombuffer(json.dumps(meta).encode(), dtype=np.uint8)
    with atomic_path(path, suffix=".npz") as tmp:
        with open(tmp, "wb") as f:
            np.savez(f, **arrays)
    return path


def load_lut(path: str | os.PathLike) -> Lut:
    """Read a LUT written by `save_lut`; a missing, corrupt or outdated file raises `JaxfishError`."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: LUT file not found")
    try:
        with np.load(path) as data:
            meta = json.loads(bytes(data["meta"]).decode())
            arrays = {name: jnp.asarray(data[name]) for name in _ARRAYS}
            arrays.update({name: jnp.asarray(data[name]) for name in _OPTIONAL if name in data.files})
    except (OSError, ValueError, KeyError) as e:
        raise JaxfishError(f"{path}: not a readable jaxfish LUT ({e})") from e
    if meta.get("format") != LUT_FORMAT_VERSION:
        raise JaxfishError(f"{path}: field 'format': LUT format {meta.get('format')} != {LUT_FORMAT_VERSION}")
    return Lut(**arrays, **{name: int(meta[name]) for name in _STATIC})


def cached_lut(
    source: AbstractCamera,
    target: AbstractCamera,
    *,
    cache_dir: str | os.PathLike,
    target_to_source=None,
    supersample: int = 1,
    dtype=jnp.float32,
) -> Lut:
    """`build_lut` through a disk cache: ``cache_dir/lut-<key>.npz`` (see `lut_cache_key`).

    A cache file that cannot be read is rebuilt and overwritten.
    """
    key = lut_cache_key(source, target, target_to_source=target_to_source, supersample=supersample, dtype=dtype)
    path = Path(cache_dir) / f"lut-{key[:32]}.npz"
    if path.is_file():
        try:
            return load_lut(path)
        except JaxfishError:
            pass
    lut = compiled_build_lut(
        source, target, target_to_source=target_to_source, supersample=supersample, dtype=dtype
    )
    save_lut(lut, path)
    return lut
