"""Face DVS events mapped to fisheye pixels on the host (NumPy): the builder's twin of
`jaxfish.groundtruth.map_events` + `compact_events` (no recompilation per event count)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from .._constants import DVS_EVENT_DTYPE
from ..groundtruth import EventMap


def map_face_events(targets: np.ndarray, width: int, face_size: int, face: np.ndarray, x: np.ndarray, y: np.ndarray,
                    t: np.ndarray, pol: np.ndarray, fanout: np.ndarray | None = None) -> np.ndarray:
    """NumPy twin of `jaxfish.groundtruth.map_events` + `compact_events` (same rule, same order:
    stable sort by time, ties in face-event then fisheye-pixel order) for an `EventMap`'s
    ``targets`` (and ``fanout``, derived from ``targets`` when omitted).

    Args: ``targets`` ``(F * S * S, M)`` fisheye flat indices (-1 padding); ``width`` of the
    fisheye; ``face_size`` ``S``; per face event its ``face`` index, ``x``, ``y`` (face pixels),
    ``t`` (ns) and ``pol``. Returns the fisheye events in CARLA's DVS dtype (t unchanged, ns)."""
    tg_all = np.asarray(targets)
    n_src = tg_all.shape[0]
    fan = np.sum(tg_all >= 0, axis=1) if fanout is None else np.asarray(fanout)
    s = int(face_size)
    f, xi, yi = (np.asarray(a, np.int64) for a in (face, x, y))
    inb = (f >= 0) & (xi >= 0) & (xi < s) & (yi >= 0) & (yi < s)
    src = (f * s + yi) * s + xi
    inb &= (src >= 0) & (src < n_src)
    src = np.where(inb, src, 0)
    counts = np.where(inb, fan[src], 0)
    ev_idx = np.repeat(np.arange(src.shape[0]), counts)  # each face event, once per fisheye pixel it feeds
    slot = np.arange(ev_idx.shape[0]) - np.repeat(np.cumsum(counts) - counts, counts)
    flat = tg_all[src[ev_idx], slot]
    tt = np.asarray(t, np.int64)[ev_idx]
    order = np.argsort(tt, kind="stable")
    out = np.empty(order.shape[0], DVS_EVENT_DTYPE)
    out["x"], out["y"] = flat[order] % width, flat[order] // width
    out["t"], out["pol"] = tt[order], np.asarray(pol, bool)[ev_idx][order]
    return out


def camera_events(events: Sequence[np.ndarray], event_map: EventMap) -> np.ndarray:
    """A camera's face events (one CARLA-dtype array per face, in the event map's face order)
    mapped to its fisheye through ``event_map``: CARLA-dtype events, t in ns, time order."""
    face = np.concatenate([np.full(ev.shape[0], i, np.int32) for i, ev in enumerate(events)])
    cat = {k: np.concatenate([ev[k] for ev in events]) for k in ("x", "y", "t", "pol")}
    return map_face_events(np.asarray(event_map.targets), int(event_map.width), int(event_map.face_size), face,
                           cat["x"], cat["y"], cat["t"], cat["pol"], fanout=np.asarray(event_map.fanout))
