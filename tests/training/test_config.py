import math

import pytest

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
                                         ("seed", -1), ("seed", 2**63), ("seed", 1.5)])
def test_bad_values_name_the_field(field, value):
    with pytest.raises(ValueError, match=field):
        TrainConfig(data="d", out="o", **{field: value})


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
