"""COLMAP text model: ``cameras.txt`` (``CAMERA_ID MODEL WIDTH HEIGHT PARAMS...``) and, for the
poses, ``images.txt`` (``IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME`` then a line of 2D points;
world -> camera): two lines per image, as COLMAP reads them, the line after an image line being its
points line (``X Y POINT3D_ID`` triples, or empty); any other line there (an image line whose
points line is missing) is refused with the file and line. COLMAP's pixel origin is the top-left corner of the top-left pixel: its
principal point is jaxfish's plus 0.5 px. The world is jaxfish's vehicle frame; a camera with no
image keeps the identity pose. Camera names: the image ``NAME`` without its extension.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from ._common import (
    CameraRecord,
    ModelMapping,
    fail,
    find_reader,
    find_writer,
    number,
    quaternion_matrix,
    quaternion_xyzw,
    rigid_inverse,
    short,
)

_P = ("fx", "fy", "cx", "cy")
COLMAP_MODELS: tuple[ModelMapping, ...] = (
    ModelMapping("OPENCV_FISHEYE", "kannala_brandt", (*_P, "k1", "k2", "k3", "k4")),
    ModelMapping("SIMPLE_RADIAL_FISHEYE", "kannala_brandt", ("fx|fy", "cx", "cy", "k1")),
    ModelMapping("RADIAL_FISHEYE", "kannala_brandt", ("fx|fy", "cx", "cy", "k1", "k2")),
    ModelMapping("FISHEYE", "kannala_brandt", _P),
    ModelMapping("SIMPLE_FISHEYE", "kannala_brandt", ("fx|fy", "cx", "cy")),
    ModelMapping("PINHOLE", "pinhole", _P),
    ModelMapping("SIMPLE_PINHOLE", "pinhole", ("fx|fy", "cx", "cy")),
    ModelMapping("OPENCV", "opencv", (*_P, "k1", "k2", "p1", "p2")),
    ModelMapping("FULL_OPENCV", "opencv", (*_P, "k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")),
    ModelMapping("SIMPLE_RADIAL", "opencv", ("fx|fy", "cx", "cy", "k1")),
    ModelMapping("RADIAL", "opencv", ("fx|fy", "cx", "cy", "k1", "k2")),
    ModelMapping("PINHOLE", "opencv", _P),
    ModelMapping("SIMPLE_PINHOLE", "opencv", ("fx|fy", "cx", "cy")),
    ModelMapping("FOV", "fov", (*_P, "w")),
    ModelMapping("EUCM", "extended_unified", (*_P, "alpha", "beta")),
    ModelMapping("RAD_TAN_THIN_PRISM_FISHEYE", "fisheye624",
                 (*_P, "k0", "k1", "k2", "k3", "k4", "k5", "p0", "p1", "s0", "s1", "s2", "s3")),
)
"""COLMAP camera model <-> jaxfish model (COLMAP's parameter order; ``fx|fy`` is its single focal
length ``f``). The first row of a jaxfish model that holds a camera exactly is the one written."""

_PIXEL_ORIGIN = 0.5  # COLMAP cx = jaxfish cx + 0.5


def _lines(text: str) -> list[tuple[int, str]]:
    return [(i + 1, ln.strip()) for i, ln in enumerate(text.splitlines()) if ln.strip() and not ln.lstrip().startswith("#")]


def read(cameras_txt: Path, images_txt: Path | None) -> list[CameraRecord]:
    """The cameras of a COLMAP text model (``images.txt`` optional)."""
    source = str(cameras_txt)
    text = cameras_txt.read_text(encoding="utf-8", errors="strict")
    cams: dict[int, CameraRecord] = {}
    for lineno, line in _lines(text):
        parts = line.split()
        where = f"line {lineno}"
        if len(parts) < 4:
            raise fail(source, where, f"expected CAMERA_ID MODEL WIDTH HEIGHT PARAMS..., got {short(line)}")
        try:
            cam_id = int(parts[0])
        except ValueError:
            raise fail(source, f"{where}.CAMERA_ID", f"expected an integer, got {short(parts[0])}") from None
        if cam_id in cams:
            raise fail(source, f"{where}.CAMERA_ID", f"camera {cam_id} is listed twice")
        m = find_reader(COLMAP_MODELS, parts[1])
        if m is None:
            known = ", ".join(dict.fromkeys(r.tool for r in COLMAP_MODELS))
            raise fail(source, f"{where}.MODEL", f"COLMAP model {short(parts[1])} is not one jaxfish reads (known: {known})")
        w, h = (number(parts[2 + j], source, f"{where}.{k}") for j, k in enumerate(("WIDTH", "HEIGHT")))
        for v, k in ((w, "WIDTH"), (h, "HEIGHT")):
            if v <= 0 or v != int(v):
                raise fail(source, f"{where}.{k}", f"expected a positive whole number, got {short(v)}")
        vals = [number(x, source, f"{where}.PARAMS[{j}]") for j, x in enumerate(parts[4:])]
        params = m.read(vals, source, f"{where}.MODEL")
        params["cx"] -= _PIXEL_ORIGIN
        params["cy"] -= _PIXEL_ORIGIN
        cams[cam_id] = CameraRecord(f"camera{cam_id}", m.model, params, int(w), int(h), np.eye(4), where=where)
    if not cams:
        raise fail(source, "<cameras>", "no camera lines")
    if images_txt is not None and images_txt.exists():
        _read_images(images_txt, cams)
    return list(cams.values())


def _points_line(line: str, source: str, where: str, image_where: str) -> None:
    """Check that ``line`` is a ``POINTS2D`` line (``X Y POINT3D_ID`` triples of numbers, or empty;
    a comment line, which COLMAP also takes as the points line, holds none)."""
    parts = line.split()
    if not parts or parts[0].startswith("#"):
        return
    try:
        values = np.asarray(parts, np.float64)
    except ValueError:
        values = None
    if values is None or len(parts) % 3 or not np.all(np.isfinite(values)):
        raise fail(source, where, f"expected the POINTS2D line of the image on {image_where} (X Y POINT3D_ID "
                                  f"triples, or an empty line: images.txt has two lines per image), got {short(line.strip())}")


def _read_images(path: Path, cams: dict[int, CameraRecord]) -> None:
    source = str(path)
    seen: set[int] = set()
    # Two lines per image, as COLMAP reads them: an image line (blank and comment lines before it
    # are skipped), then the line after it, whatever it holds, is its 2D points line (may be
    # empty). A file that ends after an image line has that image without points.
    raw = path.read_text(encoding="utf-8").splitlines()
    k = 0
    while k < len(raw):
        lineno, line = k + 1, raw[k]
        if not line.strip() or line.lstrip().startswith("#"):
            k += 1
            continue
        parts = line.split()
        where = f"line {lineno}"
        if len(parts) < 10:
            raise fail(source, where, f"expected IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME, got {line.strip()!r}")
        if k + 1 < len(raw):
            _points_line(raw[k + 1], source, f"line {lineno + 1}", where)
        q = [number(parts[1 + j], source, f"{where}.{n}") for j, n in enumerate(("QW", "QX", "QY", "QZ"))]
        t = [number(parts[5 + j], source, f"{where}.{n}") for j, n in enumerate(("TX", "TY", "TZ"))]
        try:
            cam_id = int(parts[8])
        except ValueError:
            raise fail(source, f"{where}.CAMERA_ID", f"expected an integer, got {short(parts[8])}") from None
        if cam_id not in cams:
            raise fail(source, f"{where}.CAMERA_ID", f"camera {cam_id} is not in cameras.txt")
        qn = float(np.linalg.norm(q))
        if abs(qn - 1.0) > 1e-3:
            raise fail(source, f"{where}.QW", f"expected a unit quaternion (QW QX QY QZ), norm is {qn:.6g}")
        world_to_cam = np.eye(4)
        world_to_cam[:3, :3], world_to_cam[:3, 3] = quaternion_matrix([q[1], q[2], q[3], q[0]]), t
        if cam_id not in seen:  # a camera seen in several images: the first one places it
            seen.add(cam_id)
            r = cams[cam_id]
            r.camera_to_vehicle = rigid_inverse(world_to_cam)
            r.name = " ".join(parts[9:]).rsplit(".", 1)[0] or r.name
        k += 2  # the image line and its points line
    names = [r.name for r in cams.values()]
    if len(set(names)) != len(names):
        for cam_id, r in cams.items():
            r.name = f"camera{cam_id}"


def write(records: Sequence[CameraRecord]) -> tuple[str, str]:
    """``(cameras.txt, images.txt)`` texts; one image per camera named ``NAME.png``."""
    cams = ["# Camera list with one line of data per camera:", "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]",
            f"# Number of cameras: {len(records)}"]
    imgs = ["# Image list with two lines of data per image:",
            "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME", "#   POINTS2D[] as (X, Y, POINT3D_ID)",
            f"# Number of images: {len(records)}, mean observations per image: 0"]
    for i, r in enumerate(records, start=1):
        p = dict(r.params)
        found = find_writer(COLMAP_MODELS, r.model, p)
        assert found is not None, r.model
        m, values = found
        values = [v + _PIXEL_ORIGIN if spec in ("cx", "cy") else v for spec, v in zip(m.params, values, strict=True)]
        cams.append(" ".join([str(i), str(m.tool), str(r.width), str(r.height), *(repr(float(v)) for v in values)]))
        w2c = rigid_inverse(r.camera_to_vehicle)
        q = quaternion_xyzw(w2c[:3, :3])
        vals = [q[3], q[0], q[1], q[2], *w2c[:3, 3]]
        imgs.append(" ".join([str(i), *(repr(float(v)) for v in vals), str(i), f"{r.name}.png"]))
        imgs.append("")
    return "\n".join(cams) + "\n", "\n".join(imgs) + "\n"
