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


def test_a_missing_ict_path_in_the_environment_is_an_error(tmp_path, monkeypatch):
    monkeypatch.setenv("FACENORMALS_ICT", str(tmp_path / "nowhere.npz"))
    with pytest.raises(ModelFileError, match="nowhere.npz: FACENORMALS_ICT names a file that does not exist"):
        load_model("auto")
    monkeypatch.setenv("FACENORMALS_ICT", str(tmp_path))  # a folder, e.g. the repository
    with pytest.raises(ModelFileError, match=r"FACENORMALS_ICT names a folder; it must name the converted archive "
                                             r"\(a repository is converted once with `facenormals models fetch ict --from"):
        load_model("auto")


def test_a_repository_root_or_its_model_folder_loads(tmp_path):
    """load_ict_raw takes the repository's root as well as FaceXModel/; load_model said 'not found'."""
    import shutil

    from tests.models.test_ict import RAW_SUBSET

    if not (RAW_SUBSET / "generic_neutral_mesh.obj").exists():
        pytest.skip("shared raw ICT-FaceKit subset not found")
    shutil.copytree(RAW_SUBSET, tmp_path / "ICT-FaceKit-master" / "FaceXModel")
    for folder in (tmp_path / "ICT-FaceKit-master", tmp_path / "ICT-FaceKit-master" / "FaceXModel"):
        assert load_model(str(folder)).num_shape == 2


def test_a_mat_file_of_another_layout_is_named(tmp_path):
    import numpy as np
    import scipy.io

    path = tmp_path / "BFM_model_front.mat"
    scipy.io.savemat(path, {"meanshape": np.zeros((1, 30)), "idBase": np.zeros((30, 2))})
    with pytest.raises(ModelFileError, match=r"BFM_model_front\.mat: neither a BFM 2009 model .* nor an LYHM one "
                                             r"\('shp'\); it holds \['idBase', 'meanshape'\]"):
        load_model(str(path))


def test_a_repository_zip_names_the_conversion(tmp_path):
    path = tmp_path / "ICT-FaceKit-master.zip"
    path.write_bytes(b"PK")
    with pytest.raises(ModelFileError, match="facenormals models fetch ict --from .*ICT-FaceKit-master.zip"):
        load_model(str(path))


def test_models_without_landmarks_are_refused_with_the_remedy():
    from facenormals.fitting import fit_head
    from facenormals.fitting.oracle import render_oracle_views
    from facenormals.models import MorphableModel, builtin_head_model

    head = builtin_head_model()
    bare = MorphableModel(head.mean, head.shape_basis, head.faces, shape_std=head.shape_std, name="bare")
    views = render_oracle_views(head, torch.zeros(1, head.num_shape), [0.0], image_size=32)
    with pytest.raises(ValueError, match="model: 'bare' has 0 named landmarks; .*MorphableModel.with_annotations"):
        fit_head(views.normal_maps, torch.zeros(1, 1, 0, 2), bare)
    annotated = bare.with_annotations(head.landmarks)
    assert annotated.landmark_names == head.landmark_names and annotated.name == "bare"
    region = annotated.face_region
    nose = head.mean[head.landmarks["nose_tip"]]
    assert bool(((head.mean[region] - nose).norm(dim=-1) < 95.0).all())
    assert 0.8 < int((region & head.face_region).sum()) / int(head.face_region.sum()) <= 1.0
    fit = fit_head(views.normal_maps, views.landmarks, annotated, rounds=1, iterations_per_round=2)
    assert fit.vertices.shape == (1, head.num_vertices, 3)


def test_arguments_folders_and_units_are_named(tmp_path):
    from facenormals.models import MorphableModel, builtin_head_model

    with pytest.raises(ValueError, match="dtype: expected a floating-point torch dtype, got torch.int32"):
        load_model("builtin", dtype=torch.int32)
    with pytest.raises(ValueError, match="dtype: expected a floating-point torch dtype, got 'float32'"):
        load_model("builtin", dtype="float32")
    with pytest.raises(ValueError, match="spec: expected a model name .* or a path, got None"):
        load_model(None)
    with pytest.raises(ModelFileError, match=f"{tmp_path}: a folder, not a model file"):
        load_model(str(tmp_path))
    head = builtin_head_model()  # a model file whose mean is in metres (e.g. converted twice)
    MorphableModel(head.mean / 1000, head.shape_basis / 1000, head.faces, name="m").save(tmp_path / "metres.npz")
    with pytest.raises(ModelFileError, match=r"metres.npz: the loaded mean spans 0.367 mm across, not the 50-5000"):
        load_model(tmp_path / "metres.npz")


def test_a_damaged_ict_archive_names_its_remedy(ict_npz, tmp_path, monkeypatch):
    from facenormals.models import ict_release_differences

    good = ict_npz.read_bytes()
    cached = tmp_path / "home" / "ict" / "ict_face_head.npz"
    cached.parent.mkdir(parents=True)
    cached.write_bytes(good[: len(good) // 2])
    monkeypatch.setenv("FACENORMALS_HOME", str(tmp_path / "home"))
    monkeypatch.delenv("FACENORMALS_ICT", raising=False)
    for spec in ("ict", "auto"):  # "auto" must not fall back to the built-in head silently
        with pytest.raises(ModelFileError, match="cannot read ICT-FaceKit archive .*; `facenormals models fetch ict "
                                                 "--force` rebuilds it"):
            load_model(spec)
    with pytest.raises(ModelFileError, match=f"{cached}: cannot read ICT-FaceKit archive"):
        ict_release_differences(cached)
    elsewhere = tmp_path / "copy.npz"
    elsewhere.write_bytes(good[: len(good) // 2])
    monkeypatch.setenv("FACENORMALS_ICT", str(elsewhere))
    with pytest.raises(ModelFileError, match="replace it, or name a good copy with \\$FACENORMALS_ICT"):
        load_model("ict")
