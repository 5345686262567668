import math
import re

import pytest
import torch

from facenormals.training import TrainConfig


def test_learning_rate_schedule_warmup_then_cosine():
    c = TrainConfig(data="d", out="o", steps=110, lr=1.0, warmup_steps=10, min_lr_ratio=0.1)
    assert c.learning_rate(0) == pytest.approx(0.1)
    assert c.learning_rate(9) == pytest.approx(1.0)
    assert c.learning_rate(10) == pytest.approx(1.0)
    assert c.learning_rate(60) == pytest.approx(0.1 + 0.9 * 0.5 * (1 + math.cos(math.pi * 0.5)))
    assert c.learning_rate(110) == pytest.approx(0.1)
    rates = [c.learning_rate(s) for s in range(10, 111)]
    assert all(a >= b for a, b in zip(rates, rates[1:]))


@pytest.mark.parametrize("field,value", [("steps", 0), ("batch_size", -1), ("lr", 0.0), ("ema_decay", 1.0),
                                         ("precision", "fp8"), ("workers", -1), ("max_minutes", 0.0),
                                         ("lr", float("inf")), ("sigma", float("nan")), ("workers", True),
                                         ("threads", 1.5), ("threads", True), ("landmark_weight", float("inf")),
                                         ("seed", -1), ("seed", 2**63), ("seed", 1.5), ("sigma", 1e-9),
                                         ("sigma", 0.4), ("max_minutes", float("inf"))])
def test_bad_values_name_the_field(field, value):
    with pytest.raises(ValueError, match=field):
        TrainConfig(data="d", out="o", **{field: value})


def test_the_narrowest_landmark_sigma_still_decodes_to_its_points():
    """sigma=1e-9 was accepted: every target map was 0 and the network learned to find no landmark."""
    from facenormals.data.landmark_maps import landmark_maps, landmarks_from_maps
    from facenormals.training.config import MIN_SIGMA

    points = torch.rand(2, 24, 2, generator=torch.Generator().manual_seed(3)) * 100 + 14
    visible = torch.ones(2, 24, dtype=torch.bool)
    found, found_visible = landmarks_from_maps(landmark_maps(points, visible, (128, 128), MIN_SIGMA))
    assert found_visible.all() and (found - points).norm(dim=-1).max() < 0.05
    assert TrainConfig(data="d", out="o", sigma=MIN_SIGMA).sigma == MIN_SIGMA
    with pytest.raises(ValueError, match="sigma: expected a landmark Gaussian of at least 0.5 px .*got 0.3"):
        TrainConfig(data="d", out="o", sigma=0.3)


def test_an_output_path_that_is_a_file_is_refused(tmp_path):
    (tmp_path / "run").write_text("x")
    with pytest.raises(ValueError, match="out: .*run exists and is not a folder"):
        TrainConfig(data="d", out=str(tmp_path / "run"))


@pytest.mark.parametrize("field", ["data", "out", "init", "holdout"])
def test_an_empty_path_is_refused_not_read_as_the_current_folder(field):
    """An unset $OUT in a script trained into the current folder."""
    values = {"data": "d", "out": "o", field: ""}
    with pytest.raises(ValueError, match=f"{field}: expected a folder or file name, got an empty string"):
        TrainConfig(**values)


def test_round_trip_and_unknown_fields():
    c = TrainConfig(data="d", out="o", steps=7)
    assert TrainConfig.from_dict(c.to_dict()) == c
    with pytest.raises(ValueError, match="unknown"):
        TrainConfig.from_dict({**c.to_dict(), "bogus": 1})


@pytest.mark.parametrize("field,value", [("ema_decay", "0.5"), ("min_lr_ratio", "0.1"), ("min_lr_ratio", True),
                                         ("max_minutes", "5"), ("max_minutes", True), ("device", 3),
                                         ("device", "tpu")])
def test_values_of_the_wrong_type_name_the_field(field, value):
    """These raised TypeError or AttributeError (device=3 only once training started), or were taken
    as numbers (True)."""
    with pytest.raises(ValueError, match=field):
        TrainConfig(data="d", out="o", **{field: value})


@pytest.mark.parametrize("device", ["cudafoo", "cuda:x", "cuda:-1", "cuda:", "cuda:0:1", " cuda", "CPU"])
def test_only_the_documented_devices_are_taken(device):
    """'cudafoo', 'cuda:x' and 'cuda:-1' were accepted although only 'cuda:N' is."""
    with pytest.raises(ValueError, match="device: expected 'auto', 'cpu', 'cuda' or 'cuda:N', got"):
        TrainConfig(data="d", out="o", device=device)
    for good in ("auto", "cpu", "cuda", "cuda:0", "cuda:12"):
        assert TrainConfig(data="d", out="o", device=good).device == good


def test_a_learning_rate_above_the_cap_names_lr_and_the_option(tmp_path, capsys):
    """--lr 1e38 was accepted, then failed at the first step with a float overflow naming no option."""
    from facenormals.cli import main
    from facenormals.training.config import MAX_LR

    assert TrainConfig(data="d", out="o", lr=MAX_LR).lr == MAX_LR
    for lr in (1e38, MAX_LR * 1.01):
        with pytest.raises(ValueError, match=re.escape(f"lr: expected a learning rate of at most 10000, got {lr!r}")):
            TrainConfig(data="d", out="o", lr=lr)
    out = tmp_path / "run"
    assert main(["train", "--data", str(tmp_path), "--out", str(out), "--lr", "1e38", "--quiet"]) == 1
    assert "facenormals train: error: --lr: expected a learning rate of at most 10000, got 1e+38" in capsys.readouterr().err
    assert not out.exists()
