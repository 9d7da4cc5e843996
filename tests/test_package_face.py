"""The package's face: importing the core loads no edge module and no heavy library, the package's own
imports form no cycle, the core never imports the edge, and no module imports another module's
private (underscore) name."""

from __future__ import annotations

import ast
import json
import pkgutil
from pathlib import Path

import pytest

from tests.helpers import run_python

ROOT = Path(__file__).resolve().parents[1] / "jaxfish"
EDGE = ("io", "dataset", "carla", "cli")
"""The edge subpackages: files, the simulator, the command line."""
HEAVY = ("OpenImageIO", "dask", "distributed", "typer", "rich")
"""Libraries that only the edge may load."""


def _subpackages() -> list[str]:
    return sorted(m.name for m in pkgutil.iter_modules([str(ROOT)]) if m.ispkg and not m.name.startswith("_"))


CORE = [s for s in _subpackages() if s not in EDGE]


# ------------------------------------------------------------------ what an import loads
_PROBE = """
import importlib, json, sys
heavy = {heavy!r}
edge = {edge!r}

def offending():
    return {{m for m in sys.modules
            if m.split(".")[0] in heavy or (m.split(".")[0] == "jaxfish" and m.split(".")[1:2] and m.split(".")[1] in edge)}}

found = {{}}
for module in {modules!r}:
    before = offending()
    importlib.import_module(module)
    found[module] = sorted(offending() - before)
print(json.dumps(found))
"""


def test_importing_the_core_loads_neither_the_edge_nor_heavy_libraries():
    """One fresh interpreter imports ``jaxfish`` and then each core subpackage: what the imports
    load together is the union of what each loads alone, so that none of them may load an edge
    subpackage or a heavy library; a module that does is named with the first import loading it."""
    modules = ["jaxfish"] + [f"jaxfish.{s}" for s in CORE]
    out = run_python(["-c", _PROBE.format(modules=modules, heavy=HEAVY, edge=EDGE)], cwd=ROOT.parent)
    assert out.returncode == 0, out.stderr
    found = json.loads(out.stdout.strip().splitlines()[-1])
    assert list(found) == modules
    assert not any(found.values()), {f"import {m} loads": loaded for m, loaded in found.items() if loaded}


def test_the_root_reexports_io_lazily():
    import jaxfish
    import jaxfish.io

    for name in ("load_calibration", "load_rig", "save_calibration", "save_rig"):
        assert name in dir(jaxfish)
        assert getattr(jaxfish, name) is getattr(jaxfish.io, name)
    assert "Calibration" in dir(jaxfish) and "__version__" in dir(jaxfish)
    with pytest.raises(AttributeError, match="no_such_name"):
        jaxfish.no_such_name  # noqa: B018


# ------------------------------------------------------------------ the import graph
def _module_files() -> dict[str, Path]:
    files = {}
    for path in ROOT.rglob("*.py"):
        parts = path.relative_to(ROOT.parent).with_suffix("").parts
        files[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    return files


MODULES = _module_files()


def _package_of(module: str) -> str:
    return module if MODULES[module].name == "__init__.py" else module.rpartition(".")[0]


def _resolve(module: str, node: ast.Import | ast.ImportFrom) -> list[tuple[str, str | None, int]]:
    """``(imported module, imported name or None, line)`` for each name of one import statement of
    ``module``: relative imports resolved, and ``from package import name`` where ``package.name``
    is a module counted as importing that module."""
    if isinstance(node, ast.Import):
        return [(a.name, None, node.lineno) for a in node.names]
    base = node.module or ""
    if node.level:
        package = _package_of(module).split(".")
        base = ".".join(package[: len(package) - node.level + 1] + ([node.module] if node.module else []))
    out = []
    for a in node.names:
        full = f"{base}.{a.name}"
        out.append((full, None, node.lineno) if full in MODULES else (base, a.name, node.lineno))
    return out


def _imports(module: str, source: str | None = None) -> list[tuple[str, str | None, int]]:
    """Every import of ``module`` (module level, inside functions and ``TYPE_CHECKING`` blocks
    alike), as `_resolve` gives them."""
    tree = ast.parse(MODULES[module].read_text() if source is None else source)
    return [x for node in ast.walk(tree) if isinstance(node, (ast.Import, ast.ImportFrom)) for x in _resolve(module, node)]


IMPORTS = {m: _imports(m) for m in MODULES}


def _graph() -> dict[str, dict[str, int]]:
    """Module -> {imported jaxfish module: first line}."""
    graph: dict[str, dict[str, int]] = {m: {} for m in MODULES}
    for m, imports in IMPORTS.items():
        for target, _, line in sorted(imports, key=lambda x: x[2]):
            if target in MODULES and target != m:
                graph[m].setdefault(target, line)
    return graph


def _cycles(graph: dict[str, dict[str, int]]) -> list[list[str]]:
    """One cycle per strongly connected component of more than one module (Tarjan, iterative)."""
    index, low, stack, on_stack, components = {}, {}, [], set(), []
    counter = 0
    for root in sorted(graph):
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = counter
        counter += 1
        stack.append(root)
        on_stack.add(root)
        while work:
            v, children = work[-1]
            for w in children:
                if w not in index:
                    index[w] = low[w] = counter
                    counter += 1
                    stack.append(w)
                    on_stack.add(w)
                    work.append((w, iter(sorted(graph[w]))))
                    break
                if w in on_stack:
                    low[v] = min(low[v], index[w])
            else:
                work.pop()
                if work:
                    low[work[-1][0]] = min(low[work[-1][0]], low[v])
                if low[v] == index[v]:
                    component = set()
                    while True:
                        w = stack.pop()
                        on_stack.discard(w)
                        component.add(w)
                        if w == v:
                            break
                    if len(component) > 1:
                        components.append(component)
    cycles = []
    for component in components:  # a shortest cycle through the component's first module
        start = min(component)
        paths, seen = [[start]], {start}
        while paths:
            path = paths.pop(0)
            nxt = sorted(w for w in graph[path[-1]] if w in component)
            if start in nxt:
                cycles.append(path + [start])
                break
            for w in nxt:
                if w not in seen:
                    seen.add(w)
                    paths.append(path + [w])
    return cycles


def _subpackage(module: str) -> str | None:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else None


def test_the_parser_resolves_relative_imports_inside_functions():
    source = "from . import _oracle\nimport numpy\ndef f():\n    from ..io import _x, read_image\n    from ._caster import FAR_M\n"
    assert sorted(_imports("jaxfish.scene._caster", source)) == [
        ("jaxfish.io", "_x", 4), ("jaxfish.io", "read_image", 4), ("jaxfish.scene._caster", "FAR_M", 5),
        ("jaxfish.scene._oracle", None, 1), ("numpy", None, 2)]
    assert _imports("jaxfish.io", "from ._json import read_json") == [("jaxfish.io._json", "read_json", 1)]
    assert _cycles({"a": {"b": 1}, "b": {"c": 1}, "c": {"a": 1, "d": 1}, "d": {}}) == [["a", "b", "c", "a"]]


def test_no_import_cycles():
    graph = _graph()
    cycles = _cycles(graph)
    text = [" -> ".join(f"{a} ({MODULES[a].relative_to(ROOT.parent)}:{graph[a][b]})" for a, b in zip(c, c[1:], strict=False))
            + f" -> {c[-1]}" for c in cycles]
    assert not cycles, "import cycles:\n" + "\n".join(text)


def test_the_core_never_imports_the_edge():
    offenders = []
    for m, imports in IMPORTS.items():
        sub = _subpackage(m)
        if sub is None or sub in EDGE:  # the root re-exports io lazily (test above)
            continue
        for target, _, line in imports:
            parts = target.split(".")
            if (parts[0] == "jaxfish" and len(parts) > 1 and parts[1] in EDGE) or parts[0] in HEAVY:
                offenders.append(f"{MODULES[m].relative_to(ROOT.parent)}:{line} imports {target}")
    assert not offenders, offenders


def test_the_root_imports_the_edge_only_inside_functions():
    tree = ast.parse(MODULES["jaxfish"].read_text())
    offenders = []
    for node in tree.body:  # what runs on import: not function bodies, not TYPE_CHECKING blocks
        if isinstance(node, ast.FunctionDef) or (isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test)):
            continue
        for sub in ast.walk(node):
            if isinstance(sub, (ast.Import, ast.ImportFrom)):
                for target, _, line in _resolve("jaxfish", sub):
                    if _subpackage(target) in EDGE or target.split(".")[0] in HEAVY:
                        offenders.append(f"jaxfish/__init__.py:{line} imports {target}")
    assert not offenders, offenders


def test_no_module_imports_a_private_name_of_another():
    offenders = []
    for m, imports in IMPORTS.items():
        for target, name, line in imports:
            if name is None or not name.startswith("_") or name.startswith("__"):
                continue
            if target.split(".")[0] == "jaxfish" and target != m:
                offenders.append(f"{MODULES[m].relative_to(ROOT.parent)}:{line} imports {name} from {target}")
    # module attributes: `module._name` where `module` was bound by an import of a jaxfish module
    for m, path in MODULES.items():
        tree = ast.parse(path.read_text())
        aliases = {}
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                aliases.update({a.asname or a.name.split(".")[0]: a.name for a in node.names if a.name.startswith("jaxfish")})
            elif isinstance(node, ast.ImportFrom):
                aliases.update({a.asname or a.name: a.name for a, (t, n, _) in zip(node.names, _resolve(m, node), strict=True)
                                if n is None and t.startswith("jaxfish")})
        for node in ast.walk(tree):
            if (isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) and node.value.id in aliases
                    and node.attr.startswith("_") and not node.attr.startswith("__")):
                offenders.append(f"{path.relative_to(ROOT.parent)}:{node.lineno} uses {ast.unparse(node)}")
    assert not offenders, "private names used across modules (make them public in their module):\n" + "\n".join(offenders)



# ------------------------------------------------------------------ one definition each
def test_the_far_depth_and_the_dvs_dtype_are_defined_once():
    import numpy as np

    import jaxfish.groundtruth
    import jaxfish.io
    import jaxfish.reprojection
    import jaxfish.scene
    from jaxfish import _constants

    for alias in (jaxfish.reprojection.FAR_DEPTH_M, jaxfish.groundtruth.FAR_RANGE_M, jaxfish.scene.FAR_M,
                  jaxfish.io.CARLA_MAX_DEPTH_M):
        assert alias is _constants.FAR_DEPTH_M
    assert jaxfish.io.DVS_EVENT_DTYPE is _constants.DVS_EVENT_DTYPE and jaxfish.scene.DVS_DTYPE is _constants.DVS_EVENT_DTYPE
    assert _constants.FAR_DEPTH_M == 1000.0 and _constants.DVS_EVENT_DTYPE == np.dtype(
        [("x", "<u2"), ("y", "<u2"), ("t", "<i8"), ("pol", "?")])
    redefined = []
    for m, path in MODULES.items():
        if m == "jaxfish._constants":
            continue
        tree = ast.parse(path.read_text())
        for node in tree.body:  # module-level names bound to the far depth's literal
            if isinstance(node, (ast.Assign, ast.AnnAssign)) and isinstance(node.value, ast.Constant) \
                    and node.value.value == _constants.FAR_DEPTH_M:
                redefined.append(f"{path.relative_to(ROOT.parent)}:{node.lineno} {ast.unparse(node)}")
        for node in ast.walk(tree):  # any dtype built with the DVS fields
            if isinstance(node, ast.Call) and ast.unparse(node.func).endswith("dtype") and any(
                    isinstance(c, ast.Constant) and c.value == "pol" for c in ast.walk(node)):
                redefined.append(f"{path.relative_to(ROOT.parent)}:{node.lineno} {ast.unparse(node)}")
    assert not redefined, redefined
