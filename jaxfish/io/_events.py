"""Event files: CARLA's DVS dtype (``.npy``, t in nanoseconds), tonic-compatible ``x, y, t, p``
arrays (``.npz`` with the time unit stored, t in microseconds), and the colour rendering PNG."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from .._errors import ImageError
from ._carla import DVS_EVENT_DTYPE
from ._npz import NpzMember, load_npy, write_npy, write_npz

TONIC_EVENT_DTYPE = np.dtype([("x", "<i2"), ("y", "<i2"), ("t", "<i8"), ("p", "i1")])
"""The tonic event dtype jaxfish writes: ``x, y`` int16, ``t`` int64 (µs), ``p`` int8 (1 / 0),
packed (13 bytes an event, the widths of tonic's own DVSGesture records with a signed polarity, so
that tonic's transforms, e.g. a polarity flip to -1, work on it)."""

TONIC_MAX_PIXEL = int(np.iinfo(np.int16).max)
"""The largest pixel coordinate `TONIC_EVENT_DTYPE` holds (sensors up to 32768 pixels wide and high)."""


def carla_events(x, y, t_ns, polarity) -> np.ndarray:
    """Structured array in CARLA's DVS dtype (`DVS_EVENT_DTYPE`: ``x, y`` uint16, ``t`` int64
    nanoseconds, ``pol`` bool) from columns."""
    x = np.asarray(x)
    ev = np.empty(x.shape[0], DVS_EVENT_DTYPE)
    if x.size and (x.min() < 0 or np.asarray(y).min() < 0 or x.max() > 65535 or np.asarray(y).max() > 65535):
        raise ImageError("carla_events: pixel coordinates must lie in 0..65535")
    ev["x"], ev["y"], ev["t"], ev["pol"] = x, np.asarray(y), np.asarray(t_ns, np.int64), np.asarray(polarity, bool)
    return ev


def _structured_events(events: np.ndarray, where: object) -> np.ndarray:
    """``events`` as a 1-D array with CARLA's DVS fields (x, y, t, pol); a plain numeric array (its
    cast to a record dtype never fails, it would invent events) raises `ImageError`."""
    ev = np.asarray(events)
    if ev.dtype.names is None or set(ev.dtype.names) != set(DVS_EVENT_DTYPE.names) or ev.ndim != 1:
        raise ImageError(f"{where}: events must be a 1-D array with CARLA's DVS fields {DVS_EVENT_DTYPE.names} "
                         f"(DVS_EVENT_DTYPE), got {ev.dtype} of shape {ev.shape}")
    return ev


def carla_to_tonic(events: np.ndarray) -> np.ndarray:
    """CARLA events (t in ns) -> tonic's ``x, y, t, p`` (`TONIC_EVENT_DTYPE`: t in **µs**, floor
    division; p 1 / 0). Raises `ImageError` for a pixel coordinate outside 0..`TONIC_MAX_PIXEL`."""
    ev = _structured_events(events, "carla_to_tonic")
    _check_tonic_pixels(ev, "carla_to_tonic")
    return _tonic_into(ev, np.empty(ev.shape[0], TONIC_EVENT_DTYPE))


def _check_tonic_pixels(ev: np.ndarray, where: object) -> None:
    """`ImageError` unless every ``x, y`` of ``ev`` lies in 0..`TONIC_MAX_PIXEL` (int16 would wrap)."""
    for axis in ("x", "y"):
        c = ev[axis]
        if c.size and (int(c.max()) > TONIC_MAX_PIXEL or (c.dtype.kind in "if" and int(c.min()) < 0)):
            raise ImageError(f"{where}: field '{axis}': tonic events hold pixel coordinates 0..{TONIC_MAX_PIXEL}, "
                             f"got {c.min()}..{c.max()}")


def _tonic_into(ev: np.ndarray, out: np.ndarray) -> np.ndarray:
    """`carla_to_tonic` of CARLA-field events ``ev`` into the `TONIC_EVENT_DTYPE` array ``out``."""
    out["x"], out["y"] = ev["x"], ev["y"]
    t = ev["t"] if ev.dtype["t"] == np.int64 else ev["t"].astype(np.int64)  # e.g. float times: truncated first
    np.floor_divide(t, 1000, out=out["t"])
    out["p"] = ev["pol"]  # cast as astype(int8) casts (True -> 1)
    return out


TONIC_CHUNK_EVENTS = 1 << 16
"""Events `write_events_tonic` converts at a time (an 832 KiB buffer, reused)."""


def write_events_npy(path: str | os.PathLike, events: np.ndarray) -> Path:
    """Write events in CARLA's dtype (t in ns) as ``.npy`` (atomic; no pickle)."""
    path = Path(path)
    ev = _structured_events(events, path)
    if ev.dtype != DVS_EVENT_DTYPE:
        ev = ev.astype(DVS_EVENT_DTYPE)  # same fields, other widths or order
    write_npy(path, np.ascontiguousarray(ev))
    return path


def read_events_npy(path: str | os.PathLike) -> np.ndarray:
    """Read a CARLA-dtype events ``.npy`` (t in ns)."""
    path = Path(path)
    if not path.is_file():
        raise ImageError(f"{path}: file missing")
    try:
        ev = load_npy(path)
    except (ValueError, OSError, EOFError) as e:
        raise ImageError(f"{path}: not a readable .npy array ({e})") from None
    if ev.dtype != DVS_EVENT_DTYPE:
        raise ImageError(f"{path}: dtype {ev.dtype} is not CARLA's DVS dtype {DVS_EVENT_DTYPE}")
    return ev


def write_events_tonic(path: str | os.PathLike, events: np.ndarray, *, width: int, height: int) -> Path:
    """Write CARLA events as a tonic-compatible ``.npz`` (`write_npz`: the same events always give
    the same bytes): ``events`` (`TONIC_EVENT_DTYPE`, t in µs, `carla_to_tonic`),
    ``time_unit = "us"`` and ``sensor_size = (width, height, 2)`` (int64). The events are
    converted and written a chunk at a time. Raises `ImageError` naming the file for a sensor or
    a pixel coordinate beyond `TONIC_MAX_PIXEL`."""
    path = Path(path)
    ev = _structured_events(events, path)
    if not (0 < width <= TONIC_MAX_PIXEL + 1 and 0 < height <= TONIC_MAX_PIXEL + 1):
        raise ImageError(f"{path}: field 'sensor_size': tonic events hold sensors up to {TONIC_MAX_PIXEL + 1} pixels "
                         f"wide and high, got {width} x {height}")
    _check_tonic_pixels(ev, path)

    def chunks():
        buf = np.empty(min(ev.shape[0], TONIC_CHUNK_EVENTS), TONIC_EVENT_DTYPE)
        for start in range(0, ev.shape[0], TONIC_CHUNK_EVENTS):
            part = ev[start:start + TONIC_CHUNK_EVENTS]
            yield memoryview(_tonic_into(part, buf[:part.shape[0]]).view(np.uint8))

    return write_npz(path, events=NpzMember(TONIC_EVENT_DTYPE, ev.shape, chunks), time_unit=np.asarray("us"),
                     sensor_size=np.asarray([width, height, 2], np.int64))


def read_events_tonic(path: str | os.PathLike) -> tuple[np.ndarray, str, tuple[int, int, int]]:
    """Read what `write_events_tonic` wrote: ``(events, time_unit, sensor_size)``."""
    path = Path(path)
    if not path.is_file():
        raise ImageError(f"{path}: file missing")
    with np.load(path, allow_pickle=False) as z:
        for key in ("events", "time_unit", "sensor_size"):
            if key not in z:
                raise ImageError(f"{path}: field '{key}' missing")
        return z["events"], str(z["time_unit"]), tuple(int(v) for v in z["sensor_size"])  # type: ignore[return-value]
