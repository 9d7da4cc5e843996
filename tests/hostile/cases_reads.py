"""Hostile inputs about what is read, not only that it opens: file contents that lie about their
format, paths that are not regular files, numbers and ranges too large to hold, and the small
library edges (empty arrays, zero quaternions, a full disk)."""

from __future__ import annotations

import errno
import json
import os
from pathlib import Path

import numpy as np

from .corpus import FV_CALIBRATION, Case, edit_json, json_text

FRAME0 = Path("capture/frames/000000")
FACE = FRAME0 / "cameras/FV/front"
BUILD = "build {capture} {tmp}/out --frames 0 --no-bev"


def _as_jpeg(relative: Path):
    """Setup: the face image re-encoded as a JPEG under its ``.png`` name (same size and channels)."""

    def setup(tmp: Path) -> None:
        import OpenImageIO as oiio

        from jaxfish.io import read_image

        path = tmp / relative
        pixels = read_image(path)[..., :3]
        jpeg = tmp / "face.jpg"
        out = oiio.ImageOutput.create(str(jpeg))
        out.open(str(jpeg), oiio.ImageSpec(pixels.shape[1], pixels.shape[0], 3, oiio.UINT8))
        out.write_image(np.ascontiguousarray(pixels))
        out.close()
        os.replace(jpeg, path)

    return setup


def _fifo(relative: str | Path):
    """Setup: a FIFO (nobody writes to it: reading it would block forever) in place of a file."""

    def setup(tmp: Path) -> None:
        path = tmp / relative
        if path.exists():
            path.unlink()
        os.mkfifo(path)

    return setup


def _symlink_loop(relative: str | Path):
    def setup(tmp: Path) -> None:
        path = tmp / relative
        if path.exists():
            path.unlink()
        other = path.with_name(path.name + ".other")
        os.symlink(other, path)
        os.symlink(path, other)

    return setup


def _directory(relative: str | Path):
    def setup(tmp: Path) -> None:
        path = tmp / relative
        if path.exists():
            path.unlink()
        path.mkdir()

    return setup


def _actor(field: str, value):
    """Setup: actors.json of frame 0 with ``actors[1]``'s ``field`` (dotted, list index last) set."""

    def setup(tmp: Path) -> None:
        def edit(doc):
            target = doc["actors"][1]
            *keys, last = field.split(".")
            for k in keys:
                target = target[k]
            if last.isdigit():
                target[int(last)] = value
            else:
                target[last] = value

        edit_json(tmp / FRAME0 / "actors.json", edit)

    return setup


def _text_replace(relative: str | Path, old: str, new: str):
    def setup(tmp: Path) -> None:
        path = tmp / relative
        text = path.read_text()
        assert old in text, (path, old)
        json_text(path, text.replace(old, new, 1))

    return setup


def _calib(edit):
    def setup(tmp: Path) -> None:
        edit_json(tmp / "FV.json", edit)

    return setup


def _set(*path_and_value):
    *keys, value = path_and_value

    def edit(obj):
        for k in keys[:-1]:
            obj = obj[k]
        obj[keys[-1]] = value

    return edit


_SYN_T = "translation used in CARLA (CARLA reference)"


def _kb_calibration(width=1280, quaternion=None):
    """Setup: ``{tmp}/kb.json``, a Kannala-Brandt calibration (refit's file layout)."""

    def setup(tmp: Path) -> None:
        src = json.loads(FV_CALIBRATION.read_text())
        ext = src["extrinsic"]
        if quaternion is not None:
            ext = {**ext, "quaternion": quaternion}
        doc = {"name": "FV", "extrinsic": ext,
               "intrinsic": {"model": "kannala_brandt", "fx": 330.0, "fy": 330.0, "cx": 640.0, "cy": 480.0,
                             "k1": 0.0, "k2": 0.0, "k3": 0.0, "k4": 0.0, "width": width, "height": 966}}
        (tmp / "kb.json").write_text(json.dumps(doc).replace('"HUGE"', "1" + "0" * 400))

    return setup


# ---------------------------------------------------------------- library calls


def _fisheye():
    from jaxfish.io import load_calibration

    return load_calibration(FV_CALIBRATION).camera


def _kb():
    import jax.numpy as jnp

    from jaxfish.cameras import KannalaBrandt

    return KannalaBrandt(330.0, 330.0, 640.0, 480.0, jnp.array([0.05, 0.01, 0.0, 0.0]), width=1280, height=966)


def _empty_rays(result) -> bool:
    rays, valid = result
    return rays.shape == (0, 3) and valid.shape == (0,)


def _resample_zero_channels(_tmp: Path):
    import jaxfish as jf
    from jaxfish.reprojection import CubeRig, build_lut, resample_bilinear

    lut = build_lut(CubeRig(8), jf.resize_fisheye(_fisheye(), 16, 12))
    return resample_bilinear(np.zeros((5, 8, 8, 0), np.uint8), lut)


def _enospc(tmp: Path):
    from jaxfish.io._atomic import atomic_path

    with atomic_path(tmp / "out" / "depth.npy") as part:
        part.write_bytes(b"\x93NUMPY")
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))  # what a write to a full disk raises


def _zero_quaternion(_tmp: Path):
    from jaxfish import Pose

    return Pose.from_quaternion_xyzw([0.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0])


def _load_calibration(name: str):
    def call(tmp: Path):
        from jaxfish.io import load_calibration

        return load_calibration(tmp / name)

    return call


def _npy_claiming(relative: Path, rows: int):
    """Setup: the ``.npy`` at ``relative`` with a header claiming ``rows`` rows (its data unchanged)."""

    def setup(tmp: Path) -> None:
        import io

        path = tmp / relative
        a = np.load(path)
        head = io.BytesIO()
        np.lib.format.write_array_header_1_0(head, {"descr": np.lib.format.dtype_to_descr(a.dtype),
                                                    "fortran_order": False, "shape": (rows, *a.shape[1:])})
        path.write_bytes(head.getvalue() + a.tobytes())

    return setup


CASES = [
    # File contents that lie about their format: a lossy JPEG read as labels or encoded depth.
    Case("reads-build-semantic-face-jpeg", BUILD, setup=_as_jpeg(FACE / "semantic_curr.png"), exit=1,
         says=("semantic_curr.png", "expected a lossless PNG file, found JPEG data")),
    Case("reads-build-depth-face-jpeg", BUILD, setup=_as_jpeg(FACE / "depth_prev.png"), exit=1,
         says=("depth_prev.png", "expected a lossless PNG file")),
    Case("reads-build-rgb-face-jpeg-is-read", BUILD, setup=_as_jpeg(FACE / "rgb_curr.png"), exit=0),
    # A .npy header claiming far more data than the file holds: read as truncated, never allocated.
    Case("reads-build-lidar-npy-huge-header", BUILD, setup=_npy_claiming(FRAME0 / "lidar.npy", 10**12), exit=1,
         says=("lidar.npy", "truncated .npy", "the file holds")),
    Case("reads-build-dvs-npy-huge-header", BUILD, setup=_npy_claiming(FACE / "dvs.npy", 10**12), exit=1,
         says=("dvs.npy", "truncated .npy")),
    # Paths that are not regular files: refused before anything blocks reading them.
    Case("reads-build-face-fifo", BUILD, setup=_fifo(FACE / "depth_curr.png"), exit=1,
         says=("depth_curr.png", "FIFO")),
    Case("reads-build-actors-fifo", BUILD, setup=_fifo(FRAME0 / "actors.json"), exit=1,
         says=("actors.json", "FIFO")),
    Case("reads-build-capture-calibration-fifo", BUILD, setup=_fifo("capture/calibration/FV.json"),
         says=("FV.json", "FIFO"), absent=("{tmp}/out",)),
    Case("reads-build-capture-json-directory", BUILD, setup=_directory("capture/capture.json"),
         says=("capture.json", "is a directory"), absent=("{tmp}/out",)),
    Case("reads-convert-calibration-fifo", "convert {tmp}/pipe.json --to kb --out {tmp}/o.json",
         setup=_fifo("pipe.json"), says=("pipe.json", "FIFO"), absent=("{tmp}/o.json",)),
    Case("reads-convert-calibration-directory", "convert {tmp}/dir.json --to kb --out {tmp}/o.json",
         setup=_directory("dir.json"), says=("dir.json", "is a directory"), absent=("{tmp}/o.json",)),
    Case("reads-convert-calibration-symlink-loop", "convert {tmp}/loop.json --to kb --out {tmp}/o.json",
         setup=_symlink_loop("loop.json"), says=("loop.json", "symbolic links"), absent=("{tmp}/o.json",)),
    Case("reads-lib-calibration-directory", call=_load_calibration("dir.json"), setup=_directory("dir.json"),
         says=("dir.json", "is a directory")),
    Case("reads-lib-calibration-missing", call=_load_calibration("nope.json"), raises=FileNotFoundError,
         says=("nope.json", "not found")),
    # Ranges checked against the capture before they are expanded.
    Case("reads-build-frames-billion", "build {capture} {tmp}/out --frames 0-999999999",
         says=("--frames", "2, 3, 4, 5, 6 ... not in", "capture.json", "its frames: 0-1"), absent=("{tmp}/out",)),
    Case("reads-build-frames-huge-number", "build {capture} {tmp}/out --frames 0," + "9" * 5000,
         says=("--frames",), absent=("{tmp}/out",)),
    Case("reads-bev-frames-billion", "bev {capture} --out {tmp}/bev --frames 0-999999999",
         says=("--frames", "not in the capture"), absent=("{tmp}/bev",)),
    # Numbers too large: named by file and field.
    Case("reads-build-capture-json-int-5000-digits", BUILD,
         setup=_text_replace("capture/capture.json", '"seed": 1', '"seed": ' + "7" * 5000),
         says=("capture.json", "field 'seed'", "an integer of 5000 digits"), absent=("{tmp}/out",)),
    Case("reads-build-ego-int-5000-digits", BUILD,
         setup=_text_replace(FRAME0 / "ego.json", '"velocity": [', '"velocity": [' + "9" * 5000 + ", "), exit=1,
         says=("ego.json", "field 'velocity[0]'", "5000 digits")),
    Case("reads-build-face-size-above-limit", BUILD,
         setup=lambda tmp: edit_json(tmp / "capture/capture.json", _set("face_size", 10**9)),
         says=("capture.json", "face_size", "65536"), absent=("{tmp}/out",)),
    Case("reads-convert-quaternion-10e400", "convert {calib} --to kb --out {tmp}/o.json",
         setup=_calib(lambda c: c["extrinsic"]["quaternion"].__setitem__(0, 10**400)),
         says=("FV.json", "extrinsic.quaternion[0]", "401 digits"), absent=("{tmp}/o.json",)),
    Case("reads-convert-translation-10e400", "convert {calib} --to kb --out {tmp}/o.json",
         setup=_calib(lambda c: c["extrinsic"][_SYN_T].__setitem__(2, -(10**400))),
         says=("FV.json", f"extrinsic.{_SYN_T}[2]", "401 digits"), absent=("{tmp}/o.json",)),
    Case("reads-convert-k1-1e400-literal", "convert {calib} --to kb --out {tmp}/o.json",
         setup=_text_replace("FV.json", "341.725", "1e400"), says=("FV.json", "intrinsic.k1", "1e400"),
         absent=("{tmp}/o.json",)),
    Case("reads-convert-kb-quaternion-10e400", "convert {tmp}/kb.json --to radial_poly --out {tmp}/o.json",
         setup=_kb_calibration(quaternion=["HUGE", 0, 0, 1]),
         says=("kb.json", "extrinsic.quaternion[0]", "401 digits"), absent=("{tmp}/o.json",)),
    Case("reads-convert-width-1e12", "convert {calib} --to kb --out {tmp}/o.json",
         setup=_calib(_set("intrinsic", "width", 1e12)),
         says=("FV.json", "intrinsic.width", "65536"), absent=("{tmp}/o.json",)),
    Case("reads-convert-kb-width-1e12", "convert {tmp}/kb.json --to radial_poly --out {tmp}/o.json",
         setup=_kb_calibration(width=1e12), says=("kb.json", "intrinsic.width", "65536"), absent=("{tmp}/o.json",)),
    Case("reads-cube2fisheye-width-1e12", "cube2fisheye --faces {capture}/frames/000000/cameras/FV --calibration {calib} "
         "--out {tmp}/o.png", setup=_calib(_set("intrinsic", "width", 1e12)), says=("FV.json", "intrinsic.width"),
         absent=("{tmp}/o.png",)),
    Case("reads-cube2fisheye-label-face-jpeg", "cube2fisheye --faces {capture}/frames/000000/cameras/FV --calibration "
         "{calib} --kind label --out {tmp}/o.png", setup=_as_jpeg(FACE / "semantic_curr.png"),
         says=("semantic_curr.png", "expected a lossless PNG file, found JPEG data"), absent=("{tmp}/o.png",)),
    Case("reads-cube2fisheye-rgb-face-jpeg-is-read", "cube2fisheye --faces {capture}/frames/000000/cameras/FV "
         "--calibration {calib} --kind rgb --out {tmp}/o.png", setup=_as_jpeg(FACE / "rgb_curr.png"), exit=0),
    Case("reads-build-actor-id-2-70", BUILD, setup=_actor("id", 2**70), exit=1,
         says=("actors.json", "actors[1].id", "65535")),
    Case("reads-build-actor-id-70000", BUILD, setup=_actor("id", 70000), exit=1,
         says=("actors.json", "actors[1].id", "actor id 70000 above 65535")),
    Case("reads-build-actor-location-10e400", BUILD, setup=_actor("transform.location.0", 10**400), exit=1,
         says=("actors.json", "actors[1].transform.location[0]", "401 digits")),
    # Small library edges.
    Case("reads-woodscape-unproject-empty", call=lambda _t: _fisheye().unproject(np.zeros((0, 2))), raises=None,
         check=_empty_rays),
    Case("reads-kannala-brandt-unproject-empty", call=lambda _t: _kb().unproject(np.zeros((0, 2))), raises=None,
         check=_empty_rays),
    Case("reads-resample-bilinear-zero-channels", call=_resample_zero_channels, raises=None,
         check=lambda r: r[0].shape == (12, 16, 0) and r[1].shape == (12, 16)),
    Case("reads-pose-zero-quaternion", call=_zero_quaternion, raises=ValueError, says=("norm 0",)),
    Case("reads-atomic-write-no-space", call=_enospc, raises=OSError,
         says=("{tmp}/out/depth.npy", "No space left on device")),
]
