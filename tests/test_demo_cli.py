import json

import pytest
import torch

from facenormals.cli import main
from facenormals.demo import run_demo
from facenormals.models import builtin_head_model


def test_demo_recovers_the_builtin_head(tmp_path):
    import torch

    mine = builtin_head_model(dtype=torch.float64)  # the caller's model: used in float32, left in float64
    report = run_demo(mine, seed=1, out_dir=tmp_path, log=lambda *_: None)
    assert mine.mean.dtype == torch.float64
    assert report.fitted_rmse_mm < 0.6 * report.mean_head_rmse_mm
    assert report.fitted_correspondence_mm < report.mean_head_correspondence_mm
    assert report.landmark_error_px < 1.0
    assert report.yaw_error_deg < 2.0
    assert report.mesh_path.exists() and report.mesh_path.stat().st_size > 1000
    assert report.overlay_path.exists()


def test_cli_demo_writes_the_mesh(tmp_path, capsys):
    assert main(["demo", "--model", "builtin", "--out", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "fitted head" in out and (tmp_path / "demo_fit.ply").exists()


def test_cli_bad_model_path_is_a_clear_error(tmp_path, capsys):
    assert main(["demo", "--model", str(tmp_path / "missing.npz")]) == 1
    assert "missing.npz: model file not found" in capsys.readouterr().err


def test_cli_requires_a_command():
    with pytest.raises(SystemExit):
        main([])


def test_version_is_the_installed_distributions(capsys):
    from importlib.metadata import version

    with pytest.raises(SystemExit) as exit_:
        main(["--version"])
    assert exit_.value.code == 0
    assert capsys.readouterr().out.strip() == f"facenormals {version('facenormals')}"


def test_the_command_starts_without_torch_and_ctrl_c_while_it_loads_is_one_line(monkeypatch, capsys):
    """Regression: ``import facenormals`` imported torch (seconds), and the parser was built outside
    the Ctrl-C handler, so Ctrl-C in a command's first ~2 s printed a 30-line traceback."""
    import subprocess
    import sys

    import facenormals.cli as cli

    probe = ("import sys, facenormals, facenormals.cli; loaded = 'torch' in sys.modules; "
             "import facenormals as fn; print(loaded, fn.fitting.__name__, callable(fn.project_points), "
             "hasattr(fn, 'no_such_op'), 'sample_bicubic' in dir(fn), hasattr(fn, 'fitting.oracle'), "
             "hasattr(fn, 'a.b'))")
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True).stdout
    assert out.split() == ["False", "facenormals.fitting", "True", "False", "True", "False", "False"]

    def interrupted():
        raise KeyboardInterrupt

    monkeypatch.setattr(cli, "build_parser", interrupted)
    assert main(["reconstruct", "photo.jpg"]) == 130
    captured = capsys.readouterr()
    assert captured.err.splitlines() == ["facenormals: interrupted (files already written are kept; rerun to "
                                         "resume where that applies)"] and captured.out == ""


def test_help_and_version_do_not_import_torch():
    """Regression: the parser read ``train``'s defaults through ``facenormals.training``, whose
    package imported torch, so ``facenormals --help`` and ``--version`` took ~2.7 s. The training
    package's names still load on first use."""
    import subprocess
    import sys

    probe = ("import sys, contextlib, io, facenormals.cli as c\n"
             "with contextlib.redirect_stdout(io.StringIO()), contextlib.suppress(SystemExit):\n"
             "    c.main(['--help'])\n"
             "loaded = 'torch' in sys.modules\n"
             "import facenormals.training as t\n"
             "print(loaded, t.train.__module__, t.TrainConfig.__module__, hasattr(t, 'no_such_name'))")
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True).stdout
    assert out.split() == ["False", "facenormals.training.loop", "facenormals.training.config", "False"]


def test_models_list_and_show(capsys):
    assert main(["models", "list"]) == 0
    out = capsys.readouterr().out
    assert "builtin" in out and "ict" in out
    assert main(["models", "show", "builtin"]) == 0
    out = capsys.readouterr().out
    assert "vertices      10242" in out and "right_ear_top" in out and "source" in out


def test_models_fetch_without_network_names_from(tmp_path, monkeypatch, capsys):
    import urllib.error
    import urllib.request

    def offline(*args, **kwargs):
        raise urllib.error.URLError("no network")

    monkeypatch.setenv("FACENORMALS_HOME", str(tmp_path))
    monkeypatch.setattr(urllib.request, "urlopen", offline)
    assert main(["models", "fetch", "ict"]) == 1
    assert "--from" in capsys.readouterr().err
    assert not any(p.suffix == ".part" for p in tmp_path.rglob("*"))


def test_models_fetch_from_local_copy(tmp_path, monkeypatch, capsys):
    from tests.conftest import SHARED_DATA

    raw = SHARED_DATA / "ict_facekit" / "raw_subset" / "FaceXModel"
    if not raw.exists():
        pytest.skip("raw ICT subset not available")
    monkeypatch.setenv("FACENORMALS_HOME", str(tmp_path))
    assert main(["models", "fetch", "ict", "--from", str(raw)]) == 0
    assert (tmp_path / "ict" / "ict_face_head.npz").exists()
    assert "ready" in capsys.readouterr().out


def test_evaluate_command(tmp_path, capsys):
    model = builtin_head_model()
    ref = tmp_path / "ref.ply"
    pred = tmp_path / "pred.obj"
    model.export_mesh(ref)
    model.export_mesh(pred, model.shape_std * 0.5)
    assert main(["evaluate", str(pred), str(ref), "--model", "builtin", "--json", str(tmp_path / "r.json")]) == 0
    out = capsys.readouterr().out
    assert "similarity" in out and (tmp_path / "r.json").exists()
    assert main(["evaluate", str(tmp_path / "nope.ply"), str(ref), "--model", "builtin"]) == 1
    assert "nope.ply: mesh file not found" in capsys.readouterr().err
    bad = tmp_path / "landmarks.json"
    bad.write_text("not json")
    for landmarks in (bad, tmp_path):
        assert main(["evaluate", str(pred), str(ref), "--model", "builtin", "--prediction-landmarks", str(landmarks)]) == 1
        assert f"{landmarks}: expected a JSON object of landmark name -> vertex index" in capsys.readouterr().err
    outside = tmp_path / "outside.json"
    outside.write_text(json.dumps({**model.landmarks, "chin": 10**7}))
    assert main(["evaluate", str(pred), str(ref), "--model", "builtin", "--prediction-landmarks", str(outside)]) == 1
    assert f"{outside}: expected vertex indices in [0, {model.num_vertices}) of {pred}, got {{'chin': 10000000}}" \
        in capsys.readouterr().err
    incomplete = tmp_path / "incomplete.json"  # no chin: the error names the file it is missing from
    incomplete.write_text(json.dumps({k: v for k, v in model.landmarks.items() if k != "chin"}))
    assert main(["evaluate", str(pred), str(ref), "--model", "builtin", "--prediction-landmarks", str(incomplete)]) == 1
    assert f"{pred} (landmarks {incomplete}) against {ref}: correspondences: prediction landmarks: expected landmark " \
           "'chin'" in capsys.readouterr().err


def test_evaluate_names_the_model_file_that_lacks_an_alignment_landmark(tmp_path, capsys):
    """Regression: the error named internal arguments ("correspondences: source_landmarks: ...")
    instead of the --model file without the landmark."""
    from facenormals.models import builtin_head_model
    from facenormals.mesh import save_mesh

    model = builtin_head_model()
    few = tmp_path / "few.npz"
    model.with_annotations({k: v for k, v in model.landmarks.items() if k != "right_eye_inner"},
                           face_region=model.face_region).save(few)
    ref, pred = tmp_path / "ref.ply", tmp_path / "pred.ply"
    save_mesh(ref, model.mean, model.faces)
    save_mesh(pred, model.mean * 1.05, model.faces)
    assert main(["evaluate", str(pred), str(ref), "--model", str(few)]) == 1
    err = capsys.readouterr().err
    assert f"--model {few}: expected landmark 'right_eye_inner' (or its iBUG-68 equivalent)" in err
    assert "source_landmarks" not in err and "Traceback" not in err


def test_evaluate_json_keeps_the_model_file_and_makes_new_folders(tmp_path, capsys):
    """--json equal to --model wrote the report over the model file; --json in folders that did not
    exist yet failed after all the work and lost the report."""
    model = builtin_head_model()
    ref, pred, saved = tmp_path / "ref.ply", tmp_path / "pred.ply", tmp_path / "model.npz"
    model.export_mesh(ref)
    model.export_mesh(pred, model.shape_std * 0.5)
    model.save(saved)
    before = saved.read_bytes()
    assert main(["evaluate", str(pred), str(ref), "--model", str(saved), "--json", str(saved)]) == 1
    assert f"--json: {saved} is also an input of this command" in capsys.readouterr().err
    assert saved.read_bytes() == before
    report = tmp_path / "new" / "sub" / "r.json"
    assert main(["evaluate", str(pred), str(ref), "--model", "builtin", "--json", str(report)]) == 0
    assert json.loads(report.read_text())


def test_train_refuses_absurd_workers_and_exporting_over_its_init_weights(tmp_path, capsys):
    """--workers 99999 started processes until the machine ran out of memory; --export equal to --init
    overwrote the weights the run started from."""
    assert main(["train", "--data", str(tmp_path / "d"), "--out", str(tmp_path / "run"), "--steps", "1",
                 "--workers", "99999", "--quiet"]) == 1
    assert "workers: expected at most 256" in capsys.readouterr().err
    weights = tmp_path / "w.pt"
    weights.write_bytes(b"weights")
    assert main(["train", "--data", str(tmp_path / "d"), "--out", str(tmp_path / "run"), "--steps", "1",
                 "--init", str(weights), "--export", str(weights), "--quiet"]) == 1
    assert f"--export: {weights} holds the --init weights" in capsys.readouterr().err
    assert weights.read_bytes() == b"weights" and not (tmp_path / "run").exists()


def test_train_errors_name_the_options(tmp_path, capsys):
    """TrainConfig names its fields (batch_size); the command names its options (--batch-size)."""
    for option, value, message in (("--batch-size", "0", "expected a positive integer"),
                                   ("--min-lr-ratio", "2", "expected a value in [0, 1]"),
                                   ("--device", "tpu", "expected 'auto', 'cpu'")):
        assert main(["train", "--data", str(tmp_path / "d"), "--out", str(tmp_path / "run"), option, value,
                     "--quiet"]) == 1
        err = capsys.readouterr().err
        assert f"{option}: {message}" in err, err


def test_library_errors_and_ctrl_c_are_one_line_and_an_exit_status(monkeypatch, capsys):
    import facenormals.cli as cli

    def fail(error):
        def command(args):
            raise error
        return command

    for error, status in ((RuntimeError("no headless OpenGL"), 1), (FloatingPointError("loss is not finite"), 1),
                          (KeyboardInterrupt(), 130)):
        monkeypatch.setattr(cli, "_cmd_demo", fail(error))
        assert main(["demo", "--out", "unused"]) == status
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and err.startswith("facenormals demo: ")
        assert ("interrupted" in err) == (status == 130)
    monkeypatch.setenv("FACENORMALS_TRACEBACK", "0")
    assert main(["demo", "--out", "unused"]) == 130  # "0" means off
    capsys.readouterr()
    monkeypatch.setenv("FACENORMALS_TRACEBACK", "1")
    monkeypatch.setattr(cli, "_cmd_demo", fail(RuntimeError("boom")))
    with pytest.raises(RuntimeError, match="boom"):
        main(["demo", "--out", "unused"])


def test_train_refuses_a_bad_export_path_before_training(tmp_path, capsys):
    log = tmp_path / "log.csv"
    log.write_text("step,loss\n")
    (tmp_path / "afile").write_text("x")
    cases = [(log, "exists and is not a facenormals weight file"), (tmp_path / "afile" / "w.pt", "is a file, not a folder"),
             (tmp_path, "is a folder"), (tmp_path / "run" / "last.pt", "is the run's checkpoint")]
    for export, message in cases:
        status = main(["train", "--data", str(tmp_path / "no-data"), "--out", str(tmp_path / "run"), "--steps", "1",
                       "--export", str(export), "--quiet"])
        err = capsys.readouterr().err
        assert status == 1 and f"--export: {export}" in err and message in err, err
    assert log.read_text() == "step,loss\n" and not (tmp_path / "run").exists()


def test_train_stopped_by_a_signal_exits_130_without_exporting(tmp_path, monkeypatch, capsys):
    import facenormals.training as training
    from facenormals.training import TrainSummary

    def stopped(config, progress=True):
        return TrainSummary(step=3, samples_seen=12, finished=False, stopped_by="signal", seconds=1.0, metrics=None,
                            checkpoint=tmp_path / "run" / "last.pt")

    monkeypatch.setattr(training, "train", stopped)
    status = main(["train", "--data", str(tmp_path), "--out", str(tmp_path / "run"), "--steps", "10",
                   "--export", str(tmp_path / "w.pt"), "--quiet"])
    assert status == 130 and not (tmp_path / "w.pt").exists()
    assert "interrupted: rerun the same command to resume (and export)" in capsys.readouterr().err


def test_output_paths_are_checked_before_any_work(tmp_path, capsys):
    (tmp_path / "afile").write_text("x")
    assert main(["demo", "--model", "builtin", "--out", str(tmp_path / "afile")]) == 1
    assert "--out: " in capsys.readouterr().err
    for json_path, message in ((tmp_path, "is a folder"), (tmp_path / "afile" / "r.json", "is a file, not a folder")):
        status = main(["evaluate", str(tmp_path / "missing.ply"), str(tmp_path / "missing.ply"), "--json", str(json_path)])
        err = capsys.readouterr().err
        assert status == 1 and "--json: " in err and message in err, err


def test_reconstruct_checks_its_output_folder_before_reading_the_photos(tmp_path, capsys, monkeypatch):
    from facenormals import reconstruct

    def no_work(*args, **kwargs):
        raise AssertionError("the photos were processed")

    monkeypatch.setattr(reconstruct, "reconstruct_photos", no_work)
    (tmp_path / "afile").write_text("x")
    for out, message in ((tmp_path / "afile" / "sub", "is a file, not a folder"), (tmp_path / "afile", "is not a folder"),
                         ("", "expected a folder name, got an empty string")):
        status = main(["reconstruct", str(tmp_path / "a.jpg"), "-o", str(out)])
        err = capsys.readouterr().err
        assert status == 1 and "-o/--out: " in err and message in err, err


def test_prediction_landmarks_must_be_integer_indices(tmp_path, capsys):
    model = builtin_head_model()
    model.export_mesh(tmp_path / "ref.ply")
    model.export_mesh(tmp_path / "pred.ply")
    for value in (1.7, True):
        (tmp_path / "lm.json").write_text(json.dumps({"nose_tip": value}))
        status = main(["evaluate", str(tmp_path / "pred.ply"), str(tmp_path / "ref.ply"), "--model", "builtin",
                       "--prediction-landmarks", str(tmp_path / "lm.json")])
        assert status == 1 and "non-integer vertex indices" in capsys.readouterr().err


def test_json_report_writes_null_not_nan():
    from facenormals.cli import _json_safe

    out = json.dumps(_json_safe({"a": float("nan"), "b": [1.0, float("inf")], "c": {"d": 2.5}}), allow_nan=False)
    assert json.loads(out) == {"a": None, "b": [1.0, None], "c": {"d": 2.5}}


def test_evaluate_needs_landmarks_for_a_prediction_with_other_triangles(tmp_path, capsys):
    model = builtin_head_model()
    ref, pred = tmp_path / "ref.ply", tmp_path / "pred.ply"
    model.export_mesh(ref)
    order = torch.randperm(model.num_vertices, generator=torch.Generator().manual_seed(0))
    from facenormals.mesh import save_mesh

    save_mesh(pred, model.mean[order], torch.argsort(order)[model.faces])  # same surface, another vertex order
    assert main(["evaluate", str(pred), str(ref), "--model", "builtin"]) == 1
    assert "has the model's vertex count but not its vertex order" in capsys.readouterr().err
    rotated = tmp_path / "rotated.ply"
    shuffled = torch.randperm(len(model.faces), generator=torch.Generator().manual_seed(1))
    save_mesh(rotated, model.mean, model.faces[shuffled][:, [1, 2, 0]])
    assert main(["evaluate", str(rotated), str(ref), "--model", "builtin"]) == 0  # same vertex order
    landmarks = tmp_path / "lm.json"
    landmarks.write_text(json.dumps({k: int(torch.argsort(order)[v]) for k, v in model.landmarks.items()}))
    assert main(["evaluate", str(pred), str(ref), "--model", "builtin", "--prediction-landmarks", str(landmarks)]) == 0
    out = capsys.readouterr().out
    assert "warning" not in out and "ICP converged" in out
    # the reference, whose face region and landmarks are taken from the model by index, too: a reordered
    # one scored 27 mm and exited 0 with a warning
    assert main(["evaluate", str(ref), str(pred), "--model", "builtin"]) == 1
    assert f"{pred}: has the vertex count of model 'builtin' but not its vertex order" in capsys.readouterr().err
    # a reference in the model's vertex order with only some of its triangles (a face crop) is the model's
    crop = tmp_path / "crop.ply"
    save_mesh(crop, model.mean, model.faces[model.face_region[model.faces].all(1)])
    assert main(["evaluate", str(ref), str(crop), "--model", "builtin"]) == 0
    assert main(["evaluate", str(crop), str(ref), "--model", "builtin"]) == 0


def test_a_closed_stdout_exits_quietly_with_sigpipe_status():
    """`facenormals models show X | head`: the reader goes away; no "error: Broken pipe" line."""
    import os
    import subprocess
    import sys

    read_end, write_end = os.pipe()
    os.close(read_end)  # every write to stdout fails with EPIPE
    try:
        run = subprocess.run([sys.executable, "-m", "facenormals", "models", "show", "builtin"], stdout=write_end,
                             stderr=subprocess.PIPE, text=True, timeout=120)
    finally:
        os.close(write_end)
    assert run.returncode == 141 and run.stderr == ""


def test_a_broken_pipe_that_is_not_stdout_is_an_error(monkeypatch, capsys):
    """Only a closed stdout exits quietly; a broken pipe elsewhere (a helper process, a socket) is an
    error like any other, and stdout stays usable (main() may be called from Python)."""
    import facenormals.cli as cli

    def broken(args):
        raise BrokenPipeError(32, "Broken pipe to a helper process")

    parser = cli.build_parser()
    real_parse = parser.parse_args
    monkeypatch.setattr(cli, "build_parser", lambda: parser)
    monkeypatch.setattr(parser, "parse_args", lambda argv: (lambda a: (setattr(a, "func", broken), a)[1])(real_parse(argv)))
    assert cli.main(["models", "list"]) == 1
    captured = capsys.readouterr()
    assert "facenormals models: error: [Errno 32] Broken pipe to a helper process" in captured.err
    print("still here")
    assert capsys.readouterr().out == "still here\n"


def test_outputs_that_are_empty_inputs_or_unwritable_are_refused_before_any_work(tmp_path, capsys, monkeypatch):
    """`evaluate --json pred.ply` overwrote the prediction; empty names wrote into the current folder
    or skipped the write with exit 0; an unwritable folder failed only after the whole fit."""
    from pathlib import Path

    from facenormals import reconstruct

    model = builtin_head_model()
    pred, ref = tmp_path / "pred.ply", tmp_path / "ref.ply"
    model.export_mesh(pred)
    model.export_mesh(ref)
    before = pred.read_bytes()
    assert main(["evaluate", str(pred), str(ref), "--model", "builtin", "--json", str(pred)]) == 1
    assert f"--json: {pred} is also an input of this command" in capsys.readouterr().err
    assert pred.read_bytes() == before
    monkeypatch.chdir(tmp_path)
    commands = [
        (["evaluate", str(pred), str(ref), "--model", "builtin", "--json", ""], "--json: expected a file name"),
        (["demo", "--model", "builtin", "--out", ""], "--out: expected a folder name"),
        (["synth", "--count", "1", "--out", "", "--model", "builtin", "--quiet"], "--out: expected a folder name"),
        (["train", "--data", "d", "--out", "", "--steps", "1", "--quiet"], "--out: expected a folder name"),
        (["train", "--data", "d", "--out", "run", "--steps", "1", "--quiet", "--export", ""],
         "--export: expected a file name"),
    ]
    for argv, message in commands:
        assert main(argv) == 1, argv
        assert message in capsys.readouterr().err, argv
    assert sorted(p.name for p in tmp_path.iterdir()) == ["pred.ply", "ref.ply"]  # nothing written here
    if Path("/proc/self").is_dir():  # a folder where nothing can be created, found before the photos are read
        monkeypatch.setattr(reconstruct, "reconstruct_photos", lambda *a, **k: pytest.fail("the photos were read"))
        assert main(["reconstruct", "a.jpg", "-o", "/proc/facenormals/out"]) == 1
        assert "-o/--out: /proc/facenormals/out cannot be written" in capsys.readouterr().err
    missing = tmp_path / "new" / "deeper"
    assert main(["evaluate", str(tmp_path / "none.ply"), str(ref), "--json", str(missing / "r.json")]) == 1
    capsys.readouterr()
    assert not (tmp_path / "new").exists()  # the probe's folders are removed again


def test_the_output_check_leaves_its_folders_for_the_other_ranks_of_a_launch(tmp_path, monkeypatch):
    """Regression: under torchrun every rank checks --out at once; a rank removing the folder its probe
    had made pulled it from under another rank's probe ("--out: ... cannot be written (No such file or
    directory)", 2 in 300 trials) or its first shard."""
    from facenormals.cli import _check_writable

    monkeypatch.setenv("WORLD_SIZE", "2")
    _check_writable(tmp_path / "run" / "a", "--out", folder=True)
    assert (tmp_path / "run" / "a").is_dir() and not any((tmp_path / "run" / "a").iterdir())
    monkeypatch.setenv("WORLD_SIZE", "1")
    _check_writable(tmp_path / "solo" / "a", "--out", folder=True)
    assert not (tmp_path / "solo").exists()


def test_demo_checks_its_seed_and_writes_both_files_or_neither(tmp_path, capsys):
    for seed, message in (("-1", "seed: expected an integer >= 0"), (str(2**64), "seed: expected an integer below 2**63")):
        assert main(["demo", "--model", "builtin", "--seed", seed, "--out", str(tmp_path / "d")]) == 1
        assert message in capsys.readouterr().err
    out = tmp_path / "d1"
    out.mkdir()
    (out / "demo_fit.ply").write_text("the earlier fit")
    (out / "demo_overlay.png").mkdir()  # the overlay cannot be written
    assert main(["demo", "--model", "builtin", "--seed", "7", "--out", str(out)]) == 1
    capsys.readouterr()
    assert (out / "demo_fit.ply").read_text() == "the earlier fit"
    assert sorted(p.name for p in out.iterdir()) == ["demo_fit.ply", "demo_overlay.png"]  # no temporaries left


def test_train_names_a_checkpoint_without_its_settings(tmp_path, capsys):
    run = tmp_path / "run"
    run.mkdir()
    torch.save({"format": "facenormals-train"}, run / "last.pt")
    assert main(["train", "--data", str(tmp_path), "--out", str(run), "--steps", "1", "--quiet"]) == 1
    assert "last.pt: a facenormals training checkpoint without its settings ('config')" in capsys.readouterr().err


def test_an_empty_facenormals_home_is_unset(monkeypatch):
    from pathlib import Path

    from facenormals.models.registry import cache_dir

    monkeypatch.setenv("FACENORMALS_HOME", "")
    assert cache_dir() == Path.home() / ".cache" / "facenormals"


def test_synth_errors_name_the_command_options(tmp_path, capsys):
    """The library's parameter names (shard_size, config.background_folders) were printed as they are."""
    for extra, message in ((["--shard-size", "0"], "--shard-size: expected an integer >= 1"),
                           (["--backgrounds", str(tmp_path / "none")], f"--backgrounds: {tmp_path / 'none'} is not a folder"),
                           (["--identity-scale", "-1"], "--identity-scale: expected a finite number >= 0"),
                           (["--rank", "3", "--world-size", "2"], "--rank: expected 0 <= rank < world_size = 2")):
        assert main(["synth", "--count", "2", "--out", str(tmp_path / "d"), "--model", "builtin", "--quiet",
                     *extra]) == 1
        assert f"facenormals synth: error: {message}" in capsys.readouterr().err, extra
    assert not (tmp_path / "d").exists()


def test_models_show_describes_a_model_without_shape_components(tmp_path, capsys):
    """min() of the empty shape_std failed: `models show` of a K = 0 model (a rigid template) was an error."""
    from facenormals.models import MorphableModel

    head = builtin_head_model()
    MorphableModel(head.mean, head.shape_basis[:0], head.faces, shape_std=head.shape_std[:0],
                   landmarks=head.landmarks).save(tmp_path / "rigid.npz")
    assert main(["models", "show", str(tmp_path / "rigid.npz")]) == 0
    out = capsys.readouterr().out
    assert "shape         0 components\n" in out and "nose_tip" in out


def test_models_show_of_a_model_file_with_a_single_landmark_name_is_a_clear_error(tmp_path, capsys):
    """A 0-d landmark_names printed a TypeError traceback."""
    import numpy as np

    builtin_head_model().save(tmp_path / "good.npz")
    arrays = dict(np.load(tmp_path / "good.npz"))
    np.savez(tmp_path / "one.npz", **{**arrays, "landmark_names": np.array("nose_tip"),
                                      "landmark_indices": np.array(5)})
    assert main(["models", "show", str(tmp_path / "one.npz")]) == 1
    assert "one.npz: array 'landmark_names' has shape (), expected a 1-D list" in capsys.readouterr().err


def test_demo_names_a_bad_image_size_and_an_empty_output_folder(tmp_path, monkeypatch):
    """``image_size=0`` failed as "intrinsics: expected focal lengths f > 0", and ``out_dir=""``
    (Path("") is the working folder) wrote the demo's files there."""
    monkeypatch.chdir(tmp_path)
    model = builtin_head_model()
    with pytest.raises(ValueError, match="image_size: expected an integer >= 8, got 0"):
        run_demo(model, image_size=0, log=lambda *_: None)
    with pytest.raises(ValueError, match="out_dir: expected a folder name or None, got ''"):
        run_demo(model, out_dir="", log=lambda *_: None)
    assert list(tmp_path.iterdir()) == []


def test_train_help_shows_the_defaults_of_a_new_run(capsys):
    """train --help showed no default (its options default to None, so that a resume keeps the
    checkpoint's settings); it now shows TrainConfig's, which it reads rather than copies."""
    import re

    from facenormals.training import TrainConfig

    with pytest.raises(SystemExit):
        main(["train", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    config = TrainConfig(data="d", out="o")
    for option, field in (("steps", "steps"), ("batch-size", "batch_size"), ("sigma", "sigma"), ("lr", "lr"),
                          ("log-every", "log_every"), ("depth", "depth")):
        assert re.search(rf"--{option} \S+ [^-]*default {re.escape(str(getattr(config, field)))}\b", text), option
    assert "--max-minutes MAX_MINUTES stop with a checkpoint after this wall time; default: no limit" in text
    assert ("takes the network's shape and the optimisation and loss settings (--base-channels, --depth, --lr, "
            "--warmup-steps, --min-lr-ratio, --weight-decay, --ema-decay, --landmark-weight, --landmark-peak-weight, "
            "--foreground-weight, --sigma, --precision) from the checkpoint unless the command gives them; the other "
            "options apply as given") in text


def test_a_resume_takes_the_network_shape_from_the_checkpoint(tmp_path, monkeypatch, capsys):
    """Resuming a run of --base-channels 4 without repeating it failed: "--base-channels: 16 differs from
    the checkpoint's 4" (the default), though the help says a resume keeps the checkpoint's settings."""
    import facenormals.training as training
    from facenormals.training import TrainSummary, train
    from facenormals.training.config import TrainConfig

    from tests.training.conftest import TinyHeads

    first = TrainConfig(data="unused", out=str(tmp_path / "run"), steps=1, batch_size=2, workers=0, device="cpu",
                        precision="fp32", base_channels=4, depth=2)
    train(first, TinyHeads(4), progress=False)
    seen = {}

    def resumed(config, progress=True):
        seen.update(base_channels=config.base_channels, depth=config.depth, steps=config.steps)
        return TrainSummary(step=config.steps, samples_seen=0, finished=True, stopped_by="steps", seconds=0.0,
                            metrics=None, checkpoint=tmp_path / "run" / "last.pt")

    monkeypatch.setattr(training, "train", resumed)
    assert main(["train", "--data", str(tmp_path), "--out", str(tmp_path / "run"), "--steps", "3", "--quiet"]) == 0
    assert seen == {"base_channels": 4, "depth": 2, "steps": 3}


def test_train_names_the_option_that_differs_from_the_checkpoint(tmp_path, monkeypatch, capsys):
    """The architecture refusal named the library's field ("config.base_channels: 8 differs from the
    checkpoint's 16") to a command-line user, who set --base-channels."""
    import facenormals.training as training

    def refuse(config, progress=True):
        raise ValueError(f"config.base_channels: {config.base_channels} differs from the checkpoint's 16 in "
                         f"{config.out}/last.pt; use another --out to start afresh")

    monkeypatch.setattr(training, "train", refuse)
    assert main(["train", "--data", str(tmp_path), "--out", str(tmp_path / "run"), "--base-channels", "8",
                 "--quiet"]) == 1
    assert "facenormals train: error: --base-channels: 8 differs from the checkpoint's 16" in capsys.readouterr().err
