"""Every script in ``benchmarks/`` imports and parses its arguments (``--help``), and runs through at
its smallest size (no timing is checked: the numbers go to docs/performance.md).

The benchmarks are run by hand (their results go to docs/performance.md, never into tests), so an
API change that breaks one of their imports would otherwise go unnoticed until the next measurement.
"""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

from tests.conftest import headless_gl_or_skip, ict_archive_or_skip

BENCHMARKS = sorted(p for p in (Path(__file__).resolve().parents[1] / "benchmarks").glob("*.py")
                    if not p.name.startswith("_"))  # _threads.py, _timing.py: helper modules


def test_there_are_benchmarks():
    assert len(BENCHMARKS) >= 10


@pytest.mark.parametrize("script", BENCHMARKS, ids=lambda p: p.name)
def test_benchmark_script_imports_and_shows_its_usage(script):
    done = subprocess.run([sys.executable, str(script), "--help"], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    assert done.stdout.startswith("usage:")


#: Benchmarks that need a rendered held-out set: they stay at ``--help``.
HELP_ONLY = {"network_metrics.py", "visibility_breakdown.py"}

#: The smallest run of each other benchmark that goes through its whole body (``--help`` alone stops
#: at argparse), and what it needs.
SMOKE = {
    "accuracy_network.py": (["--heads", "1", "--model", "builtin"], "gl"),
    "accuracy_oracle.py": (["--heads", "1", "--model", "builtin"], None),
    "bench_fit.py": (["--heads", "1", "--batch", "2", "--repeats", "1", "--model", "builtin", "--threads", "1",
                     "--blas-threads", "1"], None),
    "bench_fit_batch.py": (["--device", "cpu", "--batch", "2", "--repeats", "1", "--model", "builtin"], None),
    "bench_lm_head.py": (["--repeats", "1", "--batch", "2", "--model", "builtin"], None),
    "bench_models.py": ([], None),
    "bench_reconstruct.py": (["--repeats", "1", "--model", "builtin"], None),
    "bench_synth.py": (["--workers", "1", "--count", "4", "--small", "2", "--model", "builtin", "--skip-single"], "gl"),
    "bench_vertex_normals.py": (["--repeats", "1", "--warmup", "0", "--batches", "1"], "ict"),
    "tune_network_fit.py": (["--heads", "1", "--priors", "1"], "gl+ict"),
}


def test_every_benchmark_is_run_or_known_to_need_data():
    """A new script gets a smoke run or a place in HELP_ONLY, not silently only --help."""
    assert set(SMOKE) | HELP_ONLY == {p.name for p in BENCHMARKS} and not set(SMOKE) & HELP_ONLY


@pytest.mark.parametrize("name", sorted(SMOKE))
def test_benchmark_runs_through_at_its_smallest(name, tmp_path):
    argv, needs = SMOKE[name]
    if needs and "gl" in needs:
        headless_gl_or_skip()
    if needs and "ict" in needs:
        ict_archive_or_skip()
    script = BENCHMARKS[0].parent / name
    done = subprocess.run([sys.executable, str(script), *argv], capture_output=True, text=True, timeout=600,
                          cwd=tmp_path)
    assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-3000:]
    assert not re.search(r"\bnan\b", done.stdout, re.IGNORECASE)  # a benchmark that measured nothing prints NaN
