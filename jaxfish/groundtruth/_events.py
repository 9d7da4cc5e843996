"""DVS events of the cube faces mapped to fisheye pixels through the inverse of the cube -> fisheye
LUT.

The rule (``docs/groundtruth.md``): the LUT sends every fisheye pixel's centre ray to one face
pixel (the nearest to where the ray hits the face, as `resample_nearest`). An event at face pixel
``q`` is emitted at **every** fisheye pixel whose centre ray lands on ``q``: a face pixel feeds
zero fisheye pixels (the faces oversample the fisheye almost everywhere, and face regions outside
the fisheye image feed none) or several (where the fisheye is denser than the face). The number
of fisheye events of a face event is the *fan-out* of its face pixel; timestamps and polarities
are copied, and the result is kept in time order (stable: ties keep face order, then fisheye
pixel order).
"""

from __future__ import annotations

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Int

from ..reprojection import Lut, centre_sample


class EventMap(eqx.Module):
    """The inverse LUT: for each face pixel (flat index ``(face * S + y) * S + x``), the fisheye
    pixels (flat ``v * W + u``) fed by it.

    - `targets` ``(F * S * S, M)`` int32: fisheye flat indices, -1 padding;
    - `fanout` ``(F * S * S,)`` int32: how many fisheye pixels each face pixel feeds;
    - static: `width`, `height` (fisheye), `face_size`, `num_faces`, `max_fanout` ``M``.
    """

    targets: Int[Array, "FSS M"]
    fanout: Int[Array, " FSS"]
    width: int = eqx.field(static=True)
    height: int = eqx.field(static=True)
    face_size: int = eqx.field(static=True)
    num_faces: int = eqx.field(static=True)
    max_fanout: int = eqx.field(static=True)


@functools.partial(jax.jit, static_argnums=1)
def _source_counts(lut: Lut, n_src: int) -> tuple[Int[Array, " N"], Int[Array, " FSS"]]:
    """Per fisheye pixel its face pixel at the LUT's centre sample (``n_src`` where it has none),
    and per face pixel how many fisheye pixels it feeds."""
    k = centre_sample(lut.supersample)
    key = jnp.where(lut.valid[..., k], lut.nearest_index[..., k], n_src).reshape(-1)
    return key, jnp.zeros(n_src + 1, jnp.int32).at[key].add(1)[:n_src]


@functools.partial(jax.jit, static_argnums=(2, 3))
def _inverse(key: Int[Array, " N"], count: Int[Array, " FSS"], n_src: int, m: int):
    """Per face pixel its first ``m`` fisheye pixels in index order (the order of a stable sort of
    the fisheye pixels by face pixel ``key``), -1 after, and its fan-out ``count`` capped at ``m``.
    Slot ``j`` is a scatter-min of the pixels not taken by slots ``< j``: ``m`` passes over the
    fisheye (XLA's CPU sort of the keys would take several times longer)."""
    index = jnp.arange(key.shape[0], dtype=jnp.int32)
    none = jnp.iinfo(jnp.int32).max
    slots, rest = [], key
    for _ in range(m):
        first = jnp.full(n_src + 1, none, jnp.int32).at[rest].min(index)
        slots.append(jnp.where(first[:n_src] == none, -1, first[:n_src]))
        rest = jnp.where(first[rest] == index, n_src, rest)  # a taken pixel leaves for the spare bin
    return jnp.stack(slots, axis=1), jnp.minimum(count, m)


def event_map_from_lut(lut: Lut, *, max_fanout: int | None = None) -> EventMap:
    """Build the `EventMap` of a cube -> fisheye `Lut` (its centre sample). ``max_fanout`` (static)
    defaults to the LUT's true maximum (computed on the host; pass it explicitly under `jax.jit`).
    Face pixels feeding more than ``max_fanout`` fisheye pixels keep only the first ``max_fanout``."""
    f, s_h, s_w = lut.source_shape
    n_src = f * s_h * s_w
    key, count = _source_counts(lut, n_src)
    if max_fanout is None:
        max_fanout = max(int(jnp.max(count)), 1)
    targets, fanout = _inverse(key, count, n_src, int(max_fanout))
    h, w = lut.target_shape
    return EventMap(targets=targets, fanout=fanout, width=int(w), height=int(h), face_size=int(s_w), num_faces=int(f),
                    max_fanout=int(max_fanout))


class FisheyeEvents(eqx.Module):
    """Events on the fisheye image, padded to a static size: the first `count` entries are the
    events in time order (`x` column, `y` row, `t` as given, `polarity` True = brighter, `face` the
    source face index); `valid` marks them."""

    x: Int[Array, " N"]
    y: Int[Array, " N"]
    t: Int[Array, " N"]
    polarity: Bool[Array, " N"]
    face: Int[Array, " N"]
    valid: Bool[Array, " N"]
    count: Int[Array, ""]


def map_events(
    event_map: EventMap,
    face: Int[ArrayLike, " E"],
    x: Int[ArrayLike, " E"],
    y: Int[ArrayLike, " E"],
    t: Int[ArrayLike, " E"],
    polarity: Bool[ArrayLike, " E"],
) -> FisheyeEvents:
    """Map face events (face index in the `CubeRig` order, face pixel ``x`` column / ``y`` row,
    time ``t`` in any integer unit, polarity) to fisheye events under the module's rule. Output
    size ``E * max_fanout`` (static); sorted by time, valid events first. Pure JAX.

    Without ``jax_enable_x64``, JAX holds integers as int32: host times that do not fit (CARLA's
    absolute nanoseconds, ~1e10 after 10 s of simulation) raise `ValueError` instead of wrapping
    silently; pass times relative to the frame (``t - t0``, 0.1 s = 1e8 ns fits) and add ``t0``
    back, or enable x64. (`jaxfish.io.map_face_events`, the builder's NumPy twin, keeps int64.)"""
    _check_time_range(t)
    fi = jnp.asarray(face).astype(jnp.int32)
    xi = jnp.asarray(x).astype(jnp.int32)
    yi = jnp.asarray(y).astype(jnp.int32)
    tt = jnp.asarray(t)
    s = event_map.face_size
    inb = (fi >= 0) & (fi < event_map.num_faces) & (xi >= 0) & (xi < s) & (yi >= 0) & (yi < s)
    src = jnp.where(inb, (fi * s + yi) * s + xi, 0)
    # Stable sort of the E face events by time (their M fisheye copies share a time and stay in slot
    # order), then a stable partition moving the valid copies first: the same order as a stable sort
    # of all E * M copies, at the cost of sorting E keys.
    by_time = jnp.argsort(tt, stable=True)
    tg = jnp.where(inb[:, None], event_map.targets[src], -1)[by_time]  # (E, M)
    m = event_map.max_fanout
    n = tg.size
    ok_all = (tg >= 0).reshape(-1)
    order = jnp.nonzero(ok_all, size=n, fill_value=n)[0]  # valid copies first, in order
    ok = order < n
    event = jnp.where(ok, order // m, 0)  # index into the time-sorted face events
    safe = jnp.where(ok, tg.reshape(-1)[jnp.where(ok, order, 0)], 0)
    src_event = by_time[event]
    w = event_map.width
    return FisheyeEvents(
        x=jnp.where(ok, safe % w, 0).astype(jnp.int32), y=jnp.where(ok, safe // w, 0).astype(jnp.int32),
        t=jnp.where(ok, tt[src_event], 0), polarity=ok & jnp.asarray(polarity, bool)[src_event],
        face=jnp.where(ok, fi[src_event], -1), valid=ok, count=jnp.sum(ok.astype(jnp.int32)),
    )


def _check_time_range(t) -> None:
    """Raise when host times would wrap on conversion to JAX's default integer type (int32 unless
    ``jax_enable_x64``); traced or device arrays already hold their values."""
    if isinstance(t, jax.Array):
        return
    a = np.asarray(t)
    if a.size == 0 or not np.issubdtype(a.dtype, np.integer):
        return
    held = np.dtype(jax.dtypes.canonicalize_dtype(a.dtype))
    info = np.iinfo(held)
    if held.itemsize < a.dtype.itemsize and (a.max() > info.max or a.min() < info.min):
        raise ValueError(f"map_events: times span [{a.min()}, {a.max()}], beyond {held} (jax_enable_x64 is off): "
                         "pass times relative to the frame start (t - t0) and add t0 back, or enable jax_enable_x64")


def compact_events(events: FisheyeEvents) -> dict[str, np.ndarray]:
    """The valid events as NumPy arrays ``x, y, t, polarity, face`` (host; variable length)."""
    n = int(events.count)
    return {k: np.asarray(getattr(events, k))[:n] for k in ("x", "y", "t", "polarity", "face")}
