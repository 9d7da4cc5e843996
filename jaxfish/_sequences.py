"""What a process keeps of the sequences it builds: each sequence's last frame, so that the next
sample of that sequence reuses it (its decoded cube faces, its fisheye images and labels, its RGB
PNG bytes) instead of computing it again.

A sequence is identified by its *owner*: the thread that builds it (`sequence_owner`), or the
owner a helper thread acts for (`acting_for`: a decoding or writing pool of that thread). A
process keeps the last frames of at most `sequence_slots` owners, the most recently active ones;
a serial build needs one, a process building N sequences at once (N thread workers) needs N. A
lookup may match any owner's kept entry: every match is an exact comparison (the same array
object, or the same bytes), never a guess.
"""

from __future__ import annotations

import contextlib
import os
import threading
import weakref
from collections.abc import Hashable, Iterator
from typing import Any

_SLOTS = 1
_LOCK = threading.Lock()
_ACTING = threading.local()
_STORES: weakref.WeakSet[KeptByOwner] = weakref.WeakSet()


def sequence_slots() -> int:
    """How many sequences this process keeps a last frame of (1 unless `set_sequence_slots`)."""
    return _SLOTS


def set_sequence_slots(slots: int) -> int:
    """Keep the last frame of ``slots`` sequences built at once in this process (threads each
    building consecutive samples, e.g. the thread workers of a local dask cluster); returns the
    previous value. Each kept frame holds about a sample's decoded inputs and images (0.5–1 GB at
    full size); the stores drop the least recently active sequences beyond ``slots`` at once."""
    global _SLOTS
    if isinstance(slots, bool) or not isinstance(slots, int) or slots < 1:
        raise ValueError(f"sequence slots must be an integer >= 1, got {slots!r}")
    with _LOCK:
        previous, _SLOTS = _SLOTS, slots
        stores = list(_STORES)
    for store in stores:
        store.prune()
    return previous


def usable_cores() -> int:
    """The cores this process may run on (its CPU affinity: a pinned dask worker's share), at least
    1: what its sequences and their helper threads (decoding, event mapping) share."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):  # pragma: no cover - not Linux
        return os.cpu_count() or 1


def sequence_owner() -> Hashable:
    """The owner of the sequence the calling thread builds: the owner it acts for (`acting_for`),
    else the thread itself."""
    owner = getattr(_ACTING, "owner", None)
    return threading.get_ident() if owner is None else owner


@contextlib.contextmanager
def acting_for(owner: Hashable) -> Iterator[None]:
    """Within the block, the calling thread (a pool thread decoding or writing for another)
    keeps what it keeps under ``owner`` (`sequence_owner`)."""
    before = getattr(_ACTING, "owner", None)
    _ACTING.owner = owner
    try:
        yield
    finally:
        _ACTING.owner = before


class KeptByOwner:
    """A thread-safe store of ``key -> value`` per owner, for at most `sequence_slots` owners:
    `put` under an owner beyond that many drops the least recently active owner's entries."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._owners: dict[Hashable, dict[Hashable, Any]] = {}  # least recently active first
        with _LOCK:
            _STORES.add(self)

    def put(self, key: Hashable, value: Any, owner: Hashable | None = None) -> None:
        """Keep ``value`` under ``key`` for ``owner`` (`sequence_owner` when None)."""
        owner = sequence_owner() if owner is None else owner
        with self._lock:
            entries = self._owners.pop(owner, {})
            entries[key] = value
            self._owners[owner] = entries
        self.prune()

    def prune(self) -> None:
        """Drop the least recently active owners beyond `sequence_slots`."""
        with self._lock:
            while len(self._owners) > sequence_slots():
                del self._owners[next(iter(self._owners))]

    def pop(self, key: Hashable, owner: Hashable | None = None) -> None:
        """Drop ``owner``'s entry under ``key`` (`sequence_owner` when None), if any."""
        owner = sequence_owner() if owner is None else owner
        with self._lock:
            self._owners.get(owner, {}).pop(key, None)

    def values(self, key: Hashable, owner: Hashable | None = None) -> list[Any]:
        """Every owner's value under ``key``: ``owner``'s first (`sequence_owner` when None), then
        the others', most recently active first."""
        owner = sequence_owner() if owner is None else owner
        with self._lock:
            order = sorted(reversed(list(self._owners)), key=lambda o: o != owner)
            return [self._owners[o][key] for o in order if key in self._owners[o]]

    def clear(self) -> None:
        with self._lock:
            self._owners.clear()
