"""ICT-FaceKit: the raw FaceXModel loader, the conversion to the archive, and fetching into the cache."""

from __future__ import annotations

import io
import shutil
import urllib.error
import urllib.request
import zipfile
from pathlib import Path

import numpy as np
import pytest
import torch

from facenormals.models import LANDMARK_NAMES

from facenormals.models import ModelFileError, find_ict_archive
from facenormals.models import fetch as fetch_module
from facenormals.models.fetch import FetchError, fetch_ict
from facenormals.models.ict import ict_npz_from_raw, load_ict_npz, load_ict_raw, opengl_to_model_frame

ICT_DIR = Path(__file__).resolve().parents[3] / "shared" / "data" / "ict_facekit"
RAW_SUBSET = ICT_DIR / "raw_subset" / "FaceXModel"


@pytest.fixture
def ict_raw() -> Path:
    """The shared FaceXModel subset (neutral, identity000, identity001, jawOpen, vertex_indices.json)."""
    if not (RAW_SUBSET / "generic_neutral_mesh.obj").exists():
        pytest.skip(f"shared raw ICT-FaceKit subset not found at {RAW_SUBSET}")
    return RAW_SUBSET


@pytest.fixture
def raw_copy(ict_raw, tmp_path) -> Path:
    """A writable copy of the subset, laid out as a repository: ``<tmp>/repo/FaceXModel``."""
    target = tmp_path / "repo" / "FaceXModel"
    shutil.copytree(ict_raw, target)
    for path in target.iterdir():
        path.chmod(0o644)
    return target


@pytest.fixture(scope="module")
def raw_model():
    if not (RAW_SUBSET / "generic_neutral_mesh.obj").exists():
        pytest.skip(f"shared raw ICT-FaceKit subset not found at {RAW_SUBSET}")
    return load_ict_raw(RAW_SUBSET, dtype=torch.float64)


# --- load_ict_raw ---------------------------------------------------------------------------------


def test_raw_subset_loads(raw_model):
    assert raw_model.name == "ict"
    assert (raw_model.num_vertices, raw_model.faces.shape[0]) == (11248, 22288)
    assert (raw_model.num_shape, raw_model.num_expressions) == (2, 1)
    assert raw_model.expression_names == ["jawOpen"]
    assert raw_model.landmark_names == list(LANDMARK_NAMES)
    assert len(raw_model.metadata["landmarks_ibug68"]) == 68
    assert raw_model.mean.dtype == torch.float64
    assert torch.equal(raw_model.shape_std, torch.ones(2, dtype=torch.float64))


def test_raw_subset_agrees_with_npz(raw_model, ict_npz):
    npz = load_ict_npz(ict_npz, dtype=torch.float64)
    assert torch.equal(raw_model.faces, npz.faces)
    # the archive stores float32 centimetres; 1e-4 mm is far below its resolution
    torch.testing.assert_close(raw_model.mean, npz.mean, rtol=0, atol=1e-4)
    torch.testing.assert_close(raw_model.shape_basis, npz.shape_basis[:2], rtol=0, atol=1e-5)
    jaw = npz.expression_names.index("jawOpen")
    torch.testing.assert_close(raw_model.expression_basis[0], npz.expression_basis[jaw], rtol=0, atol=1e-5)
    assert raw_model.landmarks == npz.landmarks
    assert raw_model.metadata["license"] == "MIT"


def test_raw_model_frame_and_units(raw_model, ict_raw):
    """mm and y down: the first OBJ vertex (cm, +y up, +z out of the face) maps by (x, -y, -z) * 10."""
    lines = (ict_raw / "generic_neutral_mesh.obj").read_text().splitlines()
    first = next(line for line in lines if line.startswith("v "))
    xyz = np.array([float(v) for v in first.split()[1:4]])
    np.testing.assert_allclose(raw_model.mean[0].numpy(), opengl_to_model_frame(xyz, 10.0), atol=1e-9)
    # chin below the eyes (y down), nose tip in front of the ears (face along -z)
    lm = raw_model.landmarks
    assert raw_model.mean[lm["chin"], 1] > raw_model.mean[lm["right_eye_outer"], 1]
    assert raw_model.mean[lm["nose_tip"], 2] < raw_model.mean[lm["right_ear_tragus"], 2]


def test_raw_dtype_and_repo_root(ict_raw):
    model = load_ict_raw(ict_raw.parent, num_shape=1)  # the folder containing FaceXModel/
    assert model.mean.dtype == torch.float32 and model.num_shape == 1


def test_num_shape_and_dtype_are_checked_before_reading(ict_raw):
    for bad in (1.5, True, 0):
        with pytest.raises(ValueError, match="num_shape: expected an integer"):
            load_ict_raw(ict_raw, num_shape=bad)
    with pytest.raises(ValueError, match="dtype: expected a floating-point torch dtype"):
        load_ict_raw(ict_raw, dtype=torch.int64)


def test_num_shape_larger_than_present_raises(ict_raw):
    with pytest.raises(ModelFileError, match=r"num_shape=3 but only 2 identity files"):
        load_ict_raw(ict_raw, num_shape=3)
    with pytest.raises(ValueError, match="num_shape"):
        load_ict_raw(ict_raw, num_shape=0)


def test_missing_folder_and_files(tmp_path, raw_copy):
    with pytest.raises(ModelFileError, match="not found"):
        load_ict_raw(tmp_path / "nowhere")
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(ModelFileError, match="not an ICT-FaceKit folder: no generic_neutral_mesh.obj"):
        load_ict_raw(empty)
    (raw_copy / "vertex_indices.json").unlink()
    with pytest.raises(ModelFileError, match="vertex_indices.json"):
        load_ict_raw(raw_copy)


def test_identity_gap_raises(raw_copy):
    (raw_copy / "identity000.obj").unlink()
    with pytest.raises(ModelFileError, match=r"identity000\.obj.*identity001\.obj"):
        load_ict_raw(raw_copy)


def test_truncated_obj_names_the_file(raw_copy):
    path = raw_copy / "identity001.obj"
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 10])
    with pytest.raises(ModelFileError, match=r"identity001\.obj: has \d+ vertices, expected 26719"):
        load_ict_raw(raw_copy)


def test_obj_truncated_in_faces_names_the_file(raw_copy):
    path = raw_copy / "jawOpen.obj"
    data = path.read_bytes()
    path.write_bytes(data[: len(data) - 2000])
    with pytest.raises(ModelFileError, match=r"jawOpen\.obj.*polygons"):
        load_ict_raw(raw_copy)


def test_unparsable_vertex_line_names_file_and_line(raw_copy):
    path = raw_copy / "generic_neutral_mesh.obj"
    lines = path.read_bytes().split(b"\n")
    index = next(i for i, line in enumerate(lines) if line.startswith(b"v "))
    lines[index + 5] = b"v 1.0 oops 2.0"
    path.write_bytes(b"\n".join(lines))
    with pytest.raises(ModelFileError, match=rf"generic_neutral_mesh\.obj: line {index + 6}: cannot parse vertex"):
        load_ict_raw(raw_copy)


def test_a_short_vertex_line_beside_a_long_one_is_not_read_as_shifted_coordinates(raw_copy):
    """Regression: the fast path only compared the total number of numbers with 3 per line, so a line
    with 4 (x y z w) beside one with 2 shifted the coordinates of every vertex in between."""
    path = raw_copy / "generic_neutral_mesh.obj"
    lines = path.read_bytes().split(b"\n")
    index = next(i for i, line in enumerate(lines) if line.startswith(b"v "))
    lines[index + 2] += b" 1.0"
    lines[index + 9] = b" ".join(lines[index + 9].split()[:3])
    path.write_bytes(b"\n".join(lines))
    with pytest.raises(ModelFileError, match=rf"generic_neutral_mesh\.obj: line {index + 10}: cannot parse vertex "
                                             r".*fewer than 3 coordinates"):
        load_ict_raw(raw_copy)


def test_unparsable_face_line_names_the_file(raw_copy):
    path = raw_copy / "generic_neutral_mesh.obj"
    data = path.read_bytes().replace(b"\nf ", b"\nf x/1 ", 1)
    path.write_bytes(data)
    with pytest.raises(ModelFileError, match=r"generic_neutral_mesh\.obj: line \d+: cannot parse face"):
        load_ict_raw(raw_copy)


def test_obj_with_texture_normal_indices_and_crlf(raw_copy, raw_model):
    """``f a/b/c`` and ``a//c`` forms and Windows line ends parse to the same model."""
    path = raw_copy / "generic_neutral_mesh.obj"
    text = path.read_bytes().replace(b"\n", b"\r\n")
    out = []
    for line in text.split(b"\r\n"):
        if line.startswith(b"f "):
            line = b"f " + b" ".join(t.split(b"/")[0] + b"//7" for t in line.split()[1:])
        out.append(line)
    path.write_bytes(b"\r\n".join(out))
    model = load_ict_raw(raw_copy, dtype=torch.float64)
    assert torch.equal(model.faces, raw_model.faces)
    assert torch.equal(model.mean, raw_model.mean)


# --- ict_npz_from_raw -----------------------------------------------------------------------------


def test_npz_from_raw_round_trips(ict_raw, raw_model, tmp_path):
    out = ict_npz_from_raw(ict_raw, tmp_path / "sub" / "ict_face_head.npz")
    assert out == tmp_path / "sub" / "ict_face_head.npz" and out.is_file()
    assert [p.name for p in out.parent.iterdir()] == ["ict_face_head.npz"]  # no temporary left
    model = load_ict_npz(out, dtype=torch.float64)
    assert torch.equal(model.faces, raw_model.faces)
    torch.testing.assert_close(model.mean, raw_model.mean, rtol=0, atol=1e-4)
    torch.testing.assert_close(model.shape_basis, raw_model.shape_basis, rtol=0, atol=1e-5)
    torch.testing.assert_close(model.expression_basis, raw_model.expression_basis, rtol=0, atol=1e-5)
    assert model.expression_names == ["jawOpen"] and model.landmarks == raw_model.landmarks


def test_npz_from_raw_matches_shared_layout(ict_raw, ict_npz, tmp_path):
    out = ict_npz_from_raw(ict_raw, tmp_path / "ict.npz")
    with np.load(out) as mine, np.load(ict_npz) as shared:
        assert sorted(mine.files) == sorted(shared.files)
        for key in shared.files:
            assert mine[key].dtype.kind == shared[key].dtype.kind, key
        assert str(mine["units"]) == "cm" and int(mine["face_vertex_count"]) == int(shared["face_vertex_count"])
        np.testing.assert_array_equal(mine["faces"], shared["faces"])
        np.testing.assert_array_equal(mine["landmarks_ibug68"], shared["landmarks_ibug68"])
        np.testing.assert_allclose(mine["mean"], shared["mean"], rtol=0, atol=1e-6)
        np.testing.assert_allclose(mine["identity_basis"], shared["identity_basis"][:2], rtol=0, atol=1e-6)
        jaw = list(shared["expression_names"]).index("jawOpen")
        np.testing.assert_allclose(mine["expression_basis"][0], shared["expression_basis"][jaw], rtol=0, atol=1e-6)


def test_npz_from_raw_failure_leaves_nothing(raw_copy, tmp_path):
    (raw_copy / "identity000.obj").write_text("v 1 2 3\n")
    out = tmp_path / "out" / "ict.npz"
    with pytest.raises(ModelFileError, match="identity000.obj"):
        ict_npz_from_raw(raw_copy, out)
    assert not out.exists()
    assert not out.parent.exists() or list(out.parent.iterdir()) == []


# --- fetch_ict --------------------------------------------------------------------------------------


def test_fetch_from_source_into_cache(ict_raw, tmp_path, monkeypatch):
    monkeypatch.setenv("FACENORMALS_HOME", str(tmp_path / "home"))
    monkeypatch.delenv("FACENORMALS_ICT", raising=False)
    messages: list[str] = []
    archive = fetch_ict(ict_raw.parent, progress=messages.append)  # the repository root
    assert archive == tmp_path / "home" / "ict" / "ict_face_head.npz" and archive.is_file()
    assert find_ict_archive() == archive
    assert load_ict_npz(archive).num_shape == 2
    assert any("partial" in m for m in messages)
    from facenormals.models import load_model

    # the partial copy now stands in for the model everywhere: say so each time it is loaded by name
    for spec in ("auto", "ict"):
        with pytest.warns(UserWarning, match=r"ict_face_head\.npz: a partial ICT-FaceKit \(2 identity components and "
                                             r"1 expressions of 100 and 53\); replace it .* --force"):
            assert load_model(spec).num_shape == 2

    def no_work(*args, **kwargs):
        raise AssertionError("a cached archive must not be rebuilt")

    monkeypatch.setattr(fetch_module, "ict_npz_from_raw", no_work)
    stamp = archive.stat().st_mtime_ns
    assert fetch_ict(ict_raw, progress=messages.append) == archive
    assert archive.stat().st_mtime_ns == stamp


def test_the_release_is_recognised_and_a_different_one_warns(ict_raw, raw_copy, tmp_path, recwarn):
    from facenormals.models.fetch import ict_release_differences

    messages: list[str] = []
    archive = fetch_ict(ict_raw, cache=tmp_path / "same", progress=messages.append)
    assert ict_release_differences(archive) == [] and not recwarn.list
    assert messages[-1].endswith("; the release facenormals was built with")
    # an upstream change of one vertex (the first one is 0 -2.48251 11.8387 cm)
    neutral = raw_copy / "generic_neutral_mesh.obj"
    text = neutral.read_text()
    neutral.write_text(text.replace("v 0 -2.48251 11.8387\n", "v 0 -2.48251 11.8388\n", 1))
    with pytest.warns(UserWarning, match=r"differs from the release facenormals was built with \(mean changed\)"):
        archive = fetch_ict(raw_copy.parent, cache=tmp_path / "other", progress=messages.append)
    assert ict_release_differences(archive) == ["mean"] and messages[-1].endswith("; a different release")


def test_the_shared_archive_is_the_release(ict_npz):
    from facenormals.models.fetch import ict_release_differences

    assert ict_release_differences(ict_npz) == []


def test_fetch_force_rebuilds(ict_raw, tmp_path):
    archive = fetch_ict(ict_raw, cache=tmp_path, progress=None)  # the FaceXModel folder itself
    good = archive.read_bytes()
    with np.load(archive) as data:
        arrays = {key: data[key] for key in data.files}
    np.savez(archive, **{**arrays, "mean": arrays["mean"] + 1.0})  # a different but readable archive is kept ...
    changed = archive.read_bytes()
    assert fetch_ict(ict_raw, cache=tmp_path, progress=None) == archive and archive.read_bytes() == changed
    fetch_ict(ict_raw, cache=tmp_path, progress=None, force=True)  # ... unless forced
    assert archive.read_bytes() == good and load_ict_npz(archive).num_vertices == 11248
    # a damaged one (a truncated copy, or not an archive) is converted again without --force, and says so
    for damaged in (good[: len(good) // 2], b"stale"):
        archive.write_bytes(damaged)
        lines = []
        assert fetch_ict(ict_raw, cache=tmp_path, progress=lines.append) == archive and archive.read_bytes() == good
        assert lines[0].startswith(f"{archive} is damaged (BadZipFile") and lines[0].endswith("converting it again")
    # a cached archive: a given source is not converted, and says so; a missing one is an error
    lines = []
    assert fetch_ict(ict_raw, cache=tmp_path, progress=lines.append) == archive
    assert lines == [f"ICT-FaceKit is already in {archive}; {ict_raw} was not converted (--force converts it)"]
    with pytest.raises(ModelFileError, match="nowhere: no such file or folder"):
        fetch_ict(tmp_path / "nowhere", cache=tmp_path, progress=None)


def test_fetch_without_network_names_from(tmp_path, monkeypatch):
    def offline(*args, **kwargs):
        raise urllib.error.URLError("[Errno -3] Temporary failure in name resolution")

    monkeypatch.setattr(urllib.request, "urlopen", offline)
    with pytest.raises(FetchError, match="--from") as info:
        fetch_ict(cache=tmp_path, progress=None)
    assert isinstance(info.value, ModelFileError) and isinstance(info.value, OSError)
    assert "could not download ICT-FaceKit" in str(info.value) and "name resolution" in str(info.value)
    leftovers = list((tmp_path / "ict").iterdir()) if (tmp_path / "ict").exists() else []
    assert leftovers == []


class _FakeResponse(io.BytesIO):
    def __init__(self, payload: bytes, length: int | None = None, send_length: bool = True) -> None:
        super().__init__(payload)
        self.headers = {"Content-Length": str(len(payload) if length is None else length)} if send_length else {}


def _repo_zip(folder: Path) -> bytes:
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", zipfile.ZIP_DEFLATED, compresslevel=1) as archive:
        archive.writestr("ICT-FaceKit-master/README.md", "ICT-FaceKit")
        for path in sorted(folder.iterdir()):
            archive.write(path, f"ICT-FaceKit-master/FaceXModel/{path.name}")
    return buffer.getvalue()


def test_fetch_downloads_converts_and_keeps_zip(ict_raw, tmp_path, monkeypatch):
    payload = _repo_zip(ict_raw)
    calls = []

    def serve(request, timeout=None):
        calls.append((request.full_url, timeout))
        return _FakeResponse(payload)

    monkeypatch.setattr(urllib.request, "urlopen", serve)
    archive = fetch_ict(cache=tmp_path, progress=None)
    assert calls == [(fetch_module.ICT_URL, 30.0)]
    assert sorted(p.name for p in (tmp_path / "ict").iterdir()) == ["ICT-FaceKit-master.zip", "ict_face_head.npz"]
    assert load_ict_npz(archive).num_shape == 2
    # the kept zip is reused when the archive is rebuilt
    monkeypatch.setattr(urllib.request, "urlopen", lambda *a, **k: pytest.fail("downloaded twice"))
    archive.unlink()
    assert fetch_ict(cache=tmp_path, progress=None) == archive and archive.is_file()


def test_fetch_interrupted_download_leaves_nothing(tmp_path, monkeypatch):
    monkeypatch.setattr(urllib.request, "urlopen", lambda *a, **k: _FakeResponse(b"PK\x03\x04abc", length=10_000))
    with pytest.raises(FetchError, match="--from"):
        fetch_ict(cache=tmp_path, progress=None)
    assert list((tmp_path / "ict").iterdir()) == []


def test_fetch_corrupt_cached_zip(tmp_path, monkeypatch):
    (tmp_path / "ict").mkdir()
    (tmp_path / "ict" / "ICT-FaceKit-master.zip").write_bytes(b"<html>not a zip</html>")
    monkeypatch.setattr(urllib.request, "urlopen", lambda *a, **k: pytest.fail("must not download"))
    with pytest.raises(ModelFileError, match=r"ICT-FaceKit-master\.zip.*not a valid zip"):
        fetch_ict(cache=tmp_path, progress=None)
    assert not (tmp_path / "ict" / "ict_face_head.npz").exists()


def test_fetch_from_bad_source_leaves_no_archive(raw_copy, tmp_path):
    (raw_copy / "jawOpen.obj").write_text("v 0 0 0\n")
    with pytest.raises(ModelFileError, match=r"jawOpen\.obj"):
        fetch_ict(raw_copy, cache=tmp_path / "cache", progress=None)
    assert not (tmp_path / "cache" / "ict" / "ict_face_head.npz").exists()


def test_a_damaged_compressed_archive_or_repository_zip_names_the_file(ict_npz, raw_copy, tmp_path):
    """Regression: the shared archive and GitHub's zips are deflated, and a damaged deflate stream raised
    a bare zlib.error (and lost fetch's "delete the zip" advice)."""
    import zipfile

    from facenormals.models import ModelFileError, load_ict_npz
    from tests.conftest import damage_deflate_stream

    with zipfile.ZipFile(ict_npz) as source, zipfile.ZipFile(tmp_path / "ict.npz", "w", zipfile.ZIP_DEFLATED) as target:
        for name in source.namelist():
            target.writestr(name, source.read(name))
    damage_deflate_stream(tmp_path / "ict.npz", "mean.npy")
    with pytest.raises(ModelFileError, match=r"ict\.npz: cannot read ICT-FaceKit archive \(error: .*invalid block type"):
        load_ict_npz(tmp_path / "ict.npz")

    repository = tmp_path / "ICT-FaceKit-master.zip"
    with zipfile.ZipFile(repository, "w", zipfile.ZIP_DEFLATED) as archive:
        for path in raw_copy.iterdir():
            archive.write(path, f"ICT-FaceKit-master/FaceXModel/{path.name}")
    damage_deflate_stream(repository, "ICT-FaceKit-master/FaceXModel/generic_neutral_mesh.obj")
    with pytest.raises(ModelFileError, match=r"generic_neutral_mesh\.obj: cannot read \(error: .*invalid block type"):
        fetch_ict(repository, cache=tmp_path / "cache", progress=None)
    assert not (tmp_path / "cache" / "ict" / "ict_face_head.npz").exists()


def test_an_inconsistent_archive_names_the_file_and_its_face_count_is_used(ict_npz, tmp_path):
    from facenormals.models import ModelFileError, load_ict_npz

    with np.load(ict_npz) as data:
        arrays = {k: data[k] for k in data.files}
    arrays["identity_basis"] = arrays["identity_basis"][:2]  # small copies
    arrays["expression_basis"] = arrays["expression_basis"][:1]
    arrays["expression_names"] = arrays["expression_names"][:1]
    np.savez(tmp_path / "few.npz", **{**arrays, "landmarks_ibug68": arrays["landmarks_ibug68"][:10]})
    with pytest.raises(ModelFileError, match="few.npz: inconsistent ICT-FaceKit archive"):
        load_ict_npz(tmp_path / "few.npz")
    np.savez(tmp_path / "count.npz", **{**arrays, "face_vertex_count": np.array(100)})
    assert int(load_ict_npz(tmp_path / "count.npz").face_region[100:].sum()) == 0
    for bad in (True, 2.5, 0):
        with pytest.raises(ValueError, match="num_shape: expected an integer in 1..2"):
            load_ict_npz(tmp_path / "count.npz", num_shape=bad)
    # arrays of the wrong kind or rank: errors naming the file, not tracebacks from inside
    for change, match in (
            ({"face_vertex_count": np.array([1, 2])}, r"array 'face_vertex_count' has dtype int64 and shape \(2,\), "
                                                      "expected a number"),
            ({"mean": arrays["mean"].astype(str)}, "array 'mean' has dtype <U"),
            ({"identity_basis": np.array(1.0, np.float32)}, r"array 'identity_basis' has dtype float32 and shape "
                                                            r"\(\), expected 3-D numbers"),
            ({"identity_basis": arrays["identity_basis"][:0]}, "the archive has no identity modes"),
            ({"landmarks_ibug68": arrays["landmarks_ibug68"] + 0.7}, "array 'landmarks_ibug68' holds indices that "
                                                                     "are not whole numbers"),
            ({"faces": arrays["faces"] + 0.5}, "array 'faces' holds indices that are not whole numbers")):
        np.savez(tmp_path / "bad.npz", **{**arrays, **change})
        with pytest.raises(ModelFileError, match="bad.npz: " + match):
            load_ict_npz(tmp_path / "bad.npz")
    np.savez(tmp_path / "whole.npz", **{**arrays, "faces": arrays["faces"].astype(np.float64)})
    assert torch.equal(load_ict_npz(tmp_path / "whole.npz").faces, load_ict_npz(tmp_path / "count.npz").faces)


def test_a_download_cut_short_without_a_length_is_not_kept(ict_raw, tmp_path, monkeypatch):
    payload = _repo_zip(ict_raw)
    monkeypatch.setattr(urllib.request, "urlopen",
                        lambda *a, **k: _FakeResponse(payload[: len(payload) // 2], send_length=False))
    with pytest.raises(FetchError, match="not a complete zip archive"):
        fetch_ict(cache=tmp_path, progress=None)
    assert list((tmp_path / "ict").iterdir()) == []  # a retry downloads again
    monkeypatch.setattr(urllib.request, "urlopen", lambda *a, **k: _FakeResponse(payload))
    assert load_ict_npz(fetch_ict(cache=tmp_path, progress=None)).num_shape == 2


def _small_archive(ict_npz) -> dict:
    """The archive's arrays with 2 identity modes and 1 expression (small copies)."""
    with np.load(ict_npz) as data:
        arrays = {k: data[k] for k in data.files}
    arrays["identity_basis"] = arrays["identity_basis"][:2]
    arrays["expression_basis"] = arrays["expression_basis"][:1]
    arrays["expression_names"] = arrays["expression_names"][:1]
    return arrays


def test_a_single_expression_name_names_the_archive(ict_npz, tmp_path):
    """A 0-d expression_names (one name saved as a scalar) raised a bare TypeError from iterating it."""
    arrays = _small_archive(ict_npz)
    np.savez(tmp_path / "bad.npz", **{**arrays, "expression_names": arrays["expression_names"][0]})
    with pytest.raises(ModelFileError, match=r"bad.npz: array 'expression_names' has shape \(\), expected a 1-D list"):
        load_ict_npz(tmp_path / "bad.npz")


def test_a_face_vertex_count_outside_the_mesh_names_the_archive(ict_npz, tmp_path):
    """face_vertex_count -1 gave an empty face region, silently."""
    arrays = _small_archive(ict_npz)
    num_vertices = arrays["mean"].shape[0]
    for count in (-1, 0, num_vertices + 1, np.inf):
        np.savez(tmp_path / "bad.npz", **{**arrays, "face_vertex_count": np.array(count)})
        with pytest.raises(ModelFileError, match=f"bad.npz: face_vertex_count is {count}, expected 1 to the "
                                                 f"{num_vertices} vertices"):
            load_ict_npz(tmp_path / "bad.npz")
    np.savez(tmp_path / "all.npz", **{**arrays, "face_vertex_count": np.array(num_vertices)})
    assert int(load_ict_npz(tmp_path / "all.npz").face_region.sum()) > 0


def test_a_damaged_npy_header_in_the_archive_is_refused(ict_npz, tmp_path, monkeypatch):
    """Regression: np.load reads what a member's .npy header declares: a damaged header, (1, N, 3) for
    the (2, N, 3) identity basis, loaded one identity mode silently (and fetch took the archive for the
    release). Each member must now hold exactly what its header declares."""
    from facenormals.models import load_model

    path = tmp_path / "ict.npz"
    np.savez_compressed(path, **_small_archive(ict_npz))
    assert load_ict_npz(path).num_shape == 2
    damaged = tmp_path / "damaged.npz"  # the archive rewritten around the damaged member (its checksums agree)
    with zipfile.ZipFile(path) as source, zipfile.ZipFile(damaged, "w", zipfile.ZIP_DEFLATED) as target:
        for info in source.infolist():
            member = source.read(info)
            if info.filename == "identity_basis.npy":
                assert b"'shape': (2, " in member
                member = member.replace(b"'shape': (2, ", b"'shape': (1, ")
            target.writestr(info, member)
    match = (r"damaged\.npz: cannot read ICT-FaceKit archive \(ValueError: member 'identity_basis\.npy': its \.npy "
             r"header declares \(1, \d+, 3\) float\d+ .*\(a damaged header\)\)")
    for load in (load_ict_npz, load_model, fetch_module.ict_release_differences):
        with pytest.raises(ModelFileError, match=match):
            load(damaged)
    monkeypatch.setenv("FACENORMALS_ICT", str(damaged))
    with pytest.raises(ModelFileError, match=match + "; replace it"):
        load_model("ict")


def test_the_archive_is_not_looked_up_beside_the_working_directory(tmp_path, monkeypatch):
    """Regression: ``shared/data`` beside the working directory was a candidate, so an installed
    package fitted ICT-FaceKit or the built-in head depending on where a command ran."""
    import facenormals.models.registry as registry

    monkeypatch.setenv("FACENORMALS_HOME", str(tmp_path / "home"))
    monkeypatch.delenv("FACENORMALS_ICT", raising=False)
    monkeypatch.setattr(registry, "__file__", str(tmp_path / "site" / "facenormals" / "models" / "registry.py"))
    work = tmp_path / "work" / "project"
    for base in (work, work.parent):
        archive = base / "shared" / "data" / "ict_facekit" / "ict_face_head.npz"
        archive.parent.mkdir(parents=True)
        archive.write_bytes(b"found by the working directory")
    monkeypatch.chdir(work)
    assert find_ict_archive() is None
