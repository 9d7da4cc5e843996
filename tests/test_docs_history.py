"""Docs and docstrings state contracts, not history (issue 17, item 5).

The pages of ``docs/``, ``README.md`` and the docstrings and comments of ``jaxfish/`` and
``scripts/`` say what the code does; they never tell what it used to do, which numbered session or
run changed it, or how fast it became. Measured figures live in one page, ``docs/performance.md``:
elsewhere a timing (milliseconds, "N x faster") is refused too, so that every figure has its
command and machine beside it. Each failure names the file and line.
"""

from __future__ import annotations

import ast
import io
import re
import tokenize
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PERFORMANCE = ROOT / "docs" / "performance.md"

HISTORY = [
    re.compile(p, re.I)
    for p in (
        r"\b(it|they|we|this|that|which|jaxfish)\s+used\s+to\b",  # "it used to copy" (not "steps used to locate")
        r"\bpreviously\b",
        r"\bformerly\b",
        r"\b(earlier|previous|last|later|next)\s+sessions?\b",
        r"\bsessions?\s+#?\d",
        r"\bruns?\s+#\d",
        r"\bwhat made\b.{0,40}\b(faster|slower)\b",  # "what made session 4 faster"
        r"\bthan before\b",
        r"\b(the\s+)?old default\b",
        r"\btoday'?s?\b",
        r"\bwe\s+(tried|measured|found|changed|fixed)\b",
        r"\b(is|are|takes|runs|costs)\s+now\b",
        r"\bnow\s+(is|are|takes|runs|costs)\b",
        r"\buntil it was\b",
        r"\b(was|were)\s+(slower|faster)\b",
    )
]
"""Phrases that tell history (not "an earlier run": a resume's contract names what one left behind)."""

TIMING = [
    re.compile(p, re.I)
    for p in (
        r"\b\d+(\.\d+)?(\s?[-–]\s?\d+(\.\d+)?)?\s?ms\b",  # a duration in milliseconds
        r"\b(took|takes|take|in|costs?|adds?)\s+(about\s+|~)?\d+(\.\d+)?(\s?[-–]\s?\d+(\.\d+)?)?\s?"
        r"(s|seconds|minutes)\b",  # "the loop took 0.8-0.9 s"
        r"\b\d+(\.\d+)?\s?x\s+(faster|slower|longer|the\s+(CPU|wall)\s+time)\b",  # "3x faster"
        r"\b\d+(\.\d+)?\s?(-|–)\s?\d+(\.\d+)?\s?s\s+(per sample|after compil)",  # "2.8-3.0 s per sample"
        r"\d\s?(samples|M rays)/s\b",  # a measured rate
    )
]
"""Measured figures, allowed only in docs/performance.md (a line stating a goal may name its target)."""
TARGET = re.compile(r"(goal|under|below|within|<|<=|>=|≥)\W*(about\s+|~)?$", re.I)
"""What may precede a figure that is a target, not a measurement ("goal: < 60 s", "under 100 ms")."""


def _markdown() -> list[Path]:
    return sorted((ROOT / "docs").rglob("*.md")) + [ROOT / "README.md"]


def _python() -> list[Path]:
    return sorted((ROOT / "jaxfish").rglob("*.py")) + sorted((ROOT / "scripts").glob("*.py"))


def _python_text(path: Path) -> list[tuple[int, str]]:
    """(line number, text) of every docstring line and every comment of a Python file."""
    source = path.read_text()
    lines: list[tuple[int, str]] = []
    for node in ast.walk(ast.parse(source)):
        body = getattr(node, "body", None)
        if not isinstance(body, list) or not body:
            continue
        first = body[0]
        if isinstance(first, ast.Expr) and isinstance(first.value, ast.Constant) and isinstance(first.value.value, str):
            lines += [(first.lineno + i, text) for i, text in enumerate(first.value.value.splitlines())]
        # attribute docstrings: a string statement right after an assignment
        for prev, stmt in zip(body, body[1:], strict=False):
            if (isinstance(prev, (ast.Assign, ast.AnnAssign)) and isinstance(stmt, ast.Expr)
                    and isinstance(stmt.value, ast.Constant) and isinstance(stmt.value.value, str)):
                lines += [(stmt.lineno + i, text) for i, text in enumerate(stmt.value.value.splitlines())]
    for tok in tokenize.generate_tokens(io.StringIO(source).readline):
        if tok.type == tokenize.COMMENT:
            lines.append((tok.start[0], tok.string))
    return lines


def _flag(text: str, patterns: list[re.Pattern]) -> str | None:
    """The first phrase of ``text`` that one of ``patterns`` finds (timings on a goal's line pass)."""
    for p in patterns:
        m = p.search(text)
        if m and not (p in TIMING and TARGET.search(text[: m.start()])):
            return m.group(0)
    return None


def _findings(path: Path, lines: list[tuple[int, str]], patterns: list[re.Pattern]) -> list[str]:
    """Every line with a phrase, and every pair of consecutive lines whose phrase spans the break
    (reported at the first line)."""
    rel = path.relative_to(ROOT)
    found = [f"{rel}:{n}: {hit!r} in {text.strip()!r}"
             for n, text in lines if (hit := _flag(text, patterns)) is not None]
    for (n, a), (m, b) in zip(lines, lines[1:], strict=False):
        joined = f"{a.rstrip()} {b.lstrip().lstrip('#').lstrip()}"
        if m == n + 1 and _flag(a, patterns) is None and _flag(b, patterns) is None:
            if (hit := _flag(joined, patterns)) is not None:
                found.append(f"{rel}:{n}: {hit!r} in {joined.strip()!r}")
    return found


def _md_lines(path: Path) -> list[tuple[int, str]]:
    return list(enumerate(path.read_text().splitlines(), start=1))


@pytest.mark.parametrize("path", _markdown(), ids=lambda p: str(p.relative_to(ROOT)))
def test_docs_tell_no_history(path):
    found = _findings(path, _md_lines(path), HISTORY)
    assert not found, "history in the docs (state the contract; history lives in commit messages):\n" + "\n".join(found)


@pytest.mark.parametrize("path", [p for p in _markdown() if p != PERFORMANCE], ids=lambda p: str(p.relative_to(ROOT)))
def test_timings_live_in_performance_md(path):
    found = _findings(path, _md_lines(path), TIMING)
    assert not found, "timings outside docs/performance.md (move them there, with the command):\n" + "\n".join(found)


@pytest.mark.parametrize("path", _python(), ids=lambda p: str(p.relative_to(ROOT)))
def test_docstrings_and_comments_tell_no_history_or_timings(path):
    found = _findings(path, _python_text(path), HISTORY + TIMING)
    assert not found, ("history or timings in docstrings/comments (state the contract or the design "
                       "reason; figures go to docs/performance.md):\n" + "\n".join(found))


def test_the_patterns_catch_what_they_are_for():
    """The patterns catch the phrases they are for and pass the contract wording they must not."""
    told = ["it used to copy every face twice", "session 4's runs", "What made session 4 faster",
            "as small as the old default", "about 40 % of today's work", "17 ms per frame, 1 ms now",
            "8x faster on CPU", "2.77-2.94 s per sample", "before the earlier session", "previously",
            "0.34-0.36 samples/s", "a sample took 1.75x the CPU time", "the loop took 0.8-0.9 s",
            "in **28 s (0.9 M rays/s)** after a 10 s compilation (goal: < 60 s)", "(47 ms best; goal < 100 ms)"]
    assert not [t for t in told if _flag(t, HISTORY + TIMING) is None]
    contract = ["Grid and bisection steps used to locate the first stationary point",
                "deletes the temporary files a killed run left behind", "One CARLA session",
                "skipped (complete from an earlier run)",
                "t in nanoseconds, 0.1 s apart", "the files of the samples it cut off are deleted",
                "the timestamps are in seconds", "marks the folder as a jaxfish dataset from now on",
                "whether it was fixed", "Each marker records what made its sample",
                "a rich progress bar (samples/s)", "Goal: fusion under 100 ms after compile",
                "Goal: >= 1 sample/s after compile", "under 60 s on the 2-core CPU"]
    assert not [t for t in contract if _flag(t, HISTORY + TIMING) is not None]
