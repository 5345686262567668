import pytest

from facenormals.cli import main
from facenormals.demo import run_demo
from facenormals.models import builtin_head_model


def test_demo_recovers_the_builtin_head(tmp_path):
    report = run_demo(builtin_head_model(), seed=1, out_dir=tmp_path, log=lambda *_: None)
    assert report.fitted_rmse_mm < 0.6 * report.mean_head_rmse_mm
    assert report.landmark_error_px < 1.0
    assert report.yaw_error_deg < 2.0
    assert report.mesh_path.exists() and report.mesh_path.stat().st_size > 1000


def test_cli_demo_writes_the_mesh(tmp_path, capsys):
    assert main(["demo", "--model", "builtin", "--out", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "visible-vertex RMSE, fitted" in out and (tmp_path / "demo_fit.ply").exists()


def test_cli_bad_model_path_is_a_clear_error(tmp_path, capsys):
    assert main(["demo", "--model", str(tmp_path / "missing.npz")]) == 1
    assert "missing.npz: model file not found" in capsys.readouterr().err


def test_cli_requires_a_command():
    with pytest.raises(SystemExit):
        main([])
