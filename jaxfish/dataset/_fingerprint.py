"""Fingerprints of a capture's frames: what a built sample records of its inputs."""

from __future__ import annotations

import hashlib
import os
import stat
from pathlib import Path


def frame_fingerprint(capture_dir: str | os.PathLike, frame: int) -> str:
    """SHA-256 of a capture frame's folder (``frames/{frame:06d}``): the bytes of its JSON files
    (ego, actors, IMU, GNSS: they differ between any two renders or recordings) and the name and
    size of every other file (images, events, point clouds: stat only, so that resuming a large
    build stays cheap; a path that is not a regular file, by its name and kind, never read). Hidden
    files (and jaxfish's temporaries) are ignored. An image replaced by
    another of exactly the same size is not seen: rebuild such a sample (``rebuild=True``)."""
    from ..io._capture import frame_dir

    d = frame_dir(capture_dir, frame)
    entries = []
    for dirpath, dirs, files in os.walk(d):
        dirs[:] = [x for x in dirs if not x.startswith(".")]
        entries += [os.path.join(dirpath, n) for n in files if not n.startswith(".")]
    h = hashlib.sha256()
    for path in sorted(entries):
        rel = os.path.relpath(path, d).replace(os.sep, "/")
        try:
            st = os.stat(path)
        except OSError as e:  # a broken link, a link loop: the sample's read names it
            h.update(f"{rel}\0unreadable {e.errno}\0".encode())
            continue
        if not stat.S_ISREG(st.st_mode):  # never read a FIFO or a device (it would block): the read names it
            h.update(f"{rel}\0not a regular file {stat.S_IFMT(st.st_mode)}\0".encode())
        elif rel.endswith(".json"):
            data = Path(path).read_bytes()
            h.update(f"{rel}\0{len(data)}\0".encode())
            h.update(data)
        else:
            h.update(f"{rel}\0{st.st_size}\0".encode())
    return h.hexdigest()

