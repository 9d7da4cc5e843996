"""Reprojection speed on this machine (benchmark, not a test): ``uv run python scripts/bench_reprojection.py``.

Measures, in one process, the best of repeated runs after compilation (see `best_ms`):

1. bilinear resampling of a 1280x966x3 float32 image vs ``cv2.remap`` with the *same* map (the
   SynWoodScape FV fisheye rectified to a 1280x966 pinhole), and the memory-bandwidth bound of that
   work (bytes that must move / measured copy bandwidth);
2. nearest resampling of a uint8 label image vs ``cv2.remap(INTER_NEAREST)``;
3. the full cube -> fisheye step of a capture: 4 cameras x (rgb uint8, depth float32, labels uint8)
   at t and t-1 from five 1024-px faces (one jitted call);
4. LUT construction for 4 cameras (1280x966 fisheyes from five 1024-px faces), vmapped.

Prints a table with the ratios to the goals of issue 3.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import cv2
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

import jaxfish as jf
from jaxfish.reprojection import CubeRig, build_lut, resample_bilinear, resample_depth, resample_nearest

SHARED = Path(__file__).resolve().parents[1].parent / "shared"


def best_ms(fn, *, repeat: int = 15) -> float:
    """Best wall time (ms) of ``repeat`` calls of ``fn()`` (blocking on JAX results), after one
    warm-up call. The best, not the median: on a shared 2-core machine other processes inflate
    the median, while the best run shows what the code needs."""
    jax.block_until_ready(fn())
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        jax.block_until_ready(fn())
        times.append(time.perf_counter() - t0)
    return 1e3 * float(np.min(times))


def copy_bandwidth_gb_s() -> float:
    """Memory bandwidth measured as a large NumPy copy (read + write bytes per second)."""
    a = np.ones(64 * 2**20, np.float32)  # 256 MB
    b = np.empty_like(a)
    ms = best_ms(lambda: np.copyto(b, a), repeat=5)
    return 2 * a.nbytes / (ms * 1e-3) / 1e9


def rig_cameras() -> list[jf.WoodScapeFisheye]:
    names = ("FV", "MVL", "MVR", "RV")
    if (SHARED / "calibration/synwoodscape/FV.json").is_file():
        return [jf.load_calibration(SHARED / f"calibration/synwoodscape/{n}.json").camera.astype(jnp.float32) for n in names]
    rig = jf.default_rig()
    return [rig[n].camera.astype(jnp.float32) for n in names]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--face-size", type=int, default=1024)
    parser.add_argument("--repeat", type=int, default=15)
    args = parser.parse_args()
    rows: list[tuple[str, float, str, str]] = []
    cams = rig_cameras()
    fish = cams[0]
    h, w = fish.height, fish.width
    rng = np.random.default_rng(0)
    jit_lut = jax.jit(build_lut, static_argnames=("supersample", "dtype"))

    # 1-2. Same map as cv2: FV fisheye (source) -> 1280x966 pinhole (target).
    pin = jf.Pinhole.from_fov(w, h, 120.0, dtype=jnp.float32)
    rect_lut = jit_lut(fish, pin)
    uv = np.asarray(rect_lut.uv[..., 0, :])
    map_x, map_y = np.ascontiguousarray(uv[..., 0]), np.ascontiguousarray(uv[..., 1])
    img = rng.random((h, w, 3), dtype=np.float32)
    img_j = jnp.asarray(img)[None]
    bil = jax.jit(resample_bilinear)
    t_jax = best_ms(lambda: bil(img_j, rect_lut), repeat=args.repeat)
    t_cv2 = best_ms(lambda: cv2.remap(img, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE), repeat=args.repeat)
    bw = copy_bandwidth_gb_s()
    moved = h * w * (3 * 4 + 3 * 4 + 4 + 8)  # read source once, write output, LUT index + fractions
    t_bound = moved / (bw * 1e9) * 1e3
    rows.append(("bilinear 1280x966x3 f32 (jaxfish)", t_jax, f"{t_jax / t_cv2:.2f}x cv2.remap", "goal <= 1.5x"))
    rows.append(("bilinear 1280x966x3 f32 (cv2.remap)", t_cv2, "", ""))
    rows.append(("  memory-bandwidth bound", t_bound, f"{t_jax / t_bound:.1f}x bound", f"copy {bw:.1f} GB/s"))

    labels = rng.integers(0, 25, (h, w), dtype=np.uint8)
    labels_j = jnp.asarray(labels)[None]
    near = jax.jit(resample_nearest)
    t_jax_n = best_ms(lambda: near(labels_j, rect_lut), repeat=args.repeat)
    t_cv2_n = best_ms(lambda: cv2.remap(labels, map_x, map_y, cv2.INTER_NEAREST, borderMode=cv2.BORDER_REPLICATE), repeat=args.repeat)
    rows.append(("nearest 1280x966 u8 (jaxfish)", t_jax_n, f"{t_jax_n / t_cv2_n:.2f}x cv2.remap", "goal <= 1.5x"))
    rows.append(("nearest 1280x966 u8 (cv2.remap)", t_cv2_n, "", ""))
    rect_lut = None  # free it before the large cube buffers

    # 4. LUTs of 4 cameras from a 1024-px cube rig, vmapped.
    s = args.face_size
    rig = CubeRig(s, dtype=jnp.float32)
    stacked = jax.tree_util.tree_map(lambda *x: jnp.stack(x), *cams)
    build4 = eqx.filter_jit(eqx.filter_vmap(lambda c: build_lut(rig, c)))
    t0 = time.perf_counter()
    luts = jax.block_until_ready(build4(stacked))
    t_compile = (time.perf_counter() - t0) * 1e3
    t_lut = best_ms(lambda: build4(stacked), repeat=max(3, args.repeat // 5))
    rows.append((f"LUT build, 4 cameras, {s}-px faces", t_lut, f"first call {t_compile / 1e3:.1f} s", "(compile + run)"))

    # 3. Full cube -> fisheye: 4 cameras x (rgb, depth, labels) x (t, t-1), one array per camera.
    luts_list = [jax.tree_util.tree_map(lambda a, c=c: a[c], luts) for c in range(len(cams))]
    rgb = [jnp.asarray(rng.integers(0, 256, (2, 5, s, s, 3), dtype=np.uint8)) for _ in cams]
    depth = [jnp.asarray(rng.uniform(1.0, 1000.0, (2, 5, s, s)).astype(np.float32)) for _ in cams]
    lab = [jnp.asarray(rng.integers(0, 25, (2, 5, s, s), dtype=np.uint8)) for _ in cams]

    @jax.jit
    def per_camera(r, d, l, lut):  # both time steps of one camera; the kernels loop over frames
        return resample_bilinear(r, lut)[0], resample_depth(d, lut)[0], resample_nearest(l, lut)[0]

    # Cameras in a Python loop of one jitted call each (vmap over cameras would batch the gathers,
    # which XLA runs more slowly on CPU).
    def capture():
        return [per_camera(rgb[c], depth[c], lab[c], luts_list[c]) for c in range(len(cams))]

    k_rgb = best_ms(lambda: jax.jit(resample_bilinear)(rgb[0][0], luts_list[0]), repeat=args.repeat)
    k_dep = best_ms(lambda: jax.jit(resample_depth)(depth[0][0], luts_list[0]), repeat=args.repeat)
    k_lab = best_ms(lambda: jax.jit(resample_nearest)(lab[0][0], luts_list[0]), repeat=args.repeat)
    k_sum = 8 * (k_rgb + k_dep + k_lab)
    rows.append((f"  one camera, one frame: rgb u8 (padded faces), {s}-px", k_rgb, "", ""))
    rows.append((f"  one camera, one frame: depth f32, {s}-px", k_dep, "", ""))
    rows.append((f"  one camera, one frame: labels u8, {s}-px", k_lab, "", ""))
    rows.append(("  8 x (rgb + depth + labels), measured one by one", k_sum, f"{k_sum / 500:.2f}x goal", "goal < 500 ms"))
    t_cap = best_ms(capture, repeat=max(3, args.repeat // 3))
    rows.append((f"cube->fisheye 4 cams x (rgb,depth,label) x 2 frames, {s}-px", t_cap, f"{t_cap / 500:.2f}x goal", "goal < 500 ms"))

    print(f"jax {jax.__version__}, cv2 {cv2.__version__}, {jax.devices()[0].platform}, {len(jax.devices())} device(s)")
    print(f"{'measurement':<58} {'ms':>9}  {'ratio':<22} note")
    for name, ms, ratio, note in rows:
        print(f"{name:<58} {ms:9.2f}  {ratio:<22} {note}")


if __name__ == "__main__":
    main()
