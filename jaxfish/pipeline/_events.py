"""Face DVS events mapped to fisheye pixels on the host (NumPy): the builder's twin of
`jaxfish.groundtruth.map_events` + `compact_events` (no recompilation per event count)."""

from __future__ import annotations

import threading
import weakref
from collections.abc import Sequence

import equinox as eqx
import numpy as np
from jaxtyping import Int

from .._constants import DVS_EVENT_DTYPE
from ..groundtruth import EventMap

_FEW_RUNS = 256
"""`_time_order` merges times made of at most this many ascending runs with a stable argsort."""


def _time_order(t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The stable order of the int64 times ``t`` and the sorted times. Times made of at most
    `_FEW_RUNS` ascending runs (a camera's events: each face's arrive in time order) take a stable
    argsort, which merges the runs it finds. Otherwise, when every time minus the earliest fits
    beside an event's index in 63 bits (spans up to hours for millions of events), one unstable
    sort of ``(t - min) << b | index`` gives both (the index breaks ties as a stable sort does);
    otherwise a stable argsort. The order is the same either way."""
    n = t.shape[0]
    if n > 1 and np.count_nonzero(t[1:] < t[:-1]) < _FEW_RUNS:
        order = np.argsort(t, kind="stable")
        return order, t[order]
    bits = max(n - 1, 1).bit_length()
    if n:
        low, high = int(t.min()), int(t.max())
        if high - low < 1 << (63 - bits):
            key = t - low
            key <<= bits
            key |= np.arange(n, dtype=np.int64)
            key.sort()
            order = key & ((1 << bits) - 1)
            key >>= bits
            key += low
            return order, key
    order = np.argsort(t, kind="stable")
    return order, t[order]


def _by_time(flat: np.ndarray, t: np.ndarray, pol: np.ndarray, width: int) -> np.ndarray:
    """CARLA-dtype events of fisheye flat indices ``flat``, stably sorted by ``t`` (int64)."""
    order, t_sorted = _time_order(np.asarray(t, np.int64))
    y, x = np.divmod(flat[order], width)
    out = np.empty(order.shape[0], DVS_EVENT_DTYPE)
    out["x"], out["y"] = x, y
    out["t"], out["pol"] = t_sorted, pol[order]
    return out


class FaceEventTable(eqx.Module):
    """A camera's `jaxfish.groundtruth.EventMap` on the host, compact: what `camera_events` maps
    face DVS events with (`face_event_table`). Every array is NumPy and read-only.

    - `first` ``(F * S * S,)`` int32: per face pixel (flat ``(face * S + y) * S + x``) the fisheye
      pixel it feeds (flat ``v * width + u``), -1 when it feeds none, or ``-2 - j`` when it feeds
      several: then row ``j`` of `many` holds them;
    - `many` ``(K, M)`` int32: the fisheye pixels of the ``K`` face pixels that feed several, in the
      map's slot order, -1 after the last; `many_count` ``(K,)``: how many of them;
    - static: `width` of the fisheye, `face_size` ``S``.

    It holds 4 bytes per face pixel where the `EventMap` holds ``4 (M + 1)`` (the dense targets
    and the fan-out): a rig's constants keep this table, not the map."""

    first: Int[np.ndarray, " FSS"]
    many: Int[np.ndarray, "K M"]
    many_count: Int[np.ndarray, " K"]
    width: int = eqx.field(static=True)
    face_size: int = eqx.field(static=True)


def _host_map(targets: np.ndarray, fanout: np.ndarray, width: int, face_size: int) -> FaceEventTable:
    """The `FaceEventTable` of an event map's ``targets`` ``(F * S * S, M)`` (a pixel's targets
    first, -1 after) and ``fanout`` (at most ``M`` of them are used)."""
    count = np.minimum(np.asarray(fanout), targets.shape[1])
    first = targets[:, 0].astype(np.int32)
    first[count == 0] = -1
    several = np.flatnonzero(count > 1)
    first[several] = -2 - np.arange(several.size, dtype=np.int32)
    many, many_count = np.ascontiguousarray(targets[several], np.int32), count[several].astype(np.int32)
    for a in (first, many, many_count):
        a.setflags(write=False)
    return FaceEventTable(first, many, many_count, int(width), int(face_size))


def face_event_table(event_map: EventMap) -> FaceEventTable:
    """The `FaceEventTable` of ``event_map`` (a new table: `camera_events` of the map itself keeps
    one per map instead)."""
    return _host_map(np.asarray(event_map.targets), np.asarray(event_map.fanout), event_map.width,
                     event_map.face_size)


_HOST_MAPS: dict[int, tuple[weakref.ref, FaceEventTable]] = {}
_HOST_MAPS_LOCK = threading.Lock()


def _host_map_of(event_map: EventMap) -> FaceEventTable:
    """``event_map``'s `FaceEventTable`, built once and kept while its ``targets`` array lives."""
    targets = event_map.targets
    key = id(targets)
    with _HOST_MAPS_LOCK:
        kept = _HOST_MAPS.get(key)
        if kept is not None and kept[0]() is targets:
            return kept[1]
    table = face_event_table(event_map)
    with _HOST_MAPS_LOCK:
        _HOST_MAPS[key] = (weakref.ref(targets), table)
    weakref.finalize(targets, _forget_host_map, key, weakref.ref(targets))
    return table


def _forget_host_map(key: int, ref: weakref.ref) -> None:
    with _HOST_MAPS_LOCK:
        kept = _HOST_MAPS.get(key)
        if kept is not None and kept[0] is ref:
            del _HOST_MAPS[key]


def _face_copies(table: FaceEventTable, src: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The events at face pixels ``src`` (indices into ``table.first``) once per fisheye pixel they
    feed, a pixel's targets in slot order: ``(event index, fisheye flat index)``."""
    target = table.first.take(src)  # ``src`` of NumPy's index type: taken without an index conversion
    index = np.flatnonzero(target != -1)
    flat = target.take(index)
    several = np.flatnonzero(flat < -1)  # the few events whose pixel feeds more than one
    if several.size:
        rows = -2 - flat[several]
        flat[several] = table.many[rows, 0]
        extra = table.many_count[rows] - 1
        at = np.repeat(several + 1, extra)  # inserted after the event's first copy, in slot order
        slot = np.arange(at.size) - np.repeat(np.cumsum(extra) - extra, extra) + 1
        flat = np.insert(flat, at, table.many[np.repeat(rows, extra), slot])
        index = np.insert(index, at, index[np.repeat(several, extra)])
    return index, flat


def map_face_events(targets: np.ndarray, width: int, face_size: int, face: np.ndarray, x: np.ndarray, y: np.ndarray,
                    t: np.ndarray, pol: np.ndarray, fanout: np.ndarray | None = None) -> np.ndarray:
    """NumPy twin of `jaxfish.groundtruth.map_events` + `compact_events` (same rule, same order:
    stable sort by time, ties in face-event then fisheye-pixel order) for an `EventMap`'s
    ``targets`` (and ``fanout``, derived from ``targets`` when omitted).

    Args: ``targets`` ``(F * S * S, M)`` fisheye flat indices (-1 padding, a pixel's targets
    first); ``width`` of the fisheye; ``face_size`` ``S``; per face event its ``face`` index,
    ``x``, ``y`` (face pixels), ``t`` (ns) and ``pol``. Events outside the faces feed no pixel.
    Returns the fisheye events in CARLA's DVS dtype (t unchanged, ns)."""
    tg = np.asarray(targets)
    table = _host_map(tg, np.sum(tg >= 0, axis=1) if fanout is None else fanout, int(width), int(face_size))
    s = int(face_size)
    f, xi, yi = (np.asarray(a, np.int64) for a in (face, x, y))
    inb = (f >= 0) & (xi >= 0) & (xi < s) & (yi >= 0) & (yi < s)
    src = (f * s + yi) * s + xi
    inb &= src < tg.shape[0]
    kept = np.flatnonzero(inb)
    ev_idx, flat = _face_copies(table, src[kept])
    ev_idx = kept[ev_idx]
    return _by_time(flat, np.asarray(t, np.int64)[ev_idx], np.asarray(pol, bool)[ev_idx], int(width))


def camera_events(events: Sequence[np.ndarray], event_map: EventMap | FaceEventTable) -> np.ndarray:
    """A camera's face events (one CARLA-dtype array per face, in the event map's face order, or
    an object whose ``np.asarray`` is that array: converted once each, one face at a time)
    mapped to its fisheye through ``event_map`` (an `EventMap`, or its `FaceEventTable`: the same
    events): CARLA-dtype events, t in ns, time order; the same events as `map_face_events` of the
    concatenated faces. Each face is mapped on its own: only the events that feed a fisheye pixel
    are gathered and sorted, through the map's `FaceEventTable` (made once per `EventMap`)."""
    table = event_map if isinstance(event_map, FaceEventTable) else _host_map_of(event_map)
    n = table.first.shape[0]
    s = int(table.face_size)
    flats, times, pols = [], [], []
    for i, face_events in enumerate(events):
        ev = np.asarray(face_events)
        if ev.shape[0] == 0:
            continue
        x, y = ev["x"], ev["y"]
        src = y.astype(np.intp)
        src *= s
        src += x
        src += i * s * s
        signed = x.dtype.kind == "i" or y.dtype.kind == "i"  # CARLA's are unsigned: no minimum to check
        if int(x.max()) >= s or int(y.max()) >= s or (signed and (int(x.min()) < 0 or int(y.min()) < 0)) \
                or (i + 1) * s * s > n:  # outside the face, or a face beyond the map's
            inb = (x >= 0) & (x < s) & (y >= 0) & (y < s) & (src < n)
            kept = np.flatnonzero(inb)
            ev_idx, flat = _face_copies(table, src[kept])
            ev_idx = kept[ev_idx]
        else:
            ev_idx, flat = _face_copies(table, src)
        flats.append(flat)
        times.append(ev["t"][ev_idx].astype(np.int64, copy=False))
        pols.append(ev["pol"][ev_idx].astype(bool, copy=False))
    if not flats:
        return np.empty(0, DVS_EVENT_DTYPE)
    return _by_time(np.concatenate(flats), np.concatenate(times), np.concatenate(pols), int(table.width))
