"""The scripts in ``examples/`` run as documented and produce what they claim.

Each runs in a subprocess with the built-in head (no download, a few seconds each), so an API change
that breaks an example fails here rather than in a user's hands.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


def run_example(script: str, *args: str, cwd: Path) -> str:
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    done = subprocess.run([sys.executable, str(EXAMPLES / script), *args], cwd=cwd, env=env, capture_output=True,
                          text=True, timeout=600)
    assert done.returncode == 0, f"{script} exited with {done.returncode}:\n{done.stdout[-3000:]}\n{done.stderr[-3000:]}"
    return done.stdout


def rmse_lines(out: str) -> dict[str, tuple[float, float]]:
    """``{'mean head': (p2p, corr), 'fitted head': (p2p, corr)}`` from step 5 of paper_pipeline.py."""
    found = re.findall(r"5\. (mean head|fitted head): point-to-plane RMSE ([\d.]+) mm, correspondence RMSE ([\d.]+) mm",
                       out)
    return {name: (float(p2p), float(corr)) for name, p2p, corr in found}


def test_every_example_is_listed_and_tested():
    listed = (EXAMPLES / "README.md").read_text()
    scripts = sorted(p.name for p in EXAMPLES.glob("*.py"))
    assert scripts == ["compose_ops.py", "demo_synthetic_fit.py", "paper_pipeline.py", "train_unet.py"]
    for name in scripts:
        assert f"`{name}`" in listed, f"examples/README.md does not list {name}"


def test_compose_ops_recovers_the_yaw(tmp_path):
    out = run_example("compose_ops.py", cwd=tmp_path)
    recovered, true = map(float, re.search(r"recovered yaw \(deg\): (\S+) true: (\S+)", out).groups())
    assert true == 20.0 and abs(recovered - true) < 0.1
    assert "CONVERGED" in out


def test_demo_synthetic_fit_beats_the_mean_head(tmp_path):
    out = run_example("demo_synthetic_fit.py", "--model", "builtin", "--out", str(tmp_path / "demo"), cwd=tmp_path)
    fitted = float(re.search(r"fitted_rmse_mm=([\d.]+)", out).group(1))
    mean = float(re.search(r"mean_head_rmse_mm=([\d.]+)", out).group(1))
    assert fitted < 0.6 * mean
    assert (tmp_path / "demo" / "demo_fit.ply").stat().st_size > 1000
    assert (tmp_path / "demo" / "demo_overlay.png").exists()


@pytest.mark.parametrize("views", [["20"], ["-45", "0", "45"]])
def test_paper_pipeline_fits_and_writes_every_view(tmp_path, views):
    out = run_example("paper_pipeline.py", "--model", "builtin", "--views", *views, "--out", str(tmp_path / "pp"),
                      cwd=tmp_path)
    scores = rmse_lines(out)
    assert set(scores) == {"mean head", "fitted head"}
    assert scores["fitted head"][0] < 0.6 * scores["mean head"][0]
    assert scores["fitted head"][1] < scores["mean head"][1]
    assert (tmp_path / "pp" / "head.ply").stat().st_size > 1000
    for v in range(len(views)):
        assert (tmp_path / "pp" / f"overlay_view{v}.png").exists()
        assert (tmp_path / "pp" / f"normals_view{v}.png").exists()


def test_train_unet_quick_run_exports_loadable_weights(tmp_path):
    from facenormals.nn import load_weights

    out = run_example("train_unet.py", "--count", "24", "--holdout-count", "8", "--steps", "2", "--batch-size", "4",
                      "--workers", "1", "--model", "builtin", "--out", str(tmp_path / "run"), cwd=tmp_path)
    assert "trained to step 2" in out and "held out:" in out
    net = load_weights(tmp_path / "run" / "normal_landmark_unet.pt")
    assert net.metadata.get("step") == 2
