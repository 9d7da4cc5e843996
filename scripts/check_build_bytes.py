"""Guard: the SHA-256 of every file a dataset build writes, recorded in checked-in manifests
(``tests/dataset/manifests/*.json``), so that a change to the builder can be checked to write the
same bytes.

Builds, each with one manifest:

- ``small``: the test suite's small capture (``tests/dataset/small_capture.py``: the demo's settings
  at scale 0.05, 2 frames, seed 1) built with the default options, serially and on a 2-worker dask
  ``LocalCluster`` (thread workers): both must give the recorded files.
- ``small_backward_flow``: the same capture built with ``BuildOptions(backward_flow=True)``.
- ``full_size``: the embedded scene at full size (``demo_rig(1.0)``, ``demo_config(1.0)``, seed 0),
  one frame, rendered with ``synthesize_capture`` then built with ``build_dataset`` (minutes).
- ``demo``: ``jaxfish demo OUT`` with its default settings (2 frames, scale 0.5); the files of
  ``OUT/dataset`` (minutes).

``full_size`` and ``demo`` also record the capture's files (``capture_files``); a run that writes no
capture (an in-memory source) is reported, not failed, and only the dataset's files are compared.

The bytes depend on XLA's CPU code generation (float results), on the library versions and on the
CPU's vector instructions: each manifest records the environment it was made in (`environment`).
``tests/dataset/test_build_bytes.py`` checks ``small`` and ``small_backward_flow`` and skips,
naming the difference, on another environment.

    uv run python scripts/check_build_bytes.py                    # check all: exit 1 on a difference
    uv run python scripts/check_build_bytes.py small demo         # check these
    uv run python scripts/check_build_bytes.py --record full_size # re-record (then commit the manifest)
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
MANIFESTS = ROOT / "tests" / "dataset" / "manifests"
MANIFEST_FORMAT = "jaxfish-build-bytes"
RECORD_HINT = "uv run python scripts/check_build_bytes.py --record {name}"

SIMD_FLAGS = ("sse4_2", "avx", "avx2", "fma", "avx512f", "avx512dq", "avx512bw", "avx512vl", "avx512_vnni",
              "avx512_bf16", "avx512_fp16", "amx_tile")
"""The /proc/cpuinfo flags recorded as the CPU's SIMD level: the instructions LLVM may use when XLA
compiles for the host CPU, which change the float results of the ground truth."""

EXCLUDED: dict[str, str] = {}
"""Files (relative paths) left out of every manifest, with the reason. None: every file a build
writes is deterministic (completion markers and ``dataset.json`` hold no times, hosts or paths, and
the tonic ``.npz`` zip entries carry the fixed 1980-01-01 stamp of ``zipfile.ZipInfo``)."""


# ------------------------------------------------------------------ environment and hashes
def environment() -> dict[str, object]:
    """What the bytes of a build depend on besides jaxfish's code: Python, jax/jaxlib, numpy and
    OpenImageIO versions (the EXR encoder), the PNG deflate implementation and version
    (`jaxfish.io._png.deflate_name`: ISA-L, or zlib where ``isal`` is missing), the JAX backend and
    configuration (``jax_enable_x64`` changes the bytes: the test suite enables it, the CLI does not), ``XLA_FLAGS``, the machine
    architecture and the CPU's SIMD flags (those of `SIMD_FLAGS` in /proc/cpuinfo; ``None`` where it
    cannot be read)."""
    import jax
    import jaxlib
    import numpy as np
    import OpenImageIO as oiio

    from jaxfish.io._png import deflate_name

    flags: list[str] | None = None
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("flags"):
                present = set(line.split(":", 1)[1].split())
                flags = [f for f in SIMD_FLAGS if f in present]
                break
    except OSError:
        pass
    return {"python": platform.python_version(), "jax": jax.__version__, "jaxlib": jaxlib.__version__,
            "numpy": np.__version__, "OpenImageIO": oiio.__version__,
            "png_deflate": deflate_name(), "backend": jax.default_backend(),
            "jax_enable_x64": bool(jax.config.jax_enable_x64),
            "jax_numpy_dtype_promotion": str(jax.config.jax_numpy_dtype_promotion),
            "XLA_FLAGS": os.environ.get("XLA_FLAGS", ""), "machine": platform.machine(), "simd": flags}


def environment_difference(recorded: dict, here: dict) -> list[str]:
    """``"key: recorded X, here Y"`` for every environment key that differs."""
    return [f"{k}: recorded {recorded.get(k)!r}, here {here.get(k)!r}"
            for k in sorted(set(recorded) | set(here)) if recorded.get(k) != here.get(k)]


def tree_hashes(root: str | os.PathLike) -> dict[str, str]:
    """``{relative path: SHA-256}`` of every file under ``root`` (hidden ones included), less
    `EXCLUDED`."""
    root = Path(root)
    return {p.relative_to(root).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file() and p.relative_to(root).as_posix() not in EXCLUDED}


def tree_difference(recorded: dict[str, str], here: dict[str, str]) -> dict[str, list[str]]:
    """The files ``missing`` (recorded, not written), ``extra`` (written, not recorded) and
    ``changed`` (other bytes), each sorted."""
    return {"missing": sorted(set(recorded) - set(here)), "extra": sorted(set(here) - set(recorded)),
            "changed": sorted(k for k in set(recorded) & set(here) if recorded[k] != here[k])}


def describe_difference(diff: dict[str, list[str]], limit: int = 10) -> str:
    """One line per kind of difference, naming the first ``limit`` files; empty when equal."""
    lines = []
    for kind in ("changed", "missing", "extra"):
        files = diff[kind]
        if files:
            more = f" (+{len(files) - limit} more)" if len(files) > limit else ""
            lines.append(f"{len(files)} {kind}: {', '.join(files[:limit])}{more}")
    return "\n".join(lines)


def manifest_path(name: str) -> Path:
    return MANIFESTS / f"{name}.json"


def load_manifest(name: str) -> dict:
    return json.loads(manifest_path(name).read_text())


def save_manifest(name: str, recipe: dict, files: dict[str, str], capture_files: dict[str, str] | None = None) -> Path:
    data = {"format": MANIFEST_FORMAT, "name": name, "recipe": recipe, "environment": environment(),
            "re_record": RECORD_HINT.format(name=name), "excluded": EXCLUDED, "files": files}
    if capture_files is not None:
        data["capture_files"] = capture_files
    path = manifest_path(name)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(data, indent=1, sort_keys=False) + "\n")
    return path


# ------------------------------------------------------------------ the builds
def use_test_suite_config() -> None:
    """Apply the test suite's JAX configuration (``tests/conftest.py``, whose import sets it: x64 and
    strict dtype promotion), in which the small manifests are checked."""
    import tests.conftest  # noqa: F401


def small_recipe(options: dict | None = None) -> dict:
    """What the small manifests were made from (a manifest whose recipe differs is stale)."""
    from jaxfish.dataset import BuildOptions
    from tests.dataset import small_capture

    return {"capture": "tests/dataset/small_capture.py", "scale": small_capture.SCALE, "seed": small_capture.SEED,
            "frames": small_capture.FRAMES, "options": BuildOptions(**(options or {})).to_dict()}


def _small(scratch: Path, options: dict | None, dask: bool) -> list[tuple[str, dict[str, str], dict[str, str] | None]]:
    from jaxfish.dataset import BuildOptions, build_dataset
    from tests.dataset.small_capture import small_capture_dir

    runs = [("serial", {})] + ([("dask workers=2 threads", {"workers": 2, "processes": False})] if dask else [])
    out = []
    for label, kwargs in runs:
        dest = scratch / label.replace(" ", "_") / "dataset"
        report = build_dataset(small_capture_dir(), dest, options=BuildOptions(**(options or {})), **kwargs)
        if not report.ok:
            raise SystemExit(f"small build ({label}) failed: {report.summary()}")
        out.append((label, tree_hashes(dest), None))
    return out


FULL_SIZE_SEED = 0


def _full_size(scratch: Path) -> list[tuple[str, dict[str, str], dict[str, str] | None]]:
    from jaxfish.cli._demo import demo_config, demo_rig
    from jaxfish.dataset import build_dataset, synthesize_capture

    capture = synthesize_capture(scratch / "capture", demo_rig(1.0), frames=1, seed=FULL_SIZE_SEED,
                                 config=demo_config(1.0))
    report = build_dataset(capture, scratch / "dataset")
    if not report.ok:
        raise SystemExit(f"full-size build failed: {report.summary()}")
    return [("serial", tree_hashes(scratch / "dataset"), tree_hashes(capture))]


def _demo(scratch: Path) -> list[tuple[str, dict[str, str], dict[str, str] | None]]:
    """``jaxfish demo OUT --write-capture`` (rendered to files, then built: every file of the
    manifest) and ``jaxfish demo OUT`` (the scene in memory: the same sample files; its markers and
    dataset.json name another source, see `IN_MEMORY_SOURCE_FILES`)."""
    exe = Path(sys.executable).parent / "jaxfish"
    runs = []
    for label, extra in (("jaxfish demo --write-capture", ["--write-capture"]), (IN_MEMORY_LABEL, [])):
        out = scratch / ("demo-files" if extra else "demo-memory")
        cmd = [str(exe) if exe.is_file() else "jaxfish", "demo", str(out), *extra]
        start = time.perf_counter()
        done = subprocess.run(cmd, capture_output=True, text=True)
        wall = time.perf_counter() - start
        if done.returncode != 0:
            raise SystemExit(f"{' '.join(cmd)} exited {done.returncode}:\n{done.stdout}\n{done.stderr}")
        print(f"demo: `{' '.join(cmd[1:2] + extra)}` took {wall:.1f} s wall", flush=True)
        capture = out / "capture"
        runs.append((label, tree_hashes(out / "dataset"), tree_hashes(capture) if capture.is_dir() else None))
    return runs


IN_MEMORY_LABEL = "jaxfish demo (in memory)"
"""The run whose source is the embedded scene in memory."""


def in_memory_source_file(rel: str) -> bool:
    """The files that record their source's fingerprint (the completion markers and dataset.json):
    an in-memory source has its own; `tests/pipeline/test_pipeline.py` checks they differ by it only."""
    return rel.startswith(".done/") or rel == "dataset.json"


def comparable(label: str, files: dict[str, str]) -> dict[str, str]:
    """``files`` as the run ``label`` is compared: for the run whose source is in memory, without
    the files `in_memory_source_file` names."""
    return {k: v for k, v in files.items() if label != IN_MEMORY_LABEL or not in_memory_source_file(k)}


SUITE_CONFIG = ("small", "small_backward_flow")
"""The builds made in the test suite's JAX configuration (`use_test_suite_config`); the others in
jaxfish's default one, as the CLI runs."""

BUILDS: dict[str, tuple[Callable[[], dict], Callable[[Path], list]]] = {
    "small": (lambda: small_recipe(), lambda s: _small(s, None, dask=True)),
    "small_backward_flow": (lambda: small_recipe({"backward_flow": True}),
                            lambda s: _small(s, {"backward_flow": True}, dask=False)),
    "full_size": (lambda: {"capture": "synthesize_capture(demo_rig(1.0), frames=1, seed=0, config=demo_config(1.0))",
                           "build": "build_dataset(capture, out) with default options"},
                  _full_size),
    "demo": (lambda: {"command": "jaxfish demo OUT", "files": "OUT/dataset (capture_files: OUT/capture)",
                      "defaults": {"frames": 2, "scale": 0.5, "seed": 0}},
             _demo),
}


# ------------------------------------------------------------------ record / check
def record(name: str, scratch: Path) -> bool:
    recipe_fn, run_fn = BUILDS[name]
    runs = run_fn(scratch)
    (label, files, capture_files), rest = runs[0], runs[1:]
    for other, other_files, _ in rest:  # e.g. the dask build must equal the serial one before recording it
        diff = tree_difference(comparable(other, files), comparable(other, other_files))
        if any(diff.values()):
            print(f"{name}: {other} differs from {label}; not recorded:\n{describe_difference(diff)}")
            return False
    path = save_manifest(name, recipe_fn(), files, capture_files)
    print(f"{name}: recorded {len(files)} files" + (f" + {len(capture_files)} capture files" if capture_files else "")
          + f" in {path.relative_to(ROOT)}")
    return True


def check(name: str, scratch: Path) -> bool:
    recipe_fn, run_fn = BUILDS[name]
    manifest = load_manifest(name)
    here = environment()
    env_diff = environment_difference(manifest["environment"], here)
    if env_diff:
        print(f"{name}: WARNING: another environment than the recorded one ({'; '.join(env_diff)}); "
              f"a difference may come from it (re-record: {RECORD_HINT.format(name=name)})")
    if manifest["recipe"] != recipe_fn():
        print(f"{name}: the manifest's recipe {manifest['recipe']} is not this script's {recipe_fn()}: "
              f"re-record ({RECORD_HINT.format(name=name)})")
        return False
    ok = True
    for label, files, capture_files in run_fn(scratch):
        recorded = manifest["files"]
        if label == IN_MEMORY_LABEL:
            skipped = sorted(k for k in recorded if in_memory_source_file(k))
            print(f"{name} ({label}): {len(skipped)} files naming the source not compared ({', '.join(skipped[:3])} ...)")
        recorded, files = comparable(label, recorded), comparable(label, files)
        diff = tree_difference(recorded, files)
        if any(diff.values()):
            ok = False
            print(f"{name} ({label}): dataset files differ from the manifest "
                  f"({len(recorded)} recorded, {len(files)} written):\n{describe_difference(diff, limit=50)}")
        else:
            print(f"{name} ({label}): all {len(files)} dataset files equal the manifest")
        if "capture_files" in manifest:
            if capture_files is None:
                print(f"{name} ({label}): no capture folder written (an in-memory source): capture files not compared")
                continue
            diff = tree_difference(manifest["capture_files"], capture_files)
            if any(diff.values()):
                ok = False
                print(f"{name} ({label}): capture files differ from the manifest:\n{describe_difference(diff, limit=50)}")
            else:
                print(f"{name} ({label}): all {len(capture_files)} capture files equal the manifest")
    return ok


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("builds", nargs="*", metavar="BUILD", help=f"which builds (default all): {', '.join(BUILDS)}")
    parser.add_argument("--record", action="store_true", help="record the manifests instead of checking them")
    parser.add_argument("--keep", type=Path, default=None,
                        help="build in this new folder and keep it (default: a temporary folder, removed)")
    args = parser.parse_args(argv)
    names = args.builds or list(BUILDS)
    unknown = [n for n in names if n not in BUILDS]
    if unknown:
        parser.error(f"unknown build {unknown[0]!r}; choose from {', '.join(BUILDS)}")
    if len(names) > 1:  # each build in its own process: its own JAX configuration, its own memory
        codes = [subprocess.run([sys.executable, __file__, *(["--record"] if args.record else []),
                                 *(["--keep", str(args.keep)] if args.keep else []), name]).returncode for name in names]
        bad = [n for n, c in zip(names, codes, strict=True) if c]
        print(("recorded" if args.record else "equal") if not bad else f"FAILED: {', '.join(bad)}")
        return 1 if bad else 0
    if str(ROOT) not in sys.path:  # tests.dataset.small_capture: the test suite's capture recipe
        sys.path.insert(0, str(ROOT))
    if names[0] in SUITE_CONFIG:
        use_test_suite_config()
    ok = True
    for name in names:
        scratch = Path(tempfile.mkdtemp(prefix=f"jaxfish_bytes_{name}_")) if args.keep is None else args.keep / name
        scratch.mkdir(parents=True, exist_ok=True)
        start = time.perf_counter()
        try:
            ok &= (record if args.record else check)(name, scratch)
        finally:
            if args.keep is None:
                shutil.rmtree(scratch, ignore_errors=True)
        print(f"{name}: {time.perf_counter() - start:.1f} s", flush=True)
    if not args.record:
        print("equal" if ok else "DIFFERENT")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
