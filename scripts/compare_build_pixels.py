"""Check that two builds hold the same pixels: every PNG decoded by OpenImageIO (shape, dtype, values
and its ``jaxfish:*`` text attributes) and every other file byte for byte. Used to show that a PNG
encoder change alters bytes only, never pixels or metadata.

    # in each checkout (its own jaxfish is imported from the current directory):
    uv run python /path/to/scripts/compare_build_pixels.py build OUT
    # then, anywhere:
    uv run python scripts/compare_build_pixels.py compare OUT_A OUT_B

``build OUT`` renders the test suite's small capture (``tests/dataset/small_capture.py``: scale 0.05,
2 frames, seed 1) into ``OUT/capture`` in the test suite's JAX configuration and builds it into
``OUT/dataset`` (default options) and ``OUT/dataset_backward_flow`` (``backward_flow=True``): the
recipes of the ``small`` and ``small_backward_flow`` byte manifests (``scripts/check_build_bytes.py``).
``compare A B`` exits 1 naming the first differences, else prints how many files of each kind matched.
The completion markers (``.done/*.json``) record the SHA-256 of the sample's files and of its capture
frame directory: they are compared with the hashes of PNG files and frame directories left out (same
keys, every other value equal).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
from pathlib import Path


def build(out: Path) -> None:
    sys.path.insert(0, str(Path.cwd()))  # the checkout whose jaxfish and tests build
    import tests.conftest  # noqa: F401  (the test suite's JAX configuration)
    from jaxfish.cli._demo import demo_config, demo_rig
    from jaxfish.dataset import BuildOptions, build_dataset, synthesize_capture
    from tests.dataset import small_capture as sc

    capture = synthesize_capture(out / "capture", demo_rig(sc.SCALE), frames=sc.FRAMES, seed=sc.SEED,
                                 config=demo_config(sc.SCALE))
    for name, options in (("dataset", {}), ("dataset_backward_flow", {"backward_flow": True})):
        report = build_dataset(capture, out / name, options=BuildOptions(**options))
        if not report.ok:
            raise SystemExit(f"{name}: build failed: {report.summary()}")
    print(f"built {out}")


def decoded(path: Path) -> tuple[str, tuple[int, ...], str, dict[str, str]]:
    """``(SHA-256 of the pixels, shape, dtype, {jaxfish:* attribute: text})`` by OpenImageIO."""
    import numpy as np
    import OpenImageIO as oiio

    config = oiio.ImageSpec()
    config.attribute("oiio:UnassociatedAlpha", 1)
    inp = oiio.ImageInput.open(str(path), config)
    if inp is None:
        raise SystemExit(f"{path}: OpenImageIO cannot open it ({oiio.geterror()})")
    try:
        spec = inp.spec()
        pixels = np.asarray(inp.read_image(0, 0, 0, spec.nchannels, oiio.UNKNOWN))
        attrs = {a.name: str(a.value) for a in spec.extra_attribs if a.name.startswith("jaxfish:")}
    finally:
        inp.close()
    return hashlib.sha256(pixels.tobytes()).hexdigest(), pixels.shape, str(pixels.dtype), attrs


def marker_without_png_hashes(path: Path) -> dict:
    """A completion marker with the hashes that follow PNG bytes blanked (keys kept)."""
    doc = json.loads(path.read_text())
    for key in doc.get("files", {}):
        if key.lower().endswith(".png"):
            doc["files"][key] = "png"
    for key in doc.get("source", {}):
        if key.startswith("frames/"):
            doc["source"][key] = "frame directory"
    return doc


def compare(a: Path, b: Path) -> int:
    files_a = {p.relative_to(a).as_posix() for p in a.rglob("*") if p.is_file()}
    files_b = {p.relative_to(b).as_posix() for p in b.rglob("*") if p.is_file()}
    problems = [f"only in {a}: {f}" for f in sorted(files_a - files_b)]
    problems += [f"only in {b}: {f}" for f in sorted(files_b - files_a)]
    counts = {"png same pixels": 0, "png same bytes": 0, "other same bytes": 0, "markers same but png hashes": 0}
    for rel in sorted(files_a & files_b):
        pa, pb = a / rel, b / rel
        if rel.lower().endswith(".png"):
            da, db = decoded(pa), decoded(pb)
            if da != db:
                problems.append(f"{rel}: decoded pixels or metadata differ ({da[1:]} vs {db[1:]})")
            else:
                counts["png same pixels"] += 1
                counts["png same bytes"] += pa.read_bytes() == pb.read_bytes()
        elif pa.read_bytes() == pb.read_bytes():
            counts["other same bytes"] += 1
        elif "/.done/" in f"/{rel}" and rel.endswith(".json"):
            if marker_without_png_hashes(pa) == marker_without_png_hashes(pb):
                counts["markers same but png hashes"] += 1
            else:
                problems.append(f"{rel}: completion markers differ beyond PNG hashes")
        else:
            problems.append(f"{rel}: bytes differ")
    for line in problems[:20]:
        print(line)
    print(f"{len(files_a & files_b)} files in both; " + ", ".join(f"{k}: {v}" for k, v in counts.items())
          + f"; {len(problems)} differences")
    return 1 if problems else 0


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    sub.add_parser("build").add_argument("out", type=Path)
    c = sub.add_parser("compare")
    c.add_argument("a", type=Path)
    c.add_argument("b", type=Path)
    args = parser.parse_args()
    if args.command == "build":
        build(args.out)
        return 0
    return compare(args.a, args.b)


if __name__ == "__main__":
    sys.exit(main())
