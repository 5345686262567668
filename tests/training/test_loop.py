import csv
import os
import re

import pytest
import torch

from facenormals.nn import load_weights
from facenormals.training import TrainConfig, export_weights, landmark_threshold, load_checkpoint, train
from facenormals.training.loop import _EpochSampler

from .conftest import TinyHeads


def _config(tmp_path, **changes):
    values = dict(data="unused", out=str(tmp_path / "run"), steps=8, batch_size=4, lr=3e-3, warmup_steps=2,
                  workers=0, device="cpu", precision="fp32", log_every=2, checkpoint_every=4, eval_every=4,
                  eval_samples=8, base_channels=4, depth=2, seed=3)
    values.update(changes)
    return TrainConfig(**values)


def test_training_logs_checkpoints_and_lowers_the_loss(tmp_path):
    data = TinyHeads(48)
    summary = train(_config(tmp_path, steps=30, log_every=5), data, holdout=TinyHeads(8, seed=1), progress=False)
    assert summary.finished and summary.step == 30 and summary.samples_seen == 120
    rows = list(csv.DictReader((tmp_path / "run" / "log.csv").open()))
    assert [int(r["step"]) for r in rows] == [5, 10, 15, 20, 25, 30]
    assert float(rows[-1]["loss"]) < 0.7 * float(rows[0]["loss"])
    evals = list(csv.DictReader((tmp_path / "run" / "eval.csv").open()))
    assert int(evals[-1]["step"]) == 30 and int(evals[-1]["samples"]) == 8  # final: the whole holdout
    state = load_checkpoint(tmp_path / "run" / "last.pt")
    assert state["step"] == 30 and state["config"]["steps"] == 30


def test_resume_is_bitwise_identical_for_the_same_config(tmp_path):
    data = TinyHeads(20)
    straight = train(_config(tmp_path / "a"), data, progress=False)  # 5 batches per epoch: crosses an epoch
    config = _config(tmp_path / "b")
    # interrupt after 3 steps through the SIGTERM path, then resume from last.pt
    import signal

    calls = {"n": 0}
    original = torch.optim.AdamW.step

    def step_then_interrupt(self, *args, **kwargs):
        out = original(self, *args, **kwargs)
        calls["n"] += 1
        if calls["n"] == 3:
            signal.raise_signal(signal.SIGTERM)
        return out

    torch.optim.AdamW.step = step_then_interrupt
    try:
        first = train(config, data, progress=False)
    finally:
        torch.optim.AdamW.step = original
    assert first.stopped_by == "signal" and first.step == 3 and not first.finished
    resumed = train(config, data, progress=False)
    assert resumed.step == 8
    # the first log row after the resume averages the one step it saw (not 1 / log_every of it)
    rows = {r["step"]: float(r["loss"]) for r in csv.DictReader((tmp_path / "b" / "run" / "log.csv").open())}
    reference = {r["step"]: float(r["loss"]) for r in csv.DictReader((tmp_path / "a" / "run" / "log.csv").open())}
    assert 0.75 < rows["4"] / reference["4"] < 1.33 and rows["6"] == reference["6"]
    # the step before the stop (3, not a multiple of log_every) is logged at the stop, not lost
    assert list(rows) == ["2", "3", "4", "6", "8"] and 0.75 < rows["3"] / reference["4"] < 1.33
    a, b = load_checkpoint(straight.checkpoint), load_checkpoint(resumed.checkpoint)
    for key in a["model"]:
        torch.testing.assert_close(b["model"][key], a["model"][key], rtol=0, atol=0)
        torch.testing.assert_close(b["ema"][key], a["ema"][key], rtol=0, atol=0)


def test_resume_refuses_another_architecture(tmp_path):
    data = TinyHeads(8)
    train(_config(tmp_path, steps=2), data, progress=False)
    with pytest.raises(ValueError, match="base_channels"):
        train(_config(tmp_path, steps=4, base_channels=8), data, progress=False)


def test_export_weights_round_trip(tmp_path):
    summary = train(_config(tmp_path, steps=2), TinyHeads(8), progress=False)
    path = export_weights(summary.checkpoint, tmp_path / "w.pt", metadata={"note": "test"})
    net = load_weights(path)
    ema = load_checkpoint(summary.checkpoint)["ema"]
    for key, value in net.state_dict().items():
        torch.testing.assert_close(value, ema[key].half().float())
    assert net.metadata["note"] == "test" and net.metadata["step"] == 2
    assert net.metadata["image_size"] == 32  # TinyHeads' side: predict_maps warns on other crops
    calibrated = load_weights(export_weights(summary.checkpoint, tmp_path / "c.pt", calibration_data=TinyHeads(8)))
    thresholds = calibrated.metadata["landmark_threshold"]  # one per landmark channel
    assert len(thresholds) == 24 and all(0.05 <= t <= 0.95 for t in thresholds)
    assert landmark_threshold(calibrated).shape == (24,)
    assert calibrated.metadata["landmark_threshold_samples"] == 8


def test_init_starts_a_new_run_from_exported_weights(tmp_path):
    first = train(_config(tmp_path / "a", steps=3), TinyHeads(8), progress=False)
    weights = export_weights(first.checkpoint, tmp_path / "w.pt", dtype=torch.float32)
    config = _config(tmp_path / "b", steps=1, lr=1e-12, warmup_steps=0, init=str(weights))
    second = train(config, TinyHeads(8), progress=False)
    state = load_checkpoint(second.checkpoint)
    assert state["step"] == 1  # a new schedule, not a resume of the first run
    start = load_checkpoint(first.checkpoint)["ema"]
    for key, value in state["model"].items():  # one step at lr 1e-12 leaves the loaded weights
        torch.testing.assert_close(value, start[key], rtol=1e-6, atol=1e-6)
    with pytest.raises(ValueError, match="init: .*w.pt"):
        train(_config(tmp_path / "c", steps=1, base_channels=8, init=str(weights)), TinyHeads(8), progress=False)


def test_bad_checkpoint_and_weight_files_name_the_file(tmp_path):
    bad = tmp_path / "bad.pt"
    bad.write_bytes(b"not a checkpoint")
    with pytest.raises(ValueError, match="bad.pt"):
        load_checkpoint(bad)
    with pytest.raises(ValueError, match="bad.pt"):
        load_weights(bad)
    with pytest.raises(FileNotFoundError, match="missing.pt"):
        load_weights(tmp_path / "missing.pt")
    folder = tmp_path / "afolder.pt"  # a folder is not "missing": say what it is
    folder.mkdir()
    with pytest.raises(FileNotFoundError, match="afolder.pt: a folder, not a checkpoint"):
        load_checkpoint(folder)
    with pytest.raises(FileNotFoundError, match="afolder.pt: a folder, not a weight file"):
        load_weights(folder)
    with pytest.raises(FileNotFoundError, match="init: .*afolder.pt: a folder, not a weight file"):
        train(_config(tmp_path, init=str(folder)), TinyHeads(8), progress=False)


def test_epoch_sampler_is_a_deterministic_rank_partition_that_resumes():
    size, world = 10, 2
    streams = [_EpochSampler(size, seed=5, rank=r, world_size=world) for r in range(world)]
    firsts = [[i for _, i in zip(range(5), iter(s))] for s in streams]
    assert sorted(firsts[0] + firsts[1]) == list(range(10))  # one epoch: disjoint and complete
    full = [i for _, i in zip(range(12), iter(_EpochSampler(size, 5, 0, world)))]
    resumed = [i for _, i in zip(range(5), iter(_EpochSampler(size, 5, 0, world, start=7)))]
    assert resumed == full[7:12]
    assert full[:5] != full[5:10]  # a new permutation per epoch


def test_a_killed_run_resumes_from_its_checkpoint_and_drops_repeated_log_rows(tmp_path):
    data = TinyHeads(16)
    config = _config(tmp_path, steps=4, log_every=1, checkpoint_every=2)
    train(config, data, progress=False)
    log = tmp_path / "run" / "log.csv"
    # pretend the process died after logging steps 3-4 but before a checkpoint at step 2 was superseded
    state = load_checkpoint(tmp_path / "run" / "last.pt")
    state["step"], state["samples_seen"] = 2, 8
    torch.save(state, tmp_path / "run" / "last.pt")
    train(_config(tmp_path, steps=4, log_every=1, checkpoint_every=2), data, progress=False)
    steps = [int(r["step"]) for r in csv.DictReader(log.open())]
    assert steps == [1, 2, 3, 4]


def test_dataloader_workers_ignore_stop_signals():
    import signal

    from facenormals.training.loop import _ignore_stop_signals

    previous = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        _ignore_stop_signals(0)
        assert signal.getsignal(signal.SIGTERM) is signal.SIG_IGN and signal.getsignal(signal.SIGINT) is signal.SIG_IGN
    finally:
        for s, h in previous.items():
            signal.signal(s, h)


def test_resume_applies_a_changed_weight_decay(tmp_path, monkeypatch):
    data = TinyHeads(8)
    train(_config(tmp_path, steps=2), data, progress=False)
    seen = []
    original = torch.optim.AdamW.step

    def record(self, *args, **kwargs):
        seen.append(self.param_groups[0]["weight_decay"])
        return original(self, *args, **kwargs)

    monkeypatch.setattr(torch.optim.AdamW, "step", record)
    train(_config(tmp_path, steps=4, weight_decay=0.5), data, progress=False)
    assert seen == [0.5, 0.5]  # the optimiser state alone would restore 1e-4


def test_rerunning_a_finished_run_writes_nothing(tmp_path):
    data = TinyHeads(8)
    config = _config(tmp_path, steps=2, eval_every=100)
    train(config, data, holdout=TinyHeads(4, seed=1), progress=False)
    run = tmp_path / "run"
    before = {name: (run / name).read_bytes() for name in ("last.pt", "log.csv", "eval.csv")}
    summary = train(config, data, holdout=TinyHeads(4, seed=1), progress=False)
    assert summary.finished and summary.step == 2
    assert {name: (run / name).read_bytes() for name in before} == before  # no second eval row, no rewrite


def test_a_failed_log_rewrite_keeps_the_log(tmp_path, monkeypatch):
    from facenormals.training.loop import _truncate_csv

    log = tmp_path / "log.csv"
    log.write_text("step,loss\n" + "".join(f"{s},{s / 10}\n" for s in range(1, 11)))

    def fail(*args, **kwargs):
        raise OSError("disk full")

    monkeypatch.setattr(csv.DictWriter, "writerows", fail)
    with pytest.raises(OSError, match="disk full"):
        _truncate_csv(log, 5, ["step", "loss"])
    assert len(log.read_text().splitlines()) == 11  # untouched
    monkeypatch.undo()
    _truncate_csv(log, 5, ["step", "loss"])
    assert [int(r["step"]) for r in csv.DictReader(log.open())] == [1, 2, 3, 4, 5]


def test_a_row_cut_off_by_a_kill_is_dropped_not_run_into(tmp_path):
    """Regression: a last row without its line end (a kill in the middle of a write) was kept, and
    the next row appended after a resume ran into it (``3,0.2`` + ``4,0.1`` read as one row)."""
    from facenormals.training.loop import _truncate_csv

    log = tmp_path / "log.csv"
    log.write_text("step,loss\n1,0.5\n2,0.4\n3,0.")
    _truncate_csv(log, 5, ["step", "loss"])
    assert log.read_bytes() == b"step,loss\r\n1,0.5\r\n2,0.4\r\n"
    log.write_text("step,lo")  # not even the header whole: like an empty log
    _truncate_csv(log, 5, ["step", "loss"])
    assert not log.exists()
    log.write_text("step,loss\r\n1,0.5\r\n")  # whole rows with csv's own line ends: untouched
    _truncate_csv(log, 5, ["step", "loss"])
    assert log.read_bytes() == b"step,loss\r\n1,0.5\r\n"


def test_a_foreign_or_damaged_log_is_named_and_an_old_one_gets_the_new_columns(tmp_path):
    """Regression: rows were appended under a foreign header, and a damaged row or a log without a
    step column failed with a bare KeyError / int() message."""
    from facenormals.training.loop import _LOG_FIELDS

    run = tmp_path / "run"
    run.mkdir()
    (run / "log.csv").write_text("precious\n")
    with pytest.raises(ValueError, match=r"run/log.csv: not a facenormals training log \(columns \['precious'\]"):
        train(_config(tmp_path, steps=1), TinyHeads(4), progress=False)
    assert (run / "log.csv").read_text() == "precious\n"
    (run / "log.csv").write_text("step,loss\n1,0.5\ngarbage,line\n")
    with pytest.raises(ValueError, match="run/log.csv: line 3: expected a training log row with an integer step, "
                                         "got 'garbage'"):
        train(_config(tmp_path, steps=1), TinyHeads(4), progress=False)
    (run / "log.csv").write_text("")  # a run killed before its first row was flushed: a log like none
    train(_config(tmp_path, steps=1, log_every=1), TinyHeads(4), progress=False)  # a checkpoint at step 1
    assert (run / "log.csv").read_text().splitlines()[0] == ",".join(_LOG_FIELDS)
    (run / "log.csv").write_text("step,loss\n1,0.5\n")  # as before the other columns existed: kept, widened
    train(_config(tmp_path, steps=2, log_every=1), TinyHeads(4), progress=False)
    with (run / "log.csv").open() as handle:
        reader = csv.DictReader(handle)
        rows = list(reader)
    assert reader.fieldnames == _LOG_FIELDS
    assert [r["step"] for r in rows] == ["1", "2"] and rows[0]["loss"] == "0.5" and rows[0]["lr"] == ""
    assert float(rows[1]["lr"]) > 0


def test_export_refuses_integer_storage_and_thresholds_load_weights_would_refuse(tmp_path):
    """An int8 export loaded as an all-zero network, silently; a NaN threshold was written, then refused."""
    summary = train(_config(tmp_path, steps=1), TinyHeads(4), progress=False)
    for dtype in (torch.int8, torch.bool, torch.complex64):
        with pytest.raises(ValueError, match=f"dtype: expected torch.float16, torch.bfloat16 or torch.float32, "
                                             f"got {dtype}"):
            export_weights(summary.checkpoint, tmp_path / "w.pt", dtype=dtype)
    for threshold in (float("nan"), 5, [0.5] * 3):
        with pytest.raises(ValueError, match=r"metadata\['landmark_threshold'\]: expected"):
            export_weights(summary.checkpoint, tmp_path / "w.pt", metadata={"landmark_threshold": threshold})
    assert not (tmp_path / "w.pt").exists()
    net = load_weights(export_weights(summary.checkpoint, tmp_path / "w.pt", dtype=torch.bfloat16))
    ema = load_checkpoint(summary.checkpoint)["ema"]
    for key, value in net.state_dict().items():
        torch.testing.assert_close(value, ema[key].bfloat16().float())


def test_export_refuses_to_overwrite_its_checkpoint(tmp_path):
    summary = train(_config(tmp_path, steps=1), TinyHeads(4), progress=False)
    with pytest.raises(ValueError, match="out: .*last.pt is the checkpoint being exported"):
        export_weights(summary.checkpoint, summary.checkpoint)
    assert load_checkpoint(summary.checkpoint)["step"] == 1


def test_an_error_with_worker_processes_exits_instead_of_hanging(tmp_path):
    """The DataLoader workers ignore stop signals; an exception leaving ``train`` must still let the
    interpreter exit (it used to wait forever for the workers at exit)."""
    import subprocess
    import sys
    from pathlib import Path

    script = (
        "import sys\n"
        "from facenormals.training import TrainConfig, train\n"
        "from facenormals.training import loop\n"
        "from tests.training.conftest import TinyHeads\n"
        "original, calls = loop.normal_landmark_loss, []\n"
        "def diverging(*args, **kwargs):  # the second step's loss is NaN (lr is capped below a divergent 1e30)\n"
        "    loss, terms = original(*args, **kwargs)\n"
        "    calls.append(1)\n"
        "    return (loss * float('nan') if len(calls) > 1 else loss), terms\n"
        "loop.normal_landmark_loss = diverging\n"
        "config = TrainConfig(data='unused', out=sys.argv[1], steps=3, batch_size=4, lr=3e-3, warmup_steps=1,\n"
        "    workers=1, device='cpu', precision='fp32', log_every=1, checkpoint_every=100, eval_every=100,\n"
        "    eval_samples=4, base_channels=4, depth=2, seed=3)\n"
        "train(config, TinyHeads(8), progress=False)\n"
    )
    root = Path(__file__).resolve().parents[2]
    done = subprocess.run([sys.executable, "-c", script, str(tmp_path / "run")], cwd=root, capture_output=True,
                          text=True, timeout=120, env={**__import__("os").environ, "PYTHONPATH": str(root)})
    assert done.returncode == 1
    assert "FloatingPointError: step 1: the loss is not finite" in done.stderr
    assert "resume from" not in done.stderr  # no checkpoint was written to resume from


def test_resuming_with_other_data_seed_or_fewer_steps_says_so(tmp_path, capsys):
    data = TinyHeads(8)
    train(_config(tmp_path, steps=2), data, progress=False)
    capsys.readouterr()
    train(_config(tmp_path, steps=2, data="elsewhere", seed=4), data, progress=False)
    out = capsys.readouterr().out
    assert "--data elsewhere (checkpoint: unused)" in out and "--seed 4 (checkpoint: 3)" in out
    assert "at step 2, at or beyond --steps 2: nothing to train" in out
    train(_config(tmp_path, steps=2), data, progress=False)
    assert "--data" not in capsys.readouterr().out


def test_a_refused_run_leaves_no_empty_folder(tmp_path):
    with pytest.raises(FileNotFoundError, match="init: .*missing.pt: no such weight file"):
        train(_config(tmp_path, init=str(tmp_path / "missing.pt")), TinyHeads(8), progress=False)
    with pytest.raises((ValueError, OSError), match="nowhere"):
        train(_config(tmp_path, holdout=str(tmp_path / "nowhere")), TinyHeads(8), progress=False)
    assert not (tmp_path / "run").exists()


def test_a_config_with_paths_and_numpy_numbers_makes_a_readable_checkpoint(tmp_path):
    import numpy as np
    from pathlib import Path

    config = _config(tmp_path, out=Path(tmp_path / "run"), data=Path("unused"), lr=np.float64(3e-3),
                     steps=np.int64(2), batch_size=np.int32(4))
    assert isinstance(config.out, str) and type(config.lr) is float and type(config.steps) is int
    summary = train(config, TinyHeads(8), progress=False)
    assert load_checkpoint(summary.checkpoint)["config"]["out"] == str(tmp_path / "run")
    assert train(_config(tmp_path, steps=3), TinyHeads(8), progress=False).step == 3  # resumes
    export_weights(summary.checkpoint, tmp_path / "w.pt")


def test_resuming_with_other_training_settings_says_so(tmp_path, capsys):
    data = TinyHeads(8)
    train(_config(tmp_path, steps=2, lr=5e-4, sigma=3.0), data, progress=False)
    capsys.readouterr()
    train(_config(tmp_path, steps=4), data, progress=False)
    out = capsys.readouterr().out
    assert "with lr 0.003 (checkpoint: 0.0005)" in out and "e.g. --lr 0.0005" in out
    assert "with sigma 1.5 (checkpoint: 3.0)" in out and "warmup_steps" not in out


def test_a_rerun_without_a_checkpoint_drops_the_dead_run_s_log_rows(tmp_path):
    run = tmp_path / "run"
    run.mkdir()
    (run / "log.csv").write_text("step,loss\n1,0.5\n2,0.4\n")  # a run that died before its first checkpoint
    (run / "eval.csv").write_text("step,normal_mean_deg\n2,30.0\n")
    train(_config(tmp_path, steps=4, log_every=2, eval_every=100), TinyHeads(8), holdout=TinyHeads(4, seed=1),
          progress=False)
    assert [int(r["step"]) for r in csv.DictReader((run / "log.csv").open())] == [2, 4]
    assert [int(r["step"]) for r in csv.DictReader((run / "eval.csv").open())] == [4]


def test_a_finished_run_killed_during_its_final_evaluation_evaluates_on_rerun(tmp_path):
    data, holdout = TinyHeads(8), TinyHeads(4, seed=1)
    config = _config(tmp_path, steps=2, eval_every=100)
    train(config, data, holdout=holdout, progress=False)
    (tmp_path / "run" / "eval.csv").unlink()  # as if killed after the checkpoint, before the row
    summary = train(config, data, holdout=holdout, progress=False)
    assert summary.metrics is not None
    assert [int(r["step"]) for r in csv.DictReader((tmp_path / "run" / "eval.csv").open())] == [2]


def test_ctrl_c_interrupts_the_final_evaluation(tmp_path, monkeypatch):
    import signal

    import facenormals.training.loop as loop

    def interrupted(*args, **kwargs):
        # raise_signal delivers to this thread; os.kill may deliver to another thread of the process
        # (torch's, gloo's), and the main thread can reach the next line before the handler runs
        signal.raise_signal(signal.SIGINT)
        raise AssertionError("SIGINT was swallowed")

    monkeypatch.setattr(loop, "evaluate_network", interrupted)
    # Python's own Ctrl-C handler, which a process started in the background (`cmd &` in a script,
    # nohup) does not have: there SIGINT starts out ignored and the training restores that
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        with pytest.raises(KeyboardInterrupt):
            train(_config(tmp_path, steps=2, eval_every=100), TinyHeads(8), holdout=TinyHeads(4, seed=1),
                  progress=False)
    finally:
        signal.signal(signal.SIGINT, previous)
    assert load_checkpoint(tmp_path / "run" / "last.pt")["step"] == 2  # the checkpoint came first


def test_small_data_and_a_warm_up_longer_than_the_run_are_noted(tmp_path, capsys):
    train(_config(tmp_path, steps=2, batch_size=8, warmup_steps=5), TinyHeads(6), progress=False)
    out = capsys.readouterr().out
    assert "a batch of 8 x 1 process(es) is larger than the 6 training samples" in out
    assert "--warmup-steps 5 >= --steps 2" in out


def test_a_worker_s_data_error_is_one_line(tmp_path):
    from .conftest import BrokenHeads

    with pytest.raises(ValueError) as error:
        train(_config(tmp_path, workers=1), BrokenHeads(8), progress=False)
    assert "shard_00000.npz: sample" in str(error.value) and "is damaged" in str(error.value)
    assert "\n" not in str(error.value) and "DataLoader worker" not in str(error.value)


def test_a_training_checkpoint_given_as_weights_says_how_to_export(tmp_path):
    summary = train(_config(tmp_path, steps=1), TinyHeads(4), progress=False)
    with pytest.raises(ValueError, match="a training checkpoint, not a weight file; export its weights"):
        load_weights(summary.checkpoint)


def test_an_init_of_another_architecture_leaves_no_folder(tmp_path):
    summary = train(_config(tmp_path / "a", steps=1), TinyHeads(4), progress=False)
    weights = export_weights(summary.checkpoint, tmp_path / "w.pt")
    with pytest.raises(ValueError, match="init: .* holds a network with channels"):
        train(_config(tmp_path / "b", init=str(weights), base_channels=8), TinyHeads(4), progress=False)
    assert not (tmp_path / "b" / "run").exists()


def test_an_init_beside_a_checkpoint_is_noted_as_ignored(tmp_path, capsys):
    summary = train(_config(tmp_path, steps=1), TinyHeads(4), progress=False)
    weights = export_weights(summary.checkpoint, tmp_path / "w.pt")
    capsys.readouterr()
    train(_config(tmp_path, steps=2, init=str(weights)), TinyHeads(4), progress=False)
    assert "--init " + str(weights) + " is ignored" in capsys.readouterr().out


def test_a_worker_s_multi_line_or_key_error_keeps_its_whole_message():
    from facenormals.training.loop import _from_worker

    wrapped = ValueError("Caught ValueError in DataLoader worker process 0.\nOriginal Traceback (most recent call "
                         "last):\n  File \"x.py\", line 1, in f\n    raise ValueError(...)\nValueError: shard_0.npz: "
                         "bad array\n  expected (N, 3)\n  got (N, 4)\n")
    assert str(_from_worker(wrapped)) == "shard_0.npz: bad array\n  expected (N, 3)\n  got (N, 4)"
    key = KeyError("Caught KeyError in DataLoader worker process 0.\nOriginal Traceback (most recent call last):\n"
                   "  File \"x.py\", line 1, in f\nKeyError: 'image is not a file in the archive'\n")
    unwrapped = _from_worker(key)
    assert isinstance(unwrapped, LookupError) and str(unwrapped) == "'image is not a file in the archive'"
    plain = ValueError("no worker here")
    assert _from_worker(plain) is plain


def test_the_command_line_resumes_with_the_checkpoint_s_schedule(tmp_path, monkeypatch):
    import facenormals.training as training
    from facenormals.cli import main

    seen = []
    monkeypatch.setattr(training, "train", lambda config, progress=True: seen.append(config) or
                        __import__("facenormals.training.loop", fromlist=["x"]).TrainSummary(
                            0, 0, False, "steps", 0.0, None, tmp_path / "run" / "last.pt"))
    train(_config(tmp_path, steps=1, lr=5e-4, warmup_steps=7), TinyHeads(8), progress=False)  # a whole checkpoint
    main(["train", "--data", "unused", "--out", str(tmp_path / "run"), "--steps", "9", "--quiet"])
    main(["train", "--data", "unused", "--out", str(tmp_path / "run"), "--steps", "9", "--lr", "1e-3", "--quiet"])
    assert (seen[0].lr, seen[0].warmup_steps, seen[0].steps) == (5e-4, 7, 9)
    assert (seen[1].lr, seen[1].warmup_steps) == (1e-3, 7)


def test_a_non_finite_gradient_stops_before_the_weights_and_checkpoint(tmp_path, monkeypatch):
    """A finite loss whose gradient overflows: stepping would write NaN into the weights and then
    into last.pt, the very checkpoint the error advises resuming from."""
    from facenormals.training import loop

    class InfGradient(torch.autograd.Function):
        @staticmethod
        def forward(ctx, x):
            return x.clone()

        @staticmethod
        def backward(ctx, grad):
            return grad * float("inf")

    calls = {"n": 0}
    real_loss = loop.normal_landmark_loss

    def loss_with_an_overflow_at_the_fourth_step(*args, **kwargs):
        total, terms = real_loss(*args, **kwargs)
        calls["n"] += 1
        return (InfGradient.apply(total) if calls["n"] == 4 else total), terms

    monkeypatch.setattr(loop, "normal_landmark_loss", loss_with_an_overflow_at_the_fourth_step)
    with pytest.raises(FloatingPointError, match=r"step 3: the gradient is not finite \(the loss was [\d.]+\); the "
                                                 r"weights were not updated; lower --lr, or resume from the last "
                                                 r"checkpoint .*last.pt \(step 2\)"):
        train(_config(tmp_path, checkpoint_every=2), TinyHeads(16), progress=False)
    state = load_checkpoint(tmp_path / "run" / "last.pt")
    assert state["step"] == 2
    assert all(bool(torch.isfinite(t).all()) for t in [*state["model"].values(), *state["ema"].values()]
               if t.is_floating_point())
    monkeypatch.setattr(loop, "normal_landmark_loss", real_loss)
    assert train(_config(tmp_path, checkpoint_every=2), TinyHeads(16), progress=False).step == 8  # resumes


def test_the_training_data_is_no_holdout(tmp_path):
    import json

    from facenormals.data.shards import FORMAT_NAME
    from facenormals.training.loop import _check_holdout_is_not_training_data

    data = TinyHeads(8)
    with pytest.raises(ValueError, match="holdout: the training dataset itself"):
        train(_config(tmp_path), data, holdout=data, progress=False)

    def folder(name, seed):
        (tmp_path / name).mkdir()
        manifest = {"format": FORMAT_NAME, "version": 1, "seed": seed, "count": 4, "shard_size": 4,
                    "image_size": 32, "normal_scale": 32767.0, "model": {"name": "builtin"}, "generator": 2}
        (tmp_path / name / "manifest.json").write_text(json.dumps(manifest))
        return tmp_path / name

    class Folder:  # what the check reads of a SyntheticHeadDataset
        def __init__(self, root):
            self.root, self.manifest = root, json.loads((root / "manifest.json").read_text())

    train_root, same_seed, other_seed = folder("train", 0), folder("same", 0), folder("other", 1)
    with pytest.raises(ValueError, match=r"holdout: .*train is the training data folder"):
        _check_holdout_is_not_training_data(Folder(train_root), str(train_root / "." ))
    with pytest.raises(ValueError, match=r"holdout: .*same was rendered with the training data's seed 0, generator "
                                         r"and model: its samples are samples of the training data"):
        _check_holdout_is_not_training_data(Folder(train_root), str(same_seed))
    _check_holdout_is_not_training_data(Folder(train_root), str(other_seed))
    _check_holdout_is_not_training_data(data, str(other_seed))  # a dataset without a manifest: nothing to compare


def test_resuming_on_a_grown_dataset_says_so(tmp_path, capsys):
    train(_config(tmp_path, steps=2), TinyHeads(8), progress=False)
    capsys.readouterr()
    train(_config(tmp_path, steps=3), TinyHeads(12), progress=False)
    assert "with 12 training samples (checkpoint: 8); the epoch's sample order differs" in capsys.readouterr().out
    train(_config(tmp_path, steps=4), TinyHeads(12), progress=False)
    assert "training samples" not in capsys.readouterr().out


def test_a_network_too_deep_for_the_images_is_refused_before_the_folder(tmp_path):
    with pytest.raises(ValueError, match=r"depth: 6 stride-2 levels need images whose sides are divisible by "
                                         r"2\*\*6 = 64; the training images are 32x32 pixels"):
        train(_config(tmp_path, depth=6), TinyHeads(8), progress=False)

    class Wide(TinyHeads):  # 16x32 images: the height does not fit a depth of 5
        def __getitem__(self, i):
            item = dict(super().__getitem__(i))
            for key in ("image", "normals", "foreground"):
                item[key] = item[key][..., :16, :]
            return item

    with pytest.raises(ValueError, match=r"the training images are 16x32 pixels"):
        train(_config(tmp_path, depth=5), Wide(8), progress=False)
    assert not (tmp_path / "run").exists()


def test_any_seed_below_2_63_trains(tmp_path):
    summary = train(_config(tmp_path, steps=1, seed=2 * 10**13), TinyHeads(8), progress=False)
    assert summary.step == 1


@pytest.fixture(scope="module")
def good_checkpoint(tmp_path_factory):
    """The last.pt of one tiny run, shared by the damaged-checkpoint cases."""
    root = tmp_path_factory.mktemp("good")
    return train(_config(root, steps=2, checkpoint_every=2), TinyHeads(8), progress=False).checkpoint


def _damage(state: dict, change: str) -> None:
    from facenormals.nn import NormalLandmarkUNet

    first = next(iter(state["model"]))
    if change.startswith("no "):
        state.pop(change[3:])
    elif change == "nan model":
        state["model"][first][...] = float("nan")
    elif change == "inf ema":
        state["ema"][first].view(-1)[0] = float("inf")
    elif change == "nan optimiser":
        next(iter(state["optimizer"]["state"].values()))["exp_avg"].view(-1)[0] = float("nan")
    elif change == "text step":
        state["step"] = "abc"
    elif change == "negative step":
        state["step"] = -3
    elif change == "model not a dict":
        state["model"] = [1, 2]
    elif change == "10 landmarks":
        other = NormalLandmarkUNet(num_landmarks=10, base_channels=4, depth=2).state_dict()
        state.update(model=other, ema=other, num_landmarks=10)
    elif change == "wider weights":  # the stated config (4 base channels) does not match the weights (8)
        other = NormalLandmarkUNet(base_channels=8, depth=2).state_dict()
        state.update(model=other, ema=other)
    elif change == "foreign optimiser":
        state["optimizer"]["param_groups"] = state["optimizer"]["param_groups"] * 2


@pytest.mark.parametrize("change, message", [
    ("no model", "corrupt checkpoint: no model weights"),
    ("no ema", r"corrupt checkpoint: no averaged \(EMA\) weights"),
    ("no optimizer", "corrupt checkpoint: no optimiser state"),
    ("nan model", r"corrupt checkpoint: the model weights \('model'\) hold NaN or infinite values \(stem.0.weight"),
    ("inf ema", r"corrupt checkpoint: the averaged \(EMA\) weights \('ema'\) hold NaN or infinite values"),
    ("nan optimiser", r"corrupt checkpoint: the optimiser state \('optimizer'\) holds NaN"),
    ("text step", "corrupt checkpoint: 'step' is 'abc', expected an integer >= 0"),
    ("negative step", "corrupt checkpoint: 'step' is -3, expected an integer >= 0"),
    ("no samples_seen", "corrupt checkpoint: no 'samples_seen' entry"),
    ("model not a dict", r"corrupt checkpoint: the model weights \('model'\) are not a state dict"),
    ("10 landmarks", "a checkpoint of a network with 10 landmarks; the run trains 24"),
    ("wider weights", r"corrupt checkpoint: loading its model weights \('model'\) failed \(.*size mismatch"),
    ("foreign optimiser", r"corrupt checkpoint: loading its optimiser state \('optimizer'\) failed"),
])
def test_a_damaged_checkpoint_is_named_and_never_resumed_or_exported(tmp_path, good_checkpoint, change, message):
    """A missing entry was a KeyError traceback, other weights a size mismatch naming no file, NaN
    weights a failure advising to resume from that same file, NaN averaged weights trained on and
    were exported, and a text step an int() error naming no file."""
    state = torch.load(good_checkpoint, weights_only=True)
    _damage(state, change)
    config = _config(tmp_path, steps=4)
    last = tmp_path / "run" / "last.pt"
    last.parent.mkdir()
    torch.save(state, last)
    with pytest.raises(ValueError, match=f"{re.escape(str(last))}: {message}"):
        train(config, TinyHeads(8), progress=False)
    assert sorted(p.name for p in last.parent.iterdir()) == [".train.lock", "last.pt"]  # no log rows, nothing overwritten
    if "loading its" not in message and "landmarks" not in message:  # what load_checkpoint itself sees
        with pytest.raises(ValueError, match=f"{re.escape(str(last))}: {message}"):
            export_weights(last, tmp_path / "w.pt")
        assert not (tmp_path / "w.pt").exists()



@pytest.mark.parametrize("state, match", [
    ([1, 2], "state: expected a dictionary (a training checkpoint), got list"),
    ({"a": 1}, "state: expected a training checkpoint (format 'facenormals-train') or a weight file payload "
               "(format 'facenormals-unet'), got format None"),
    ({"format": "facenormals-train"}, "state: expected the run's settings as a dictionary ('config'), got NoneType"),
])
def test_save_checkpoint_refuses_a_state_load_checkpoint_would_refuse(tmp_path, state, match):
    """Regression: save_checkpoint(path, [1, 2]) wrote a file that load_checkpoint then refused."""
    from facenormals.training import save_checkpoint

    with pytest.raises(ValueError, match=re.escape(match)):
        save_checkpoint(tmp_path / "c.pt", state)
    assert not (tmp_path / "c.pt").exists()


@pytest.mark.parametrize("change, message", [
    ("no model", "no model weights"),
    ("negative step", "'step' is -3, expected an integer >= 0"),
    ("model not a dict", r"the model weights \('model'\) are not a state dict"),
    ("no optimizer", "no optimiser state"),
])
def test_save_checkpoint_refuses_a_training_state_without_its_entries(tmp_path, good_checkpoint, change, message):
    from facenormals.training import save_checkpoint

    state = torch.load(good_checkpoint, weights_only=True)
    save_checkpoint(tmp_path / "good.pt", state)  # what train writes is taken
    assert load_checkpoint(tmp_path / "good.pt")["step"] == state["step"]
    _damage(state, change)
    with pytest.raises(ValueError, match="state: a training checkpoint that load_checkpoint cannot read: " + message):
        save_checkpoint(tmp_path / "c.pt", state)
    assert not (tmp_path / "c.pt").exists()


def test_a_damaged_byte_in_a_checkpoint_fails_its_crc_check(tmp_path, good_checkpoint):
    """Regression: torch.load never checks the CRC-32 of its zip's members: a flipped byte turned the
    config key 'ema_decay' into 'ema_ddcay' and load_checkpoint accepted it; flipped weights loaded."""
    import struct
    import zipfile

    data = good_checkpoint.read_bytes()
    assert data.count(b"ema_decay") == 1  # in data.pkl, stored
    with zipfile.ZipFile(good_checkpoint) as archive:
        info = next(i for i in archive.infolist() if i.filename.endswith("/data/0"))
        pickle_name = next(n for n in archive.namelist() if n.endswith("/data.pkl"))
    name_length, extra_length = struct.unpack_from("<HH", data, info.header_offset + 26)
    weight = bytearray(data)
    weight[info.header_offset + 30 + name_length + extra_length + 2] ^= 0xFF  # a byte of the first tensor
    for name, damaged, member in (("key.pt", data.replace(b"ema_decay", b"ema_ddcay"), pickle_name),
                                  ("weight.pt", bytes(weight), info.filename)):
        path = tmp_path / name
        path.write_bytes(damaged)
        message = (f"{re.escape(str(path))}: not a readable checkpoint \\(damaged: its member "
                   f"{re.escape(repr(member))} fails its CRC-32 check\\)")
        with pytest.raises(ValueError, match=message):
            load_checkpoint(path)
        with pytest.raises(ValueError, match=message):
            export_weights(path, tmp_path / "w.pt")
        assert not (tmp_path / "w.pt").exists()


@pytest.mark.parametrize("metadata", [[1], "note", ({"note": 1},), 0, {3: "x"}])
def test_export_weights_names_metadata_that_is_not_a_dict_of_plain_values(tmp_path, good_checkpoint, metadata):
    """Regression: metadata=[1] was an AttributeError ('list' object has no attribute 'items') from deep
    inside; a falsy non-dict (0) was taken as no metadata."""
    with pytest.raises(ValueError, match=r"^metadata: expected (a dict of plain values|string keys)"):
        export_weights(good_checkpoint, tmp_path / "w.pt", metadata=metadata)
    assert not (tmp_path / "w.pt").exists()


def test_export_weights_names_an_out_that_is_no_file_name(tmp_path, good_checkpoint, monkeypatch):
    """Regression: out="" was OSError [Errno 16] Device or resource busy: '.', an existing folder an
    IsADirectoryError, a path under a file a FileExistsError, out=3 a TypeError."""
    from facenormals.training import save_checkpoint

    monkeypatch.chdir(tmp_path)
    (tmp_path / "folder").mkdir()
    (tmp_path / "file").write_text("x")
    for out, match in (("", "out: expected a file name (str or os.PathLike), got ''"),
                       (3, "out: expected a file name (str or os.PathLike), got 3"),
                       (None, "out: expected a file name (str or os.PathLike), got None"),
                       (tmp_path / "folder", f"out: {tmp_path / 'folder'} is a folder; give a file name"),
                       (tmp_path / "file" / "w.pt", f"out: {tmp_path / 'file' / 'w.pt'} cannot be written: "
                                                    f"{tmp_path / 'file'} is a file, not a folder")):
        with pytest.raises(ValueError, match=re.escape(match)):
            export_weights(good_checkpoint, out)
        with pytest.raises(ValueError, match=re.escape(match.replace("out:", "path:", 1))):
            save_checkpoint(out, torch.load(good_checkpoint, weights_only=True))
    with pytest.raises(ValueError, match=re.escape("checkpoint: expected a file name (str or os.PathLike), got int 3")):
        export_weights(3, tmp_path / "w.pt")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["file", "folder"]
    assert not any((tmp_path / "folder").iterdir()) and (tmp_path / "file").read_text() == "x"


_RUN_LOCK_HOLDER = """
import sys, time
from facenormals.core.files import hold_locks
with hold_locks(sys.argv[1], [0], "held"):
    print("held", flush=True)
    time.sleep(60)
"""


@pytest.mark.skipif(os.name != "posix", reason="advisory locks are POSIX")
def test_a_second_run_on_a_folder_in_use_is_refused(tmp_path):
    """Regression: the same train command started twice (a job resubmitted while the first still ran)
    exited 0 twice with log.csv rows dropped (the second's start-up truncation), duplicated and
    interleaved. The run folder's lock now refuses the second, leaving the folder as it was."""
    import signal
    import subprocess
    import sys

    from facenormals.core.files import FolderInUseError
    from facenormals.training.loop import LOCK

    train(_config(tmp_path, steps=2, log_every=1), TinyHeads(4), progress=False)
    run = tmp_path / "run"
    before = {p.name: p.read_bytes() for p in run.iterdir()}
    holder = subprocess.Popen([sys.executable, "-c", _RUN_LOCK_HOLDER, str(run / LOCK)], stdout=subprocess.PIPE,
                              text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        with pytest.raises(FolderInUseError, match=f"out {run}: another process is writing it"):
            train(_config(tmp_path, steps=4, log_every=1), TinyHeads(4), progress=False)
        assert {p.name: p.read_bytes() for p in run.iterdir()} == before
    finally:
        holder.send_signal(signal.SIGKILL)
        holder.wait()
    summary = train(_config(tmp_path, steps=4, log_every=1), TinyHeads(4), progress=False)  # free again: resumes
    assert summary.step == 4
    assert [int(r["step"]) for r in csv.DictReader((run / "log.csv").open())] == [1, 2, 3, 4]
