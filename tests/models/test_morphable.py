import numpy as np
import pytest
import torch

from facenormals.models import ModelFileError, MorphableModel, load_ict_npz
from tests.conftest import assert_close


def tiny_model(dtype=torch.float64, num_shape=3, num_expr=2):
    g = torch.Generator().manual_seed(0)
    mean = torch.randn(5, 3, generator=g, dtype=dtype)
    basis = torch.randn(num_shape, 5, 3, generator=g, dtype=dtype)
    expr = torch.randn(num_expr, 5, 3, generator=g, dtype=dtype)
    faces = torch.tensor([[0, 1, 2], [0, 2, 3], [0, 3, 4]])
    return MorphableModel(mean, basis, faces, shape_std=torch.tensor([2.0, 1.0, 0.5], dtype=dtype),
                          expression_basis=expr, landmarks={"nose_tip": 1, "chin": 4},
                          expression_names=["a", "b"], name="tiny", metadata={"source": "test"})


def test_forward_matches_naive_sum(dtype):
    model = tiny_model().to(dtype)
    g = torch.Generator().manual_seed(1)
    y = torch.randn(4, 3, generator=g, dtype=dtype)
    e = torch.rand(4, 2, generator=g, dtype=dtype)
    out = model(y, e)
    assert out.shape == (4, 5, 3) and out.dtype == dtype
    for b in range(4):
        ref = model.mean.clone()
        for k in range(3):
            ref = ref + y[b, k] * model.shape_basis[k]
        for j in range(2):
            ref = ref + e[b, j] * model.expression_basis[j]
        assert_close(out[b], ref)
    assert_close(model(torch.zeros(1, 3, dtype=dtype))[0], model.mean)


def test_buffers_follow_to():
    model = tiny_model().to(torch.float32)
    assert model.mean.dtype == torch.float32 and model.shape_std.dtype == torch.float32
    assert model.faces.dtype == torch.long
    names = {n for n, _ in model.named_buffers()}
    assert {"mean", "shape_basis", "shape_std", "faces", "expression_basis", "landmark_indices"} <= names


def test_basis_matrix_is_the_vertex_jacobian_and_follows_the_buffers():
    model = tiny_model()
    g = torch.Generator().manual_seed(1)
    y, e = torch.randn(1, 3, generator=g, dtype=torch.float64), torch.randn(1, 2, generator=g, dtype=torch.float64)
    J = model.basis_matrix(with_expression=True)
    assert J.shape == (3 * model.num_vertices, 5) and J.is_contiguous()
    for i in range(model.num_vertices):  # naive loop over vertices and coordinates
        for j in range(3):
            expected = torch.cat([model.shape_basis[:, i, j], model.expression_basis[:, i, j]])
            assert torch.equal(J[3 * i + j], expected)
    assert_close((J @ torch.cat([y, e], 1)[0]).view(-1, 3), model(y, e)[0] - model.mean)
    assert model.basis_matrix() is model.basis_matrix() and model.basis_matrix().shape[1] == 3
    model.shape_basis.mul_(2.0)  # an in-place edit invalidates the cached copy
    assert torch.equal(model.basis_matrix()[:, 0], model.shape_basis[0].reshape(-1))
    assert model.to(torch.float32).basis_matrix().dtype == torch.float32
    single = model.basis_matrix(dtype=torch.float64)  # another dtype: its own cached copy
    assert single.dtype == torch.float64 and single is model.basis_matrix(dtype=torch.float64)
    assert torch.equal(single, model.basis_matrix().double())


def test_landmarks():
    model = tiny_model()
    v = model(torch.randn(2, 3, generator=torch.Generator().manual_seed(1), dtype=torch.float64))
    assert model.landmarks == {"nose_tip": 1, "chin": 4}
    assert_close(model.landmark_vertices(v), v[:, [1, 4]])
    assert_close(model.landmark_vertices(v, ["chin"]), v[:, [4]])
    with pytest.raises(ValueError, match="unknown landmarks"):
        model.landmark_vertices(v, ["ear"])


def test_gradients_flow():
    model = tiny_model()
    g = torch.Generator().manual_seed(1)
    y = torch.randn(2, 3, generator=g, dtype=torch.float64, requires_grad=True)
    e = torch.randn(2, 2, generator=g, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda a, b: model(a, b), (y, e))


def test_save_load_round_trip(tmp_path):
    model = tiny_model()
    path = tmp_path / "m.npz"
    model.save(path)
    loaded = MorphableModel.load(path, dtype=torch.float64)
    for name in ("mean", "shape_basis", "shape_std", "expression_basis"):
        assert_close(getattr(loaded, name), getattr(model, name))
    assert torch.equal(loaded.faces, model.faces)
    assert loaded.landmarks == model.landmarks
    assert loaded.expression_names == ["a", "b"] and loaded.name == "tiny"
    assert loaded.metadata == {"source": "test"}


def test_load_errors_name_the_file(tmp_path):
    missing = tmp_path / "nope.npz"
    with pytest.raises(ModelFileError, match="nope.npz: model file not found"):
        MorphableModel.load(missing)
    from facenormals.models import load_model

    with pytest.raises(ModelFileError, match=r"^ICT: model file not found \(model names: \"ict\", \"builtin\", \"auto\"\)$"):
        load_model("ICT")  # a mistyped name
    with pytest.raises(ModelFileError, match=r"nope.npz: model file not found$"):
        load_model(missing)
    garbage = tmp_path / "garbage.npz"
    garbage.write_bytes(b"this is not a zip archive")
    with pytest.raises(ModelFileError, match="garbage.npz: cannot read"):
        MorphableModel.load(garbage)
    model = tiny_model()
    good = tmp_path / "good.npz"
    model.save(good)
    truncated = tmp_path / "truncated.npz"
    truncated.write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    with pytest.raises(ModelFileError, match="truncated.npz"):
        MorphableModel.load(truncated)
    other = tmp_path / "other.npz"
    np.savez(other, a=np.zeros(3))
    with pytest.raises(ModelFileError, match=r"other.npz: not a facenormals model file, missing keys"):
        MorphableModel.load(other)


def test_a_damaged_compressed_model_file_names_the_file(tmp_path):
    """Regression: a damaged deflate stream (a compressed .npz, e.g. re-saved with savez_compressed)
    raised a bare zlib.error from deep inside numpy."""
    import zipfile

    from tests.conftest import damage_deflate_stream

    plain = tmp_path / "plain.npz"
    tiny_model().save(plain)
    packed = tmp_path / "packed.npz"
    with zipfile.ZipFile(plain) as source, zipfile.ZipFile(packed, "w", zipfile.ZIP_DEFLATED) as target:
        for name in source.namelist():
            target.writestr(name, source.read(name))
    assert MorphableModel.load(packed).num_shape == 3  # compressed files load
    damage_deflate_stream(packed, "mean.npy")
    with pytest.raises(ModelFileError, match=r"packed\.npz: cannot read model file \(error: .*invalid block type"):
        MorphableModel.load(packed)


def test_a_damaged_npy_header_in_a_model_file_is_refused(tmp_path):
    """Regression: a changed shape digit in a member's .npy header ((20480, 3) -> (10480, 3)) loaded half
    the mesh silently: numpy reads the bytes the header declares and stops there, before zip's CRC-32
    check at the member's end. Each member is now read to its end and must hold what its header declares."""
    from facenormals.models import builtin_head_model, load_model

    path = tmp_path / "head.npz"
    builtin_head_model().save(path)
    data = path.read_bytes()
    assert data.count(b"'shape': (20480, 3)") == 1  # faces.npy's header
    path.write_bytes(data.replace(b"'shape': (20480, 3)", b"'shape': (10480, 3)"))  # the zip's checksums unchanged
    for load in (MorphableModel.load, load_model):
        with pytest.raises(ModelFileError, match=r"head\.npz: cannot read model file \(ValueError: member "
                                                 r"'faces\.npy': its \.npy header declares \(10480, 3\) int64 "
                                                 r"\(251520 bytes of data\), but the member holds 491520 \(a damaged "
                                                 r"header\)\)"):
            load(path)
    path.write_bytes(data.replace(b"'shape': (20480, 3)", b"'shape': (30480, 3)"))  # more than it holds
    with pytest.raises(ModelFileError,
                       match=r"head\.npz: .*member 'faces\.npy': its \.npy header declares \(30480, 3\)"):
        MorphableModel.load(path)
    damaged = bytearray(data)  # a damaged value: the member fails its CRC-32 check
    damaged[data.index(b"'shape': (20480, 3)") + 4000] ^= 0x01  # in faces.npy's data
    path.write_bytes(bytes(damaged))
    with pytest.raises(ModelFileError, match=r"head\.npz: cannot read model file \(BadZipFile: Bad CRC-32 for file "
                                             r"'faces\.npy'\)"):
        MorphableModel.load(path)


@pytest.mark.parametrize(
    "kwargs,match",
    [
        (dict(mean=torch.zeros(5, 2)), r"mean: expected shape \(N, 3\)"),
        (dict(shape_basis=torch.zeros(3, 4, 3)), r"shape_basis: expected shape \(K, N, 3\) with N=5"),
        (dict(faces=torch.tensor([[0, 1, 5]])), r"faces: expected vertex indices in \[0, 5\)"),
        (dict(mean=torch.full((5, 3), float("nan"))), "mean: expected finite values"),
        (dict(shape_basis=torch.full((3, 5, 3), float("inf"))), "shape_basis: expected finite values"),
        (dict(expression_basis=torch.full((1, 5, 3), float("nan"))), "expression_basis: expected finite values"),
        (dict(faces=torch.zeros(2, 3)), "faces: expected an integer tensor"),
        (dict(shape_std=torch.ones(4)), r"shape_std: expected shape \(K,\) with K=3"),
        (dict(shape_std=torch.tensor([1.0, 0.0, 1.0])), "shape_std: expected positive"),
        (dict(landmarks={"x": 9}), "landmarks: index 9"),
        (dict(faces=torch.zeros(0, 3, dtype=torch.long)), r"faces: expected at least one triangle, got shape \(0, 3\)"),
    ],
)
def test_constructor_errors(kwargs, match):
    args = dict(mean=torch.zeros(5, 3), shape_basis=torch.zeros(3, 5, 3), faces=torch.tensor([[0, 1, 2]]))
    args.update(kwargs)
    with pytest.raises(ValueError, match=match):
        MorphableModel(**args)


def test_forward_errors():
    model = tiny_model()
    with pytest.raises(ValueError, match=r"shape_coeffs: expected shape \(B, 3\)"):
        model(torch.zeros(2, 4, dtype=torch.float64))
    with pytest.raises(ValueError, match=r"expression_coeffs: expected shape \(B, 2\) with B=2"):
        model(torch.zeros(2, 3, dtype=torch.float64), torch.zeros(3, 2, dtype=torch.float64))
    with pytest.raises(ValueError, match="shape_coeffs: expected dtype torch.float64 on cpu as the model"):
        model(torch.zeros(2, 3, dtype=torch.float32))
    with pytest.raises(ValueError, match="expression_coeffs: expected dtype torch.float64"):
        model(torch.zeros(2, 3, dtype=torch.float64), torch.zeros(2, 2, dtype=torch.float32))


def test_a_model_without_expressions_takes_empty_expression_coeffs():
    full = tiny_model()
    model = MorphableModel(full.mean, full.shape_basis, full.faces)
    y = torch.randn(2, 3, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    assert_close(model(y, torch.zeros(2, 0, dtype=torch.float64)), model(y))


def test_load_rejects_non_finite_or_mistyped_arrays(tmp_path):
    """A model file with NaNs, float faces (which would be truncated) or text arrays is a ModelFileError
    naming the file, as with the other formats' loaders."""
    model = tiny_model()
    model.save(tmp_path / "good.npz")
    arrays = dict(np.load(tmp_path / "good.npz"))
    for key, value, match in (("mean", np.full((5, 3), np.nan), "mean: expected finite values"),
                              ("faces", arrays["faces"] + 0.5, "array 'faces' has dtype float64, expected integer"),
                              ("mean", np.full((5, 3), "x"), "array 'mean' has dtype <U1, expected floating-point")):
        path = tmp_path / f"bad_{key}.npz"
        np.savez(path, **{**arrays, key: value})
        with pytest.raises(ModelFileError, match=f"bad_{key}.npz: .*{match}"):
            MorphableModel.load(path)


def test_ict_npz(ict_npz):
    model = load_ict_npz(ict_npz)
    assert (model.num_vertices, model.num_shape, model.num_expressions) == (11248, 100, 53)
    assert model.faces.shape == (22288, 3)
    raw = np.load(ict_npz)
    # cm -> mm and OpenGL -> model frame (x, -y, -z)
    assert_close(model.mean, torch.from_numpy(raw["mean"] * np.array([10.0, -10.0, -10.0], dtype=np.float32)))
    region = model.face_region
    assert 4000 < int(region.sum()) < int(raw["face_vertex_count"]) and not region[int(raw["face_vertex_count"]):].any()
    nose = model.mean[model.landmarks["nose_tip"]]
    assert ((model.mean[region] - nose).norm(dim=1) < 95.0).all()
    assert model.metadata["landmarks_ibug68"] == raw["landmarks_ibug68"].tolist()
    nose = model.mean[model.landmarks["nose_tip"]]
    assert nose[2] < model.mean[:, 2].min() + 1.0  # within 1 mm of the most forward vertex


def test_inconsistent_landmark_tables_and_units_are_refused(tmp_path):
    model = tiny_model()
    path = tmp_path / "m.npz"
    model.save(path)
    with np.load(path) as data:
        arrays = {k: data[k] for k in data.files}
    for change, match in (({"landmark_names": np.array(["a", "b", "c"])}, "3 landmark names .* for 2 landmark indices"),
                          ({"landmark_names": np.array(["a", "a"])}, r"2 landmark names \(distinct: 1\)"),
                          ({"units": np.array("cm")}, "units 'cm', expected 'mm'"),
                          ({"version": np.array([1, 2])}, r"format version \[1, 2\], expected an integer")):
        np.savez(tmp_path / "bad.npz", **{**arrays, **change})
        with pytest.raises(ModelFileError, match=f"bad.npz: {match}"):
            MorphableModel.load(tmp_path / "bad.npz")


def test_sampling_and_export_check_their_arguments(tmp_path):
    model = tiny_model()
    for batch in (-1, 2.5, True):
        with pytest.raises(ValueError, match="batch: expected a non-negative integer"):
            model.sample_shape_coeffs(batch)
    for scale in (float("nan"), -1.0):
        with pytest.raises(ValueError, match="scale: expected a finite number >= 0"):
            model.sample_shape_coeffs(2, scale=scale)
    with pytest.raises(ValueError, match=r"path: expected a .ply or .obj file, got '.*head.foo'"):
        model.export_mesh(tmp_path / "head.foo")
    with pytest.raises(ValueError, match=r"shape_coeffs: expected shape \(3,\) or \(1, 3\), got \(2, 3\)"):
        model.export_mesh(tmp_path / "head.ply", torch.zeros(2, 3))


def test_landmark_indices_must_be_integers():
    """int() would truncate 2.7 to vertex 2."""
    with pytest.raises(ValueError, match=r"landmarks\['a'\]: expected an integer, got float 2.7"):
        MorphableModel(torch.zeros(5, 3), torch.zeros(3, 5, 3), torch.tensor([[0, 1, 2]]), landmarks={"a": 2.7})


def test_a_model_in_metres_is_refused_where_millimetres_matter():
    """The fit, the landmark z-buffer and the generator work in mm: a model in metres would be fitted
    with every mm constant 1000x off and its errors printed as mm."""
    from facenormals.fitting import fit_head, hidden_landmarks
    from facenormals.models import builtin_head_model

    head = builtin_head_model()
    head.check_millimetres()
    metres = MorphableModel(head.mean / 1000, head.shape_basis / 1000, head.faces, shape_std=head.shape_std,
                            landmarks=head.landmarks, name="metres")
    match = r"model 'metres': its mean spans 0.367 units across, not the 50-5000 of a face or head in millimetres"
    with pytest.raises(ValueError, match=match):
        metres.check_millimetres()
    with pytest.raises(ValueError, match=match):
        fit_head(torch.zeros(1, 3, 32, 32), torch.zeros(1, 24, 2), metres)
    with pytest.raises(ValueError, match=match):
        hidden_landmarks(metres, torch.eye(3)[None], torch.tensor([[0.0, 0.0, 0.6]]),
                         torch.tensor([[300.0, 63.5, 63.5]]), (128, 128))
    with pytest.raises(ValueError, match="units across"):
        MorphableModel(head.mean * 1000, head.shape_basis, head.faces).check_millimetres()  # micrometres


def test_a_model_wound_inside_out_is_refused():
    """Regression: triangles wound clockwise (normals pointing into the head) were accepted, and the fit
    then matched the inward normals to nothing and returned the mean head as CONVERGED; a face region
    derived from them was empty. A face mask (an open cap) wound outward passes."""
    from facenormals.models import builtin_head_model

    head = builtin_head_model()
    with pytest.raises(ValueError, match=r"faces: the mean's triangles face inward .* reverse them \(faces\[:, \[0, 2, 1\]\]\)"):
        MorphableModel(head.mean, head.shape_basis, head.faces[:, [0, 2, 1]])
    front = head.mean[:, 2] < float(head.mean[:, 2].median())  # the front half, an open cap
    keep = front[head.faces].all(1)
    index = torch.full((head.num_vertices,), -1, dtype=torch.long)
    index[front] = torch.arange(int(front.sum()))
    cap = index[head.faces[keep]]
    MorphableModel(head.mean[front], head.shape_basis[:, front], cap)
    with pytest.raises(ValueError, match="face inward"):
        MorphableModel(head.mean[front], head.shape_basis[:, front], cap[:, [0, 2, 1]])


def test_arguments_are_named_before_a_file_is_blamed(tmp_path):
    """A non-floating dtype was reported as an 'inconsistent' file; metadata that JSON cannot hold
    failed only at save time with a bare TypeError; an annotated model in metres got a face region
    of every vertex (the 95 mm radius is in mm)."""
    from facenormals.models import builtin_head_model

    path = tmp_path / "m.npz"
    tiny_model().save(path)
    with pytest.raises(ValueError, match="dtype: expected a floating-point torch dtype, got torch.int32"):
        MorphableModel.load(path, dtype=torch.int32)
    with pytest.raises(ValueError, match="metadata: expected JSON values"):
        MorphableModel(torch.zeros(3, 3), torch.zeros(1, 3, 3), torch.tensor([[0, 1, 2]]),
                       metadata={"scale": np.float32(1.0)})
    head = builtin_head_model()
    metres = MorphableModel(head.mean / 1000, head.shape_basis / 1000, head.faces, name="metres")
    with pytest.raises(ValueError, match="model 'metres': its mean spans 0.367 units across"):
        metres.with_annotations(head.landmarks)


def test_with_annotations_warns_about_names_the_network_does_not_know():
    from facenormals.models import builtin_head_model

    head = builtin_head_model()
    bare = MorphableModel(head.mean, head.shape_basis, head.faces, shape_std=head.shape_std)
    marks = dict(head.landmarks)
    marks["nose-tip"] = marks.pop("nose_tip")
    with pytest.warns(UserWarning) as record:
        model = bare.with_annotations(marks)
    messages = " | ".join(str(w.message) for w in record)
    assert "['nose-tip'] are not among the network's LANDMARK_NAMES" in messages
    assert "no 'nose_tip', so the face region scored by evaluation stays the model's own (10242 of 10242" in messages
    assert bool(model.face_region.all())


def test_derived_data_follow_replaced_buffers():
    """The cache of basis_matrix() was keyed by id(): a new buffer allocated where a freed one had
    been (same id, version 0) got the freed one's cached matrix."""
    model = tiny_model()
    for step in range(20):
        model.basis_matrix()
        model.shape_basis = model.shape_basis * 1.5  # the old buffer is freed ...
        model.shape_basis = model.shape_basis + 1.0  # ... and its memory (and id) may be reused
        assert torch.equal(model.basis_matrix()[:, 0], model.shape_basis[0].reshape(-1)), step
    normals = model.landmark_normals()
    model.mean = model.mean.flip(0)
    assert not torch.equal(model.landmark_normals(), normals)


def test_a_model_pickles_and_moves_without_its_derived_cache():
    import pickle

    model = tiny_model()
    model.basis_matrix()
    copy = pickle.loads(pickle.dumps(model))
    assert "_derived_cache" not in copy.__dict__ and torch.equal(copy.basis_matrix(), model.basis_matrix())
    moved = model.to(torch.float32)
    assert "_derived_cache" not in moved.__dict__ and moved.basis_matrix().dtype == torch.float32


def test_annotations_load_and_matrices_check_their_arguments(tmp_path):
    from facenormals.models import builtin_head_model

    head = builtin_head_model()
    bare = MorphableModel(head.mean, head.shape_basis, head.faces, shape_std=head.shape_std)
    with pytest.raises(ValueError, match=r"landmarks: index 99999 of 'nose_tip' is outside \[0, 10242\)"):
        bare.with_annotations({**head.landmarks, "nose_tip": 99999})
    for radius in (-5.0, float("nan"), "95"):  # an empty face region would score nothing
        with pytest.raises(ValueError, match="radius: expected a (finite|real) number"):
            bare.with_annotations(head.landmarks, radius=radius)
    with pytest.raises(ValueError, match="dtype: expected a floating-point torch dtype, got torch.int64"):
        bare.basis_matrix(dtype=torch.int64)
    with pytest.raises(ValueError, match=r"shape_coeffs: expected shape \(24,\) or \(1, 24\), got \(2, 12\)"):
        bare.export_mesh(tmp_path / "head.ply", torch.zeros(2, 12))
    model = tiny_model()
    model.save(tmp_path / "m.npz")
    arrays = dict(np.load(tmp_path / "m.npz"))
    for change, match in (({"face_region": np.arange(5) % 3}, "array 'face_region' has dtype int64, expected bool"),
                          ({"version": np.array(0)}, "format version 0, expected 1 to")):
        np.savez(tmp_path / "bad.npz", **{**arrays, **change})
        with pytest.raises(ModelFileError, match=f"bad.npz: {match}"):
            MorphableModel.load(tmp_path / "bad.npz")


def test_with_annotations_refuses_left_and_right_in_the_image_sense():
    """Names swapped left/right (the image's, not the subject's) fitted a head turned away from the
    camera at 144 deg of yaw, "converged" with sub-pixel landmark errors; now the pairs are named."""
    from facenormals.models import LANDMARK_NAMES, builtin_head_model

    head = builtin_head_model()
    bare = MorphableModel(head.mean, head.shape_basis, head.faces, shape_std=head.shape_std)
    swap = {"right_": "left_", "left_": "right_"}
    swapped = {}
    for name, index in head.landmarks.items():
        prefix = next((p for p in swap if name.startswith(p)), None)
        swapped[swap[prefix] + name[len(prefix):] if prefix else name] = index
    with pytest.raises(ValueError, match="right_eye_outer/left_eye_outer.* are mirrored"):
        bare.with_annotations({name: swapped[name] for name in LANDMARK_NAMES})
    one = dict(head.landmarks)
    one["right_mouth_corner"], one["left_mouth_corner"] = one["left_mouth_corner"], one["right_mouth_corner"]
    with pytest.raises(ValueError, match=r"landmarks: right_mouth_corner/left_mouth_corner are mirrored"):
        bare.with_annotations(one)
    assert bare.with_annotations(head.landmarks).landmarks == head.landmarks


def test_single_name_list_fields_of_a_model_file_are_a_model_file_error(tmp_path):
    """A 0-d landmark_names (one name saved as a scalar) raised a bare TypeError from iterating it."""
    tiny_model().save(tmp_path / "good.npz")
    arrays = dict(np.load(tmp_path / "good.npz"))
    for change in ({"landmark_names": np.array("nose_tip"), "landmark_indices": np.array(1)},
                   {"landmark_indices": np.array(1)},
                   {"expression_names": np.array("a")},
                   {"landmark_names": np.array([["nose_tip", "chin"]])}):
        key = next(iter(change))
        np.savez(tmp_path / "bad.npz", **{**arrays, **change})
        with pytest.raises(ModelFileError, match=rf"bad.npz: array '{key}' has shape \(.*\), expected a 1-D list"):
            MorphableModel.load(tmp_path / "bad.npz")


def test_buffers_are_built_on_the_device_of_the_mean(monkeypatch):
    """The default expression_basis, and a shape_std, faces or face_region given on the CPU, stayed on
    the CPU with a mean on another device. Without a GPU the meta device stands in; it holds no values,
    so only the value-reading checks are switched off (they run on the CPU arguments otherwise)."""
    import facenormals.models.morphable as morphable

    monkeypatch.setattr(morphable, "check_finite", lambda *args, **kwargs: None)
    monkeypatch.setattr(morphable, "outward_share", lambda *args, **kwargs: 1.0)
    full = tiny_model()
    meta = torch.device("meta")
    model = MorphableModel(full.mean.to(meta), full.shape_basis, full.faces, shape_std=full.shape_std,
                           face_region=full.face_region, landmarks=full.landmarks)
    assert {name: buffer.device for name, buffer in model.named_buffers()} == {
        name: meta for name, _ in full.named_buffers()}
    assert model.expression_basis.shape == (0, 5, 3) and model.faces.dtype == torch.long
    assert model.basis_matrix(with_expression=True).device == meta


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_cpu_arguments_follow_a_cuda_mean():
    full = tiny_model()
    cuda = torch.device("cuda")
    model = MorphableModel(full.mean.to(cuda), full.shape_basis, full.faces, shape_std=full.shape_std,
                           expression_basis=full.expression_basis, face_region=full.face_region)
    assert all(buffer.device.type == "cuda" for _, buffer in model.named_buffers())
    y = torch.randn(2, 3, generator=torch.Generator().manual_seed(1), dtype=torch.float64).to(cuda)
    assert_close(model(y).cpu(), full(y.cpu()))
    defaults = MorphableModel(full.mean.to(cuda), full.shape_basis.to(cuda), full.faces.to(cuda))
    assert all(buffer.device.type == "cuda" for _, buffer in defaults.named_buffers())


def test_forward_refuses_non_finite_coefficients():
    """NaN or inf coefficients gave all-NaN vertices without an error."""
    model = tiny_model()
    y, e = torch.zeros(2, 3, dtype=torch.float64), torch.zeros(2, 2, dtype=torch.float64)
    for bad in (float("nan"), float("inf")):
        with pytest.raises(ValueError, match="shape_coeffs: expected finite values, got 1 NaN or infinite"):
            model(y.index_fill(1, torch.tensor([1]), bad)[:1])
        with pytest.raises(ValueError, match="shape_coeffs: expected finite values"):
            model(y.index_fill(1, torch.tensor([1]), bad), e)
        with pytest.raises(ValueError, match="expression_coeffs: expected finite values"):
            model(y, e.index_fill(1, torch.tensor([0]), bad))


def test_a_model_without_shape_components_evaluates_and_round_trips(tmp_path):
    """K = 0 (a rigid template) is accepted by the constructor, save and load; forward and
    basis_matrix reshaped with -1, which is ambiguous for an empty basis."""
    full = tiny_model()
    model = MorphableModel(full.mean, full.shape_basis[:0], full.faces, shape_std=full.shape_std[:0])
    assert torch.equal(model(torch.zeros(2, 0, dtype=torch.float64)), full.mean.expand(2, 5, 3))
    assert model.basis_matrix().shape == (15, 0) and model.sample_shape_coeffs(3).shape == (3, 0)
    model.save(tmp_path / "k0.npz")
    assert MorphableModel.load(tmp_path / "k0.npz").num_shape == 0


def test_export_names_coefficients_that_are_no_tensor(tmp_path):
    """A list raised AttributeError: 'list' object has no attribute 'shape'."""
    with pytest.raises(ValueError, match="shape_coeffs: expected a torch.Tensor, got list"):
        tiny_model().export_mesh(tmp_path / "head.ply", [0.0, 0.0, 0.0])


def test_sampling_names_a_generator_that_is_no_generator():
    """A string raised a TypeError from deep inside torch.randn."""
    model = tiny_model()
    with pytest.raises(ValueError, match="generator: expected a torch.Generator or None, got str"):
        model.sample_shape_coeffs(2, generator="x")
    generator = torch.Generator().manual_seed(3)
    assert model.sample_shape_coeffs(2, generator=generator).shape == (2, 3)


def test_an_edited_cached_result_is_rebuilt():
    """basis_matrix() and mean_normals() return their cached tensor: a caller's J.zero_() made every
    later call return zeros."""
    model = tiny_model()
    J, normals = model.basis_matrix(), model.mean_normals()
    expected_J, expected_normals = J.clone(), normals.clone()
    assert model.basis_matrix() is J  # no copy while untouched
    J.zero_()
    normals[0].zero_()  # through a view too
    assert torch.equal(model.basis_matrix(), expected_J) and torch.equal(model.mean_normals(), expected_normals)
    assert model.basis_matrix() is model.basis_matrix()


def test_landmark_faces_give_the_exact_normals_at_the_landmarks_of_any_shape():
    from facenormals.mesh import vertex_normals
    from facenormals.models import builtin_head_model

    model = builtin_head_model(dtype=torch.float64)
    shapes = model(model.sample_shape_coeffs(3, generator=torch.Generator().manual_seed(4)))
    faces = model.landmark_faces()
    index = model.landmark_indices
    assert faces.shape[0] < model.faces.shape[0] // 50
    assert all(bool((faces == i).any()) for i in index.tolist())
    torch.testing.assert_close(vertex_normals(shapes, faces)[:, index], vertex_normals(shapes, model.faces)[:, index])
    assert model.landmark_faces() is faces  # cached
    model.landmark_indices = index.flip(0).clone()  # a new buffer rebuilds it
    assert model.landmark_faces() is not faces
