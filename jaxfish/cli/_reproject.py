"""``jaxfish cube2fisheye`` and ``jaxfish reproject``: LUT-based reprojection of image files.

Outputs follow their extension: ``.png`` (uint8 / uint16 values as read), ``.exr`` (float32; float
input stays float, integer values are stored as float32 numbers) or ``.npy`` (the array as
computed). Pixels outside the lens domain (or not seen by the source) are 0. Depth is written as
float32 Euclidean range in metres along each output ray (sky/far stays 1000), so ``.png`` is refused
for depth. Every error is one message naming the file, a non-zero exit, and no output file.

Both commands share one sample budget, `MAX_OUTPUT_SAMPLES`: the output's width x height x
``--supersample``² must not exceed 16384 x 16384; a larger output (from ``--width``/``--height``,
the fisheye calibration of ``cube2fisheye`` or a ``--target-calibration``) is refused, naming where
its size came from, before any image is read; so is an output whose estimated peak memory
(`BYTES_PER_SAMPLE`, `CUBE_BYTES_PER_SAMPLE`) exceeds the memory available at the start.
"""

from __future__ import annotations

import math
from pathlib import Path

import typer

from ..cameras import MAX_IMAGE_SIDE
from ._app import app, check_outputs, fail, say, warn_undersampled

_KINDS = ("rgb", "label", "depth")
_OUT_EXTS = (".png", ".exr", ".npy")
_FACE_EXTS = (".png", ".exr")

MAX_OUTPUT_SAMPLES = 16384 * 16384
"""The sample budget of `jaxfish reproject` and `jaxfish cube2fisheye`: the output image's width x
height x ``--supersample``² (the rays its LUT holds, 16384 x 16384 at ``--supersample 1``) must
not exceed it. Both commands refuse a larger output before reading any image: its LUT and
temporaries (tens of bytes per sample) would exhaust memory, and XLA aborts the process on a
buffer it cannot allocate."""


BYTES_PER_SAMPLE = 80
"""Peak memory of `jaxfish reproject` per output sample (its LUT, rays and temporaries), bytes:
measured 79–80 from 2048² to 8192² pinhole outputs of an RGB, label or depth fisheye (the same
for each kind), over a base of about 0.4 GB."""
BASE_BYTES = 400 * 2**20
"""`jaxfish reproject`'s memory besides the samples' (the runtime, the input image), bytes."""
CUBE_BYTES_PER_SAMPLE = 120
"""Peak memory of `jaxfish cube2fisheye` per fisheye sample (pixel x ``--supersample``²: the
face lookups, rays and temporaries), bytes: measured 112–115 for RGB, label and depth faces at
``--supersample`` 4 and 8 of a 1280 x 966 fisheye."""
CUBE_BASE_BYTES = 650 * 2**20
"""`jaxfish cube2fisheye`'s memory besides the samples' (the runtime, five decoded 1152-px
faces), bytes."""


def _available_memory() -> int | None:
    """The memory the kernel can give this process now (``MemAvailable`` of ``/proc/meminfo``),
    bytes; None where it cannot be read (not Linux)."""
    try:
        with open("/proc/meminfo", encoding="ascii") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        return None
    return None


def _check_budget(width: int, height: int, supersample: int, origin: str, *, per_sample: int = BYTES_PER_SAMPLE,
                  base: int = BASE_BYTES) -> None:
    """Refuse an output of ``width x height`` pixels at ``supersample``² rays per pixel beyond
    `MAX_OUTPUT_SAMPLES`, or one whose estimated peak memory (``per_sample`` bytes per sample over
    ``base``: `reproject`'s by default) exceeds the memory available now; ``origin`` names where
    the size came from (options or file and fields)."""
    samples = width * height * supersample * supersample
    if samples > MAX_OUTPUT_SAMPLES:
        raise fail(f"{origin} {width}x{height}: more than {MAX_OUTPUT_SAMPLES} samples at --supersample {supersample} "
                   f"(width x height x {supersample} x {supersample} = {samples}; at most 16384 x 16384 at "
                   "--supersample 1); lower --supersample or the output size")
    if width > MAX_IMAGE_SIDE or height > MAX_IMAGE_SIDE:
        raise fail(f"{origin} {width}x{height}: at most {MAX_IMAGE_SIDE} pixels per side")
    need, available = base + samples * per_sample, _available_memory()
    if available is not None and need > available:
        raise fail(f"{origin} {width}x{height} at --supersample {supersample}: needs about {need / 2**30:.1f} GiB "
                   f"({per_sample} bytes per sample), {available / 2**30:.1f} GiB of memory is available; "
                   "lower --supersample or the output size")


def _check_options(kind: str, out: Path, supersample: int) -> None:
    if kind not in _KINDS:
        raise fail(f"--kind must be one of {', '.join(_KINDS)}, got {kind!r}")
    ext = out.suffix.lower()
    if ext not in _OUT_EXTS:
        raise fail(f"{out}: unsupported output extension {ext!r} (use .png, .exr or .npy)")
    if kind == "depth" and ext == ".png":
        raise fail(f"{out}: depth is float metres (1000 = sky); write .exr or .npy")
    if supersample < 1 or supersample > 16:
        raise fail(f"--supersample must be in 1..16, got {supersample}")


def _prepare(images, kind: str, names: list[str]):
    """Stacked source array for a kind, from per-face (H, W, C) arrays; raises with the file name."""
    import numpy as np

    from .._errors import ImageError

    for name, a in zip(names, images, strict=True):  # name the first file that differs from the first one
        if a.dtype != images[0].dtype:
            raise ImageError(f"{name}: pixel type {a.dtype}, but {names[0]} is {images[0].dtype}: "
                             "all inputs must share one pixel type")
        if a.shape != images[0].shape:
            raise ImageError(f"{name}: {a.shape[1]}x{a.shape[0]} with {a.shape[2]} channel(s), but {names[0]} is "
                             f"{images[0].shape[1]}x{images[0].shape[0]} with {images[0].shape[2]}: "
                             "all inputs must share one size and channel count")
    x = np.stack(images)
    if kind == "label":
        if not np.issubdtype(x.dtype, np.integer):
            raise ImageError(f"{names[0]}: label images must be integer (index PNG), got {x.dtype}")
        return x[..., 0]  # single-channel index, or CARLA's semantic tag in the red channel
    if kind == "depth":
        if not np.issubdtype(x.dtype, np.floating) or x.shape[-1] != 1:
            raise ImageError(
                f"{names[0]}: depth must be a single-channel float EXR in metres, got {x.dtype} with {x.shape[-1]} channels"
            )
        return x[..., 0].astype(np.float32)
    return x


_CAPTURE_STEMS = {"rgb": "rgb", "label": "semantic", "depth": "depth"}
"""--kind -> the file stem it reads in a capture's face directory (``FACE/{stem}_{instant}.png``)."""


def _decode_capture(kind: str, bgra):
    """CARLA's raw BGRA buffer of a capture face -> what ``--kind`` reads from ordinary faces."""
    from ..io import bgra_to_rgb, decode_depth, decode_semantic

    if kind == "rgb":
        return bgra_to_rgb(bgra)
    return (decode_semantic if kind == "label" else decode_depth)(bgra)[..., None]


def _resample(x, lut, kind: str, *, planar: bool):
    import jax.numpy as jnp
    import numpy as np

    fns = _functions()
    fn = fns["rgb"] if kind == "rgb" else fns["label"] if kind == "label" else fns["depth_planar" if planar else "depth_range"]
    values, _ = fn(jnp.asarray(x), lut)
    return np.asarray(values)


def _jitted():
    import jax

    from ..reprojection import build_lut, resample_bilinear, resample_depth, resample_nearest

    return {
        "lut": jax.jit(build_lut, static_argnames=("supersample", "dtype")),
        "rgb": jax.jit(resample_bilinear),
        "label": jax.jit(resample_nearest),
        "depth_planar": jax.jit(lambda d, lut: resample_depth(d, lut, planar=True)),
        "depth_range": jax.jit(lambda d, lut: resample_depth(d, lut, planar=False)),
    }


_JIT: dict = {}


def _functions() -> dict:
    if not _JIT:
        _JIT.update(_jitted())
    return _JIT


def _write(out: Path, values, kind: str) -> None:
    import numpy as np

    from .._errors import ImageError
    from ..io import atomic_path, write_image

    ext = out.suffix.lower()
    if ext == ".npy":
        with atomic_path(out) as tmp:
            with open(tmp, "wb") as f:
                np.save(f, values)
        return
    if ext == ".exr":
        write_image(out, values.astype(np.float32) if values.dtype != np.float16 else values)
        return
    if values.dtype not in (np.uint8, np.uint16):
        raise ImageError(f"{out}: PNG stores uint8/uint16, the {kind} result is {values.dtype} (write .exr or .npy)")
    write_image(out, values)


def _run(body) -> None:
    from .._errors import JaxfishError

    try:
        body()
    except (JaxfishError, FileNotFoundError, IsADirectoryError, PermissionError) as e:
        raise fail(str(e)) from e


@app.command("cube2fisheye")
def cube2fisheye(
    faces: Path = typer.Option(..., "--faces", help="Directory holding front, left, right, top, bottom (.png or .exr, all S x S; back is optional), "
                               "or a capture's camera directory (CAPTURE/frames/N/cameras/FV)."),
    calibration: Path = typer.Option(..., "--calibration", "-c", help="WoodScape/SynWoodScape calibration JSON of the fisheye."),
    out: Path = typer.Option(..., "--out", "-o", help="Output file: .png, .exr or .npy."),
    kind: str = typer.Option("rgb", "--kind", help="rgb (bilinear), label (nearest / majority) or depth (planar z -> range)."),
    supersample: int = typer.Option(1, "--supersample", help="N x N rays per fisheye pixel (rgb: mean, label: majority, depth: centre), 1..16; "
                                    "the calibration's width x height x N x N must not exceed 268435456 (16384 x 16384 x 1 x 1)."),
    errata: bool = typer.Option(False, "--errata", help="Apply the SynWoodScape calibration errata when loading."),
    instant: str = typer.Option("curr", "--instant", help="With a capture's camera directory: curr (t) or prev (t-1)."),
) -> None:
    """Make a fisheye image (rgb, label or depth) from CARLA's perspective cube faces."""
    check_outputs(out=out)
    _check_options(kind, out, supersample)
    if instant not in ("curr", "prev"):
        raise fail(f"--instant must be curr or prev, got {instant!r}")

    def body():
        import jax.numpy as jnp

        from .._errors import ImageError
        from ..io import load_calibration, read_image
        from ..reprojection import FIVE_FACES, CubeRig

        if not faces.is_dir():
            raise FileNotFoundError(f"{faces}: faces directory not found")
        capture = (faces / FIVE_FACES[0]).is_dir()  # a capture camera: FACE/{rgb,semantic,depth}_{instant}.png
        stem = _CAPTURE_STEMS[kind]

        def find(name):
            if capture:
                p = faces / name / f"{stem}_{instant}.png"
                return p if p.is_file() else None
            hits = [faces / f"{name}{e}" for e in _FACE_EXTS if (faces / f"{name}{e}").is_file()]
            if len(hits) > 1:
                raise ImageError(f"{faces}: face {name!r} exists as both {hits[0].name} and {hits[1].name}")
            return hits[0] if hits else None

        paths = {name: find(name) for name in FIVE_FACES + ("back",)}
        missing = [n for n in FIVE_FACES if paths[n] is None]
        if missing:
            expected = [f"{n}/{stem}_{instant}.png" if capture else f"{n}.png|.exr" for n in missing]
            raise ImageError(
                f"{faces}: missing cube face{'s' if len(missing) > 1 else ''} {', '.join(missing)} "
                f"(expected {', '.join(expected)})"
            )
        names = FIVE_FACES + (("back",) if paths["back"] is not None else ())
        calib = load_calibration(calibration, apply_errata=errata)
        _check_budget(calib.camera.width, calib.camera.height, supersample, f"{calibration}: intrinsic.width/height",
                      per_sample=CUBE_BYTES_PER_SAMPLE, base=CUBE_BASE_BYTES)
        images, size = [], None
        for name in names:
            img = read_image(paths[name], lossless=kind != "rgb" and paths[name].suffix.lower() == ".png")
            if capture:  # CARLA's raw BGRA buffers (docs/capture_layout.md)
                try:
                    img = _decode_capture(kind, img)
                except ImageError as e:
                    raise ImageError(f"{paths[name]}: {e}") from None
            if img.shape[0] != img.shape[1]:
                raise ImageError(f"{paths[name]}: cube faces must be square, got {img.shape[1]}x{img.shape[0]}")
            if size is not None and img.shape[0] != size[1]:
                raise ImageError(
                    f"{paths[name]}: face size {img.shape[0]}x{img.shape[0]} differs from {size[0]} ({size[1]}x{size[1]})"
                )
            size = size or (str(paths[name]), img.shape[0])
            images.append(img)
        x = _prepare(images, kind, [str(paths[n]) for n in names])
        warn_undersampled(size[1], {calib.name: calib.camera})
        fns = _functions()
        rig = CubeRig(size[1], faces=names, dtype=jnp.float32)
        lut = fns["lut"](rig, calib.camera.astype(jnp.float32), supersample=supersample, dtype=jnp.float32)
        values = _resample(x, lut, kind, planar=True)
        _write(out, values, kind)
        say(
            f"{calib.name}: {len(names)} faces of {size[1]} px -> {calib.camera.width}x{calib.camera.height} {kind} "
            f"({supersample}x{supersample} samples per pixel), wrote {out}")

    _run(body)


def _rotation(yaw_deg: float, pitch_deg: float, roll_deg: float):
    """Target -> source rotation of a view turned by yaw (right +), pitch (up +), roll (clockwise +)."""
    import numpy as np

    y, p, r = (math.radians(a) for a in (yaw_deg, pitch_deg, roll_deg))
    ry = np.array([[math.cos(y), 0, math.sin(y)], [0, 1, 0], [-math.sin(y), 0, math.cos(y)]])
    rx = np.array([[1, 0, 0], [0, math.cos(p), -math.sin(p)], [0, math.sin(p), math.cos(p)]])
    rz = np.array([[math.cos(r), -math.sin(r), 0], [math.sin(r), math.cos(r), 0], [0, 0, 1]])
    return ry @ rx @ rz


@app.command("reproject")
def reproject(
    image: Path = typer.Argument(..., help="Fisheye image (.png/.exr) taken with the calibration's camera."),
    calibration: Path = typer.Option(..., "--calibration", "-c", help="Calibration JSON of the input fisheye (any lens model)."),
    out: Path = typer.Option(..., "--out", "-o", help="Output file: .png, .exr or .npy."),
    to: str = typer.Option("pinhole", "--to", help="Target model: pinhole, equirectangular, cylindrical or fisheye."),
    width: int | None = typer.Option(None, "--width", help="Target width, at most 65536 (default: the input's)."),
    height: int | None = typer.Option(None, "--height", help="Target height, at most 65536 (default: the input's)."),
    fov: float | None = typer.Option(None, "--fov", help="Horizontal field of view in degrees (pinhole 90, panoramas 180)."),
    yaw: float = typer.Option(0.0, "--yaw", help="Turn the target view right by this many degrees."),
    pitch: float = typer.Option(0.0, "--pitch", help="Turn the target view up by this many degrees."),
    roll: float = typer.Option(0.0, "--roll", help="Roll the target view clockwise by this many degrees."),
    target_calibration: Path | None = typer.Option(None, "--target-calibration", help="Calibration JSON of the target, any lens model (--to fisheye)."),
    kind: str = typer.Option("rgb", "--kind", help="rgb (bilinear), label (nearest) or depth (range in metres, kept as range)."),
    supersample: int = typer.Option(1, "--supersample", help="N x N rays per output pixel, 1..16; the output's "
                                    "width x height x N x N must not exceed 268435456 (16384 x 16384 x 1 x 1)."),
) -> None:
    """Reproject a fisheye image to another camera model (e.g. rectify it to a pinhole view)."""
    check_outputs(out=out)
    _check_options(kind, out, supersample)
    if to not in ("pinhole", "equirectangular", "cylindrical", "fisheye"):
        raise fail(f"--to must be pinhole, equirectangular, cylindrical or fisheye, got {to!r}")
    if to == "fisheye" and target_calibration is None:
        raise fail("--to fisheye needs --target-calibration")
    for name, angle in (("--yaw", yaw), ("--pitch", pitch), ("--roll", roll)):
        if not math.isfinite(angle):
            raise fail(f"{name} must be a finite number of degrees, got {angle}")
    for name, size in (("--width", width), ("--height", height)):
        if size is not None and size <= 0:
            raise fail(f"{name} must be a positive number of pixels, got {size}")
    if width is not None and height is not None:
        _check_budget(width, height, supersample, "--width/--height")
    for name, size in (("--width", width), ("--height", height)):
        if size is not None and size > MAX_IMAGE_SIDE:
            raise fail(f"{name} {size}: at most {MAX_IMAGE_SIDE} pixels per side")

    def body():
        import jax.numpy as jnp

        from .. import Cylindrical, Equirectangular, Pinhole, WoodScapeFisheye
        from .._errors import ImageError
        from ..io import load_camera_calibration, read_image

        calib = load_camera_calibration(calibration)  # any lens model (WoodScape files included)
        cam = calib.camera.astype(jnp.float32)
        w = width or cam.width
        h = height or cam.height
        origin = "--width/--height" if width or height else f"{calibration}: intrinsic.width/height"
        target = None
        if to == "fisheye":
            target = load_camera_calibration(target_calibration).camera.astype(jnp.float32)
            if width or height:
                if not isinstance(target, WoodScapeFisheye):
                    raise ImageError(f"{target_calibration}: --width/--height apply to a radial_poly target only "
                                     "(its principal point is an offset from the image centre); omit them to use "
                                     "the target calibration's own size")
            else:
                w, h = target.width, target.height
                origin = f"{target_calibration}: intrinsic.width/height"
        _check_budget(w, h, supersample, origin)
        img = read_image(image, lossless=kind != "rgb" and image.suffix.lower() == ".png")
        if (img.shape[1], img.shape[0]) != (cam.width, cam.height):
            raise ImageError(
                f"{image}: image is {img.shape[1]}x{img.shape[0]} but {calibration} describes {cam.width}x{cam.height} "
                "(resize the calibration with Calibration.resize)"
            )
        if to == "pinhole":
            f_deg = 90.0 if fov is None else fov
            if not 0 < f_deg < 180:
                raise ImageError(f"--fov must be in (0, 180) for a pinhole, got {f_deg}")
            target = Pinhole.from_fov(w, h, f_deg, dtype=jnp.float32)
        elif to in ("equirectangular", "cylindrical"):
            f_rad = math.radians(180.0 if fov is None else fov)
            if not 0 < f_rad <= 2 * math.pi:
                raise ImageError(f"--fov must be in (0, 360] for a panorama, got {fov}")
            lon = (-f_rad / 2, f_rad / 2)
            if to == "equirectangular":
                half_lat = min(f_rad * h / w / 2, math.pi / 2)
                target = Equirectangular(width=w, height=h, lon_range=lon, lat_range=(-half_lat, half_lat), dtype=jnp.float32)
            else:
                target = Cylindrical(width=w, height=h, lon_range=lon, dtype=jnp.float32)
        elif width or height:
            target = target.__class__(target.k, width=w, height=h, cx_offset=target.cx_offset,
                                      cy_offset=target.cy_offset, aspect_ratio=target.aspect_ratio)
        x = _prepare([img], kind, [str(image)])
        fns = _functions()
        r = jnp.asarray(_rotation(yaw, pitch, roll), jnp.float32)
        lut = fns["lut"](cam, target, target_to_source=r, supersample=supersample, dtype=jnp.float32)
        values = _resample(x, lut, kind, planar=False)
        _write(out, values, kind)
        say(f"{image} ({calib.name}) -> {to} {w}x{h} {kind}, wrote {out}")

    _run(body)
