"""Every Python file of the project compiles without warnings: an invalid escape sequence in a
docstring (``\\omega``, or ``\\times`` read as a tab and ``imes``) is a SyntaxWarning, not an error,
and would otherwise garble the rendered maths silently."""

import warnings
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SOURCES = sorted(p for folder in ("src", "tests", "benchmarks", "examples", "docs", "scripts")
                 for p in (ROOT / folder).rglob("*.py"))


def test_there_are_sources():
    assert any(p.name == "pose.py" for p in SOURCES)


@pytest.mark.parametrize("path", SOURCES, ids=lambda p: str(p.relative_to(ROOT)))
def test_compiles_without_warnings(path):
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        compile(path.read_text(encoding="utf-8"), str(path), "exec")
