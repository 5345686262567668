import pytest
import torch

from facenormals.models import ModelFileError, load_model


def test_builtin_and_path(tmp_path):
    model = load_model("builtin")
    assert model.name == "builtin"
    path = tmp_path / "m.npz"
    model.save(path)
    again = load_model(str(path))
    assert torch.equal(again.faces, model.faces)


def test_ict_missing_names_the_fetch_command(tmp_path, monkeypatch):
    monkeypatch.setenv("FACENORMALS_HOME", str(tmp_path))
    monkeypatch.setattr("facenormals.models.registry.find_ict_archive", lambda: None)
    with pytest.raises(ModelFileError, match="facenormals models fetch ict"):
        load_model("ict")
    assert load_model("auto").name == "builtin"


def test_unreadable_path_names_the_file(tmp_path):
    bad = tmp_path / "broken.npz"
    bad.write_text("not a model")
    with pytest.raises(ModelFileError, match="broken.npz"):
        load_model(str(bad))


def test_ict_found_in_shared(ict_npz, monkeypatch):
    monkeypatch.setenv("FACENORMALS_ICT", str(ict_npz))
    assert load_model("auto").name == "ict"
