"""`jaxfish.io` only encodes and decodes: no ground truth, BEV or rendering computation and no
jitted program in it (those live in the core: `jaxfish.pipeline`, `jaxfish.groundtruth`,
`jaxfish.bev`, `jaxfish.scene`)."""

from __future__ import annotations

import ast
from pathlib import Path

import jaxfish

IO = Path(jaxfish.__file__).resolve().parent / "io"
FORBIDDEN_MODULES = ("groundtruth", "bev", "pipeline", "dataset", "cli", "carla")
"""Packages io never imports: the ground-truth and BEV computations, and the edge above io."""
FORBIDDEN_CALLS = {"jit", "filter_jit", "vmap", "pmap", "generate_street", "render", "render_camera",
                   "render_cube_faces", "render_pixels", "simulate_camera", "simulate_view", "simulate_lidar",
                   "simulate_radar", "simulate_imu", "simulate_gnss", "cast_rays", "rig_ground_truth",
                   "fisheye_ground_truth", "view_ground_truth"}
"""Calls that compile a program, render the scene or compute ground truth."""


def _problems(path: Path) -> list[str]:
    tree = ast.parse(path.read_text())
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom):
            parts = (node.module or "").split(".")
            rel = parts[0] if node.level == 2 else (parts[1] if parts[:1] == ["jaxfish"] and len(parts) > 1 else None)
            if rel in FORBIDDEN_MODULES:
                out.append(f"{path.name}:{node.lineno}: imports jaxfish.{rel}")
        elif isinstance(node, ast.Import):
            for alias in node.names:
                parts = alias.name.split(".")
                if parts[0] == "jaxfish" and len(parts) > 1 and parts[1] in FORBIDDEN_MODULES:
                    out.append(f"{path.name}:{node.lineno}: imports {alias.name}")
        elif isinstance(node, ast.Call):
            f = node.func
            name = f.attr if isinstance(f, ast.Attribute) else f.id if isinstance(f, ast.Name) else None
            if name in FORBIDDEN_CALLS:
                out.append(f"{path.name}:{node.lineno}: calls {name}")
        elif isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            for d in node.decorator_list:
                target = d.func if isinstance(d, ast.Call) else d
                name = target.attr if isinstance(target, ast.Attribute) else getattr(target, "id", None)
                if name in FORBIDDEN_CALLS or (isinstance(d, ast.Call) and any(
                        getattr(a, "attr", getattr(a, "id", None)) in FORBIDDEN_CALLS for a in d.args)):
                    out.append(f"{path.name}:{node.lineno}: decorated with {name}")
    return out


def test_io_only_encodes_and_decodes():
    files = sorted(IO.glob("*.py"))
    assert len(files) > 5
    problems = [p for f in files for p in _problems(f)]
    assert not problems, "jaxfish.io computes or compiles: " + "; ".join(problems)


def test_the_scan_sees_what_it_forbids(tmp_path):
    bad = tmp_path / "bad.py"
    bad.write_text("import jax\nfrom ..groundtruth import rig_ground_truth\nfrom jaxfish.pipeline import x\n"
                   "f = jax.jit(lambda a: a)\n@jax.jit\ndef g(a):\n    return simulate_camera(a)\n")
    found = _problems(bad)
    assert any("jaxfish.groundtruth" in p for p in found) and any("jaxfish.pipeline" in p for p in found)
    assert sum("calls jit" in p for p in found) == 1 and any("decorated with jit" in p for p in found)
    assert any("simulate_camera" in p for p in found)
