"""The tutorials' snippets run as written, in page order, in one session per page.

Python blocks run in one namespace; a ``facenormals ...`` shell block runs as the CLI when every
file it reads exists (blocks with placeholders such as ``PRED GT`` or ``front.jpg`` are
illustrations and are skipped). Everything runs in a temporary folder holding a link to
``examples/``, so the pages' relative paths (``examples/data/astronaut.jpg``, ``out/...``) work.
"""

from __future__ import annotations

import contextlib
import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

from tests.conftest import headless_gl_or_skip, ict_archive_or_skip

ROOT = Path(__file__).resolve().parents[1]
TUTORIALS = ROOT / "docs" / "tutorials"
BLOCK = re.compile(r"^```(python|bash)\n(.*?)^```", re.MULTILINE | re.DOTALL)


def blocks(page: str) -> list[tuple[str, str]]:
    """The ``(language, code)`` of each python or bash block of a tutorial page, in order."""
    return [(m.group(1), m.group(2)) for m in BLOCK.finditer((TUTORIALS / page).read_text())]


def runnable_command(code: str) -> list[str] | None:
    """The argv of a one-command ``facenormals`` block whose input files exist, else ``None``."""
    argv = shlex.split(code.replace("\\\n", " "))
    if not argv or argv[0] != "facenormals" or "[" in code:
        return None
    outputs = {argv[i + 1] for i, a in enumerate(argv[:-1]) if a in ("-o", "--out", "--json", "--export")}
    inputs = [a for a in argv[2:] if not a.startswith("-") and ("/" in a or "." in a) and a not in outputs
              and not re.fullmatch(r"[\d.,]+", a)]
    return argv if all(Path(a).exists() for a in inputs) else None


@contextlib.contextmanager
def in_folder(path: Path):
    old = Path.cwd()
    os.chdir(path)
    try:
        yield
    finally:
        os.chdir(old)


def run_page(page: str, tmp_path: Path) -> tuple[int, int]:
    """Run a page's blocks; returns (python blocks run, commands run)."""
    (tmp_path / "examples").symlink_to(ROOT / "examples")
    namespace: dict = {"__name__": f"tutorial_{page}"}
    ran = [0, 0]
    with in_folder(tmp_path):
        for language, code in blocks(page):
            if language == "python":
                exec(compile(code, f"{page} block", "exec"), namespace)
                ran[0] += 1
            elif (argv := runnable_command(code)) is not None:
                run = subprocess.run([sys.executable, "-m", "facenormals", *argv[1:]], capture_output=True, text=True,
                                     timeout=600)
                assert run.returncode == 0, f"{page}: `{code.strip()}` exited {run.returncode}:\n{run.stderr}"
                ran[1] += 1
    return ran[0], ran[1]


def test_the_block_parser():
    assert runnable_command("facenormals evaluate PRED GT [--model MODEL]") is None
    assert runnable_command("facenormals reconstruct front.jpg left.jpg -o out/person") is None
    assert runnable_command("pip install facenormals") is None
    assert runnable_command("facenormals reconstruct README.md -o out/x --box 1,2,3,4") is not None


@pytest.fixture
def headless_gl():
    headless_gl_or_skip()


def test_compose(tmp_path, headless_gl):
    ict_archive_or_skip()
    assert run_page("compose.md", tmp_path) == (9, 0)
    assert (tmp_path / "out" / "compose" / "head.ply").is_file()
    assert (tmp_path / "out" / "compose" / "overlay.png").is_file()


def test_reconstruct(tmp_path):
    python, commands = run_page("reconstruct.md", tmp_path)
    assert (python, commands) == (2, 3)
    assert {p.name for p in (tmp_path / "out" / "astronaut").iterdir()} >= {"head.ply", "head.obj", "params.json"}


def test_multiview_then_evaluate(tmp_path, headless_gl):
    ict_archive_or_skip()
    assert run_page("multiview.md", tmp_path) == (3, 1)
    (tmp_path / "examples").unlink()
    assert run_page("evaluate.md", tmp_path) == (1, 1)
    assert (tmp_path / "out" / "multiview" / "report.json").is_file()


def test_every_code_block_is_run_or_shown_as_text():
    """A tutorial block fenced otherwise (```py, ```sh, ```console) would never run here unnoticed."""
    for page in sorted(TUTORIALS.glob("*.md")):
        fences = re.findall(r"^```(\S*)$", page.read_text(), re.MULTILINE)
        openings = fences[::2]  # fences alternate: opening (with the language), closing
        assert set(openings) <= {"python", "bash", "text"}, (page.name, openings)
