"""Benchmark: PNG encode and decode, OpenImageIO (libpng) against jaxfish's codec (`jaxfish.io._png`).

Run: ``uv run python scripts/bench_codecs.py [--repeats 15] [--face-size 768]``

One thread (OpenImageIO's ``threads`` attribute 1; ISA-L, zlib and NumPy are single-threaded here),
CPU milliseconds per image (the process's CPU time: on a machine shared with other jobs, wall time
measures the queue for a core), median over ``--repeats`` after one warm-up. jaxfish's codec is timed on
bytes in memory, OpenImageIO on a file in a temporary directory (its Python API writes files; the
file system's share is small next to the encoding). Images:

- ``real RGB``: the real SynWoodScape front frame in ``../shared/samples`` (1280 x 966 x 3, rendered,
  noisy like CARLA output);
- ``label map``: a 1280 x 966 uint8 class map made from that frame (its blurred luminance cut into 10
  bands: piecewise-constant regions with curved borders, like ``semantic_annotations/gtLabels``);
- ``KITTI flow``: 1280 x 966 x 3 uint16, a smooth rotation-plus-zoom flow field written by
  `jaxfish.io.write_kitti_flow`'s encoding.

Encoders: OpenImageIO at level 1 with the Up filter (the settings jaxfish passed to it), jaxfish's
codec at level 1 (ISA-L) and with its zlib fallback. Decoders: OpenImageIO, jaxfish's `decode_png`
(inflate + running row sum), pyspng; each reads jaxfish's own file. ``B/px``: compressed bytes
per pixel. Then the capture writer's PNG encoding of one frame (`jaxfish.io._capture.write_images`:
4 cameras x 5 cube faces x rgb, depth, semantic and instance BGRA PNGs at t; the t-1 images are
copied from the previous frame's files) at ``--face-size`` with the real frame's texture, CPU
seconds, once for each encoder (the BGRA conversions included).
"""

from __future__ import annotations

import argparse
import os
import statistics
import tempfile
import time
import zlib
from pathlib import Path

import numpy as np
import OpenImageIO as oiio

ROOT = Path(__file__).resolve().parents[1]
SAMPLE = ROOT.parent / "shared" / "samples" / "synwoodscape_FV_rgb.png"


def oiio_encode(path: Path, a: np.ndarray, level: int = 1) -> None:
    """A PNG by OpenImageIO/libpng: zlib ``level``, Up filter (libpng ``PNG_FILTER_UP``)."""
    a = a if a.ndim == 3 else a[..., None]
    out = oiio.ImageOutput.create(str(path))
    spec = oiio.ImageSpec(a.shape[1], a.shape[0], a.shape[2], oiio.UINT16 if a.dtype == np.uint16 else oiio.UINT8)
    spec.attribute("png:compressionLevel", level)
    spec.attribute("png:filter", 0x20)
    spec.attribute("oiio:UnassociatedAlpha", 1)
    out.open(str(path), spec)
    out.write_image(np.ascontiguousarray(a))
    out.close()


def oiio_decode(path: Path) -> np.ndarray:
    inp = oiio.ImageInput.open(str(path))
    try:
        return inp.read_image(0, 0, 0, inp.spec().nchannels, oiio.UNKNOWN)
    finally:
        inp.close()


def median_ms(fn, repeats: int) -> float:
    fn()  # warm-up
    times = []
    for _ in range(repeats):
        start = time.process_time()
        fn()
        times.append(time.process_time() - start)
    return 1e3 * statistics.median(times)


def images() -> dict[str, np.ndarray]:
    import cv2

    from jaxfish.io import read_image

    rgb = read_image(SAMPLE)
    lum = cv2.GaussianBlur(rgb.mean(axis=2).astype(np.float32), (0, 0), 6)
    labels = np.clip(lum / 256 * 10, 0, 9).astype(np.uint8)
    h, w = labels.shape
    y, x = np.mgrid[:h, :w].astype(np.float64)
    u, v = 0.02 * (x - w / 2) - 0.01 * (y - h / 2), 0.01 * (x - w / 2) + 0.02 * (y - h / 2)
    flow = np.empty((h, w, 3), np.uint16)
    flow[..., 0] = np.rint(u * 64) + 2**15
    flow[..., 1] = np.rint(v * 64) + 2**15
    flow[..., 2] = 1
    return {"real RGB": rgb, "label map": labels, "KITTI flow": flow}


def codec_table(repeats: int, tmp: Path) -> list[str]:
    from jaxfish.io import _png

    rows = ["| image | codec | encode CPU ms | decode CPU ms | B/px |", "|---|---|---|---|---|"]
    for name, a in images().items():
        a3 = a if a.ndim == 3 else a[..., None]
        px = a.shape[0] * a.shape[1]
        path = tmp / "oiio.png"
        enc = median_ms(lambda a=a, path=path: oiio_encode(path, a), repeats)
        dec = median_ms(lambda path=path: oiio_decode(path), repeats)
        rows.append(f"| {name} | OpenImageIO (libpng level 1 + Up) | {enc:.1f} | {dec:.1f} | {path.stat().st_size / px:.2f} |")
        data = _png.encode_png(a3)
        assert np.array_equal(_png.decode_png(data), a3)
        enc = median_ms(lambda a3=a3: _png.encode_png(a3), repeats)
        dec = median_ms(lambda data=data: _png.decode_png(data), repeats)
        raw = a3.shape[0] * (a3.shape[1] * a3.shape[2] * a3.dtype.itemsize + 1)
        libdeflate = _png.uses_libdeflate(raw, len(_png.parse_png(data).idat))
        inflate = "libdeflate" if libdeflate else _png.deflate_name()
        rows.append(f"| {name} | jaxfish ({_png.deflate_name()} level 1 + Up; {inflate} inflate + row sum) | {enc:.1f} | "
                    f"{dec:.1f} | {len(data) / px:.2f} |")
        if libdeflate:
            kept, _png._libdeflate = _png._libdeflate, None
            try:
                dec = median_ms(lambda data=data: _png.decode_png(data), repeats)
            finally:
                _png._libdeflate = kept
            rows.append(f"| {name} | jaxfish decode without libdeflate ({_png.deflate_name()} inflate) | | {dec:.1f} | |")
        if a.dtype == np.uint8:
            import pyspng

            dec = median_ms(lambda data=data: pyspng.load(data), repeats)
            rows.append(f"| {name} | pyspng decode of jaxfish's file | | {dec:.1f} | |")
        isal, libdeflate_module = _png._isal_zlib, _png._libdeflate
        _png._isal_zlib = _png._libdeflate = None
        try:
            zdata = _png.encode_png(a3)
            enc = median_ms(lambda a3=a3: _png.encode_png(a3), max(3, repeats // 3))
            dec = median_ms(lambda zdata=zdata: _png.decode_png(zdata), max(3, repeats // 3))
        finally:
            _png._isal_zlib, _png._libdeflate = isal, libdeflate_module
        rows.append(f"| {name} | jaxfish without isal and libdeflate (zlib {zlib.ZLIB_RUNTIME_VERSION} level 1 + Up) | {enc:.1f} | "
                    f"{dec:.1f} | {len(zdata) / px:.2f} |")
    return rows


def capture_frame(face_size: int, tmp: Path) -> list[str]:
    """Seconds to write one frame's cube-face PNGs at t (20 faces x 4 BGRA PNGs) with each encoder."""
    from jaxfish.io import _images
    from jaxfish.io._capture import CameraImages, write_images
    from jaxfish.io._images import read_image

    real = read_image(SAMPLE)
    rng = np.random.default_rng(0)
    faces = []
    for _ in range(20):
        y0, x0 = rng.integers(0, real.shape[0] - face_size // 2), rng.integers(0, real.shape[1] - face_size // 2)
        crop = np.resize(real[y0:, x0:], (face_size, face_size, 3))  # the real frame's texture, tiled
        yy, xx = np.mgrid[:face_size, :face_size]
        depth = (2.0 + 0.05 * yy + 0.01 * xx + rng.normal(0, 0.01, yy.shape)).astype(np.float32)
        sem = ((yy // 97 + xx // 131) % 23).astype(np.uint8)
        ids = ((yy // 61) * 7 + xx // 89).astype(np.int32) % 700
        faces.append(CameraImages(rgb=crop, depth_m=depth, semantic=sem, actor_id=ids))

    def write_all() -> float:
        start = time.process_time()
        for i, f in enumerate(faces):
            d = tmp / f"face{i}"
            d.mkdir(exist_ok=True)
            write_images(d, f, "curr")
        return time.process_time() - start

    new = write_all()
    mib = sum(p.stat().st_size for p in tmp.rglob("face*/*.png")) / 2**20
    original = _images.encode_png

    def via_oiio(pixels, *, text=None, png_level=1, where=""):
        path = tmp / "oiio_face.png"
        oiio_encode(path, pixels, png_level)
        return path.read_bytes()

    _images.encode_png = via_oiio
    try:
        old = write_all()
    finally:
        _images.encode_png = original
    return [f"capture writer, one frame at t (20 cube faces x rgb/depth/semantic/instance BGRA PNGs, "
            f"{face_size}-px faces, {mib:.0f} MiB): jaxfish {new:.2f} CPU s, OpenImageIO {old:.2f} CPU s"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--repeats", type=int, default=15)
    parser.add_argument("--face-size", type=int, default=768)
    args = parser.parse_args()
    oiio.attribute("threads", 1)
    print(f"load average {os.getloadavg()[0]:.1f}, {os.cpu_count()} cores; one thread; median of {args.repeats}")
    with tempfile.TemporaryDirectory(prefix="bench_codecs_") as tmp:
        print("\n".join(codec_table(args.repeats, Path(tmp))))
        print("\n".join(capture_frame(args.face_size, Path(tmp))))


if __name__ == "__main__":
    main()
