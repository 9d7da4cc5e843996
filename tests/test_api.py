"""The public API: documented, and the architecture rule (the core never imports the edge)."""

from __future__ import annotations

import ast
import importlib
import inspect
import pkgutil
import re
from pathlib import Path

import pytest

import jaxfish

ROOT = Path(jaxfish.__file__).resolve().parent
DOCS = ROOT.parent / "docs"
EDGE = {"io", "cli", "dataset", "carla"}


def _public_subpackages() -> list[str]:
    return sorted(m.name for m in pkgutil.iter_modules([str(ROOT)]) if m.ispkg and not m.name.startswith("_"))


def _public_names(module) -> dict[str, object]:
    names = {}
    for name in dir(module):  # dir: the root's lazily re-exported names included
        if name.startswith("_") or name in {"annotations"}:
            continue
        obj = getattr(module, name)
        if inspect.ismodule(obj):
            continue
        names[name] = obj
    return names


def _documented_targets() -> set[str]:
    targets = set()
    for md in DOCS.rglob("*.md"):
        targets.update(re.findall(r"^:::\s+([\w.]+)", md.read_text(), flags=re.M))
    return targets


def test_every_public_name_has_a_docstring():
    missing = []
    modules = [jaxfish] + [importlib.import_module(f"jaxfish.{s}") for s in _public_subpackages()]
    for module in modules:
        for name, obj in _public_names(module).items():
            if (inspect.isclass(obj) or inspect.isfunction(obj)) and not inspect.getdoc(obj):
                missing.append(f"{module.__name__}.{name}")
            if inspect.isclass(obj) and obj.__module__.startswith("jaxfish"):
                for attr, member in vars(obj).items():
                    if attr.startswith("_"):
                        continue
                    fn = member.fget if isinstance(member, property) else getattr(member, "__func__", member)
                    fn = getattr(fn, "__wrapped__", fn)
                    if callable(fn) and not inspect.isclass(fn) and not inspect.getdoc(fn):
                        missing.append(f"{module.__name__}.{name}.{attr}")
    assert not missing, f"public names without a docstring: {missing}"


def test_every_public_name_is_in_the_api_docs():
    targets = _documented_targets()
    missing = []
    for sub in [""] + _public_subpackages():
        if sub == "cli":
            continue
        module = importlib.import_module(f"jaxfish.{sub}" if sub else "jaxfish")
        for name, obj in _public_names(module).items():
            if name == "__version__" or inspect.ismodule(obj):
                continue
            candidates = {f"{module.__name__}.{name}", f"jaxfish.{name}"}
            home = getattr(obj, "__module__", None) or ""
            if home.startswith("jaxfish."):  # documented under its own subpackage
                candidates.add(f"jaxfish.{home.split('.')[1]}.{name}")
            if not candidates & targets:
                missing.append(f"{module.__name__}.{name}")
    assert not missing, f"public names missing from a '::: name' line in docs/: {missing}"


def _imported_modules(path: Path) -> list[str]:
    tree = ast.parse(path.read_text())
    package = ".".join(path.relative_to(ROOT.parent).with_suffix("").parts[:-1])
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out.extend(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - node.level + 1]
                out.append(".".join(base + ([node.module] if node.module else [])))
            else:
                out.append(node.module or "")
    return out


@pytest.mark.parametrize("sub", [s for s in _public_subpackages() if s not in EDGE])
def test_core_never_imports_the_edge(sub):
    offenders = []
    for path in (ROOT / sub).rglob("*.py"):
        for mod in _imported_modules(path):
            parts = mod.split(".")
            if len(parts) >= 2 and parts[0] == "jaxfish" and parts[1] in EDGE:
                offenders.append(f"{path.relative_to(ROOT.parent)} imports {mod}")
            if parts[0] in {"OpenImageIO", "typer", "rich", "cv2"}:
                offenders.append(f"{path.relative_to(ROOT.parent)} imports {mod}")
    assert not offenders, offenders
