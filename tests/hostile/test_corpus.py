"""Every case of the hostile-input corpus (``cases_*.py`` beside this file; see corpus.py)."""

from __future__ import annotations

import importlib
import pkgutil
from pathlib import Path

import pytest

from .corpus import Case, run_case


def _cases() -> list[Case]:
    cases: list[Case] = []
    for info in sorted(pkgutil.iter_modules([str(Path(__file__).parent)]), key=lambda m: m.name):
        if info.name.startswith("cases_"):
            cases.extend(importlib.import_module(f"{__package__}.{info.name}").CASES)
    ids = [c.id for c in cases]
    assert len(ids) == len(set(ids)), "case ids must be unique"
    return cases


@pytest.mark.parametrize("case", _cases(), ids=lambda c: c.id)
def test_hostile_case(case: Case, tmp_path, capsys):
    run_case(case, tmp_path, capsys)
