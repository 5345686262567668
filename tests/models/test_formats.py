"""Loaders for user-supplied morphable models: each test writes a tiny file of the exact layout."""

from __future__ import annotations

import pickle
import re
import sys
import types
import warnings
from pathlib import Path

import numpy as np
import pytest
import scipy.io
import scipy.sparse
import torch
import trimesh

from facenormals.models.formats import load_bfm2009, load_bfm2017, load_flame, load_lyhm
from facenormals.models.morphable import ModelFileError, MorphableModel
from tests.conftest import assert_close

try:
    import h5py
except ImportError:  # h5py is optional: only BFM 2017 and MATLAB v7.3 files need it
    h5py = None
needs_h5py = pytest.mark.skipif(h5py is None, reason="h5py is not installed")

NUM_COMPONENTS = 4


# --------------------------------------------------------------------------------------------------
# A tiny closed head: an icosphere in an OpenGL-style frame (+y up, +z out of the face), in mm
# --------------------------------------------------------------------------------------------------

SPHERE = trimesh.creation.icosphere(subdivisions=1, radius=50.0)
GL_VERTICES_MM = np.asarray(SPHERE.vertices) + np.array([3.0, 20.0, -7.0])  # off-centre: flips show
CCW_FACES = np.asarray(SPHERE.faces, dtype=np.int64)  # counter-clockwise seen from outside
NUM_VERTICES = GL_VERTICES_MM.shape[0]
TO_MODEL = np.array([1.0, -1.0, -1.0])  # (x, y, z) -> (x, -y, -z)


def orthonormal_basis(seed: int = 0, k: int = NUM_COMPONENTS) -> np.ndarray:
    """``(3N, k)`` orthonormal columns, interleaved x, y, z per vertex."""
    q, _ = np.linalg.qr(np.random.default_rng(seed).standard_normal((3 * NUM_VERTICES, k)))
    return q


BASIS = orthonormal_basis()
STD_MM = np.array([6.0, 4.0, 2.5, 1.0])


def expected_mean() -> np.ndarray:
    return GL_VERTICES_MM * TO_MODEL


def expected_component(basis: np.ndarray, k: int) -> np.ndarray:
    return basis[:, k].reshape(NUM_VERTICES, 3) * TO_MODEL


def check_model(model: MorphableModel, std_mm: np.ndarray, basis: np.ndarray = BASIS) -> None:
    """Geometry in mm in the model frame, outward winding, unit-norm components, exact semantics."""
    assert isinstance(model, MorphableModel)
    assert model.mean.dtype == torch.float32
    # a known vertex: source (x, y, z) mm -> (x, -y, -z)
    x, y, z = GL_VERTICES_MM[5]
    assert_close(model.mean[5], torch.tensor([x, -y, -z]))
    assert_close(model.mean, expected_mean())
    # counter-clockwise seen from outside: positive volume of the closed mesh
    mesh = trimesh.Trimesh(model.mean.double().numpy(), model.faces.numpy(), process=False)
    assert mesh.is_watertight and mesh.volume > 0
    assert_close(model.shape_std, std_mm)
    assert_close(model.shape_basis.reshape(model.num_shape, -1).norm(dim=1), torch.ones(model.num_shape))
    # X = mean + sum_k y_k W_k with y_k ~ N(0, std_k^2): two standard deviations along component 1
    y = torch.zeros(1, model.num_shape)
    y[0, 1] = 2.0 * model.shape_std[1]
    expected = expected_mean() + 2.0 * std_mm[1] * expected_component(basis, 1)
    assert_close(model(y)[0], expected, atol=1e-4, rtol=1e-5)


def reversed_one_based(faces: np.ndarray) -> np.ndarray:
    """Triangles wound clockwise seen from outside, 1-based, as float (as MATLAB stores them)."""
    return (faces[:, [0, 2, 1]] + 1).astype(np.float64)


def truncated_copy(path: Path, fraction: float = 0.6) -> Path:
    data = path.read_bytes()
    out = path.with_name("truncated_" + path.name)
    out.write_bytes(data[: int(len(data) * fraction)])
    return out


def assert_no_warnings(fn, *args, **kwargs):
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        return fn(*args, **kwargs)


# --------------------------------------------------------------------------------------------------
# LYHM
# --------------------------------------------------------------------------------------------------


def write_lyhm(path: Path, *, mu_as_row: bool = True, drop: str | None = None, **overrides) -> Path:
    mu = GL_VERTICES_MM.reshape(-1)
    shp = {
        "mu": mu[None, :] if mu_as_row else mu[:, None],
        "eigVec": BASIS,
        "eigVal": (STD_MM**2)[:, None],
    }
    tri = {"faces": reversed_one_based(CCW_FACES)}
    shp.update({k: v for k, v in overrides.items() if k in shp})
    if "faces" in overrides:
        tri["faces"] = overrides["faces"]
    if drop in shp:
        del shp[drop]
    variables = {"shp": shp, "tri": tri}
    if drop == "tri":
        del variables["tri"]
    scipy.io.savemat(path, variables)
    return path


def write_mat73(path: Path, variables: dict) -> Path:
    """A MATLAB v7.3-style file: HDF5 behind a 512-byte header, arrays stored transposed."""
    with h5py.File(path, "w", userblock_size=512) as handle:

        def put(group, name, value):
            if isinstance(value, dict):
                sub = group.create_group(name)
                for key, item in value.items():
                    put(sub, key, item)
            else:
                group.create_dataset(name, data=np.asarray(value).T)

        for name, value in variables.items():
            put(handle, name, value)
    with open(path, "r+b") as handle:
        handle.write(b"MATLAB 7.3 MAT-file, Platform: GLNXA64, Created on: test HDF5 schema 1.00 .".ljust(128))
    return path


@pytest.mark.parametrize("mu_as_row", [True, False], ids=["mu-row", "mu-column"])
def test_lyhm(tmp_path, mu_as_row):
    path = write_lyhm(tmp_path / "LYHM_global.mat", mu_as_row=mu_as_row)
    model = assert_no_warnings(load_lyhm, path)
    check_model(model, STD_MM)
    assert model.name == "lyhm" and model.num_shape == NUM_COMPONENTS and model.num_expressions == 0
    assert model.metadata["format"] == "lyhm-mat" and "license" in model.metadata
    assert model.metadata["file"] == str(path)


@needs_h5py
def test_lyhm_v73(tmp_path):
    mu = GL_VERTICES_MM.reshape(1, -1)
    variables = {
        "shp": {"mu": mu, "eigVec": BASIS, "eigVal": (STD_MM**2)[:, None]},
        "tri": {"faces": reversed_one_based(CCW_FACES)},
    }
    path = write_mat73(tmp_path / "LYHM_v73.mat", variables)
    check_model(load_lyhm(path), STD_MM)


def test_lyhm_tri_inside_shp_and_truncation(tmp_path):
    shp = {"mu": GL_VERTICES_MM.reshape(1, -1), "eigVec": BASIS, "eigVal": STD_MM**2,
           "tri": {"faces": reversed_one_based(CCW_FACES)}}
    path = tmp_path / "lyhm_nested.mat"
    scipy.io.savemat(path, {"shp": shp})
    model = load_lyhm(path, num_shape=2, dtype=torch.float64)
    assert model.num_shape == 2 and model.mean.dtype == torch.float64
    assert_close(model.shape_std, STD_MM[:2])
    assert_close(model.shape_basis[1], expected_component(BASIS, 1))


def test_lyhm_errors(tmp_path):
    good = write_lyhm(tmp_path / "good.mat")
    with pytest.raises(ModelFileError, match="truncated_good.mat"):
        load_lyhm(truncated_copy(good))
    with pytest.raises(ModelFileError, match=r"missing_eigvec\.mat.*shp\.eigVec"):
        load_lyhm(write_lyhm(tmp_path / "missing_eigvec.mat", drop="eigVec"))
    with pytest.raises(ModelFileError, match=r"no_tri\.mat.*tri"):
        load_lyhm(write_lyhm(tmp_path / "no_tri.mat", drop="tri"))
    with pytest.raises(ModelFileError, match=r"nowhere\.mat.*not found"):
        load_lyhm(tmp_path / "nowhere.mat")
    with pytest.raises(ModelFileError, match=r"wrong_basis\.mat.*shp\.eigVec has shape"):
        load_lyhm(write_lyhm(tmp_path / "wrong_basis.mat", eigVec=BASIS[:-3]))
    with pytest.raises(ModelFileError, match=r"wrong_val\.mat.*shp\.eigVal has 3 entries"):
        load_lyhm(write_lyhm(tmp_path / "wrong_val.mat", eigVal=STD_MM[:3]))
    bad_mu = GL_VERTICES_MM.reshape(-1)[:-1]
    with pytest.raises(ModelFileError, match=r"bad_mu\.mat.*shp\.mu has 125 entries, expected 3N"):
        load_lyhm(write_lyhm(tmp_path / "bad_mu.mat", mu=bad_mu[None, :]))
    # the coordinates axis by axis, (3, N): read as interleaved they were other vertices, silently
    with pytest.raises(ModelFileError, match=r"by_axis\.mat: shp\.mu has shape \(3, 42\).*transpose it"):
        check_model(load_lyhm(write_lyhm(tmp_path / "by_axis.mat", mu=GL_VERTICES_MM.T)), STD_MM)
    check_model(assert_no_warnings(load_lyhm, write_lyhm(tmp_path / "by_vertex.mat", mu=GL_VERTICES_MM)), STD_MM)
    zero_based = (CCW_FACES[:, [0, 2, 1]]).astype(np.float64)
    with pytest.raises(ModelFileError, match=r"zero_based\.mat.*1-based"):
        load_lyhm(write_lyhm(tmp_path / "zero_based.mat", faces=zero_based))
    with pytest.raises(ModelFileError, match=r"out_of_range\.mat.*outside"):
        load_lyhm(write_lyhm(tmp_path / "out_of_range.mat", faces=reversed_one_based(CCW_FACES) + 5))
    with pytest.raises(ModelFileError, match=r"negative\.mat.*shp\.eigVal\[3\].*num_shape=3"):
        load_lyhm(write_lyhm(tmp_path / "negative.mat", eigVal=np.array([36.0, 16.0, 6.25, -1e-9])))
    # ... which passing num_shape works around
    assert load_lyhm(tmp_path / "negative.mat", num_shape=3).num_shape == 3
    with pytest.raises(ValueError, match="num_shape"):
        load_lyhm(good, num_shape=NUM_COMPONENTS + 1)
    not_mat = tmp_path / "text.mat"
    not_mat.write_text("this is not a MATLAB file\n" * 10)
    with pytest.raises(ModelFileError, match="text.mat"):
        load_lyhm(not_mat)


# --------------------------------------------------------------------------------------------------
# BFM 2009
# --------------------------------------------------------------------------------------------------


def write_bfm2009(path: Path, *, drop: str | None = None, compress: bool = False, **overrides) -> Path:
    variables = {
        "shapeMU": (GL_VERTICES_MM * 1000.0).reshape(-1, 1).astype(np.float32),  # micrometres
        "shapePC": BASIS.astype(np.float32),
        "shapeEV": (STD_MM * 1000.0)[:, None].astype(np.float32),  # standard deviations, um
        "tl": reversed_one_based(CCW_FACES),
        "texMU": np.full((3 * NUM_VERTICES, 1), 128.0, dtype=np.float32),
    }
    variables.update(overrides)
    if drop:
        del variables[drop]
    scipy.io.savemat(path, variables, do_compression=compress)
    return path


def test_bfm2009(tmp_path):
    path = write_bfm2009(tmp_path / "01_MorphableModel.mat")
    model = assert_no_warnings(load_bfm2009, path)
    check_model(model, STD_MM)
    assert model.name == "bfm2009" and model.metadata["format"] == "bfm2009-mat"
    # BFM's coef2object: shapeMU + shapePC * (alpha .* shapeEV), alpha in standard deviations
    alpha = np.array([0.5, -1.0, 2.0, 0.25])
    bfm = (GL_VERTICES_MM * 1000.0).reshape(-1) + BASIS @ (alpha * STD_MM * 1000.0)
    ours = model(torch.as_tensor(alpha, dtype=torch.float32)[None] * model.shape_std)[0]
    assert_close(ours, bfm.reshape(-1, 3) / 1000.0 * TO_MODEL, atol=1e-3, rtol=1e-5)


@needs_h5py
def test_bfm2009_truncation_and_v73(tmp_path):
    model = load_bfm2009(write_bfm2009(tmp_path / "bfm.mat"), num_shape=3)
    assert model.num_shape == 3
    assert_close(model.shape_std, STD_MM[:3])
    v73 = write_mat73(tmp_path / "bfm_v73.mat", {
        "shapeMU": (GL_VERTICES_MM * 1000.0).reshape(-1, 1),
        "shapePC": BASIS,
        "shapeEV": (STD_MM * 1000.0)[:, None],
        "tl": reversed_one_based(CCW_FACES),
    })
    check_model(load_bfm2009(v73), STD_MM)
    from facenormals.models import load_model

    check_model(load_model(v73), STD_MM)  # a v7.3 BFM file is not sent to the LYHM loader


@pytest.mark.parametrize("compress", [False, True], ids=["plain", "compressed"])
def test_bfm2009_errors(tmp_path, compress):
    good = write_bfm2009(tmp_path / "good.mat", compress=compress)
    for fraction in (0.05, 0.3, 0.6):
        with pytest.raises(ModelFileError, match="truncated_good.mat"):
            load_bfm2009(truncated_copy(good, fraction))
    if not compress:  # only the shape variables are read: a file cut in the texture (last) still loads
        assert load_bfm2009(truncated_copy(good, 0.97)).num_shape == NUM_COMPONENTS
    with pytest.raises(ModelFileError, match=r"no_ev\.mat.*shapeEV"):
        load_bfm2009(write_bfm2009(tmp_path / "no_ev.mat", drop="shapeEV", compress=compress))
    with pytest.raises(ModelFileError, match=r"absent\.mat"):
        load_bfm2009(tmp_path / "absent.mat")
    with pytest.raises(ModelFileError, match=r"nan\.mat.*NaN"):
        pcs = BASIS.astype(np.float32).copy()
        pcs[0, 0] = np.nan
        load_bfm2009(write_bfm2009(tmp_path / "nan.mat", shapePC=pcs))
    with pytest.raises(ModelFileError, match=r"bad_tl\.mat.*tl has shape"):
        load_bfm2009(write_bfm2009(tmp_path / "bad_tl.mat", tl=np.ones((5, 4))))


# --------------------------------------------------------------------------------------------------
# BFM 2017 (statismo .h5)
# --------------------------------------------------------------------------------------------------

EXPR_BASIS = orthonormal_basis(seed=1, k=3)
EXPR_STD_MM = np.array([3.0, 2.0, 0.5])
EXPR_MEAN_MM = 0.1 * np.random.default_rng(2).standard_normal(3 * NUM_VERTICES)


def write_bfm2017(path: Path, *, expressions: bool = True, drop: str | None = None, **overrides) -> Path:
    datasets = {
        "shape/model/mean": GL_VERTICES_MM.reshape(-1).astype(np.float32),
        "shape/model/pcaBasis": BASIS.astype(np.float32),
        "shape/model/pcaVariance": (STD_MM**2).astype(np.float32),
        "shape/model/noiseVariance": np.float32(1e-4),
        "shape/representer/cells": CCW_FACES.T.astype(np.uint32),  # (3, F), 0-based
        "shape/representer/points": GL_VERTICES_MM.T.astype(np.float32),  # (3, N)
    }
    if expressions:
        datasets.update({
            "expression/model/mean": EXPR_MEAN_MM.astype(np.float32),
            "expression/model/pcaBasis": EXPR_BASIS.astype(np.float32),
            "expression/model/pcaVariance": (EXPR_STD_MM**2).astype(np.float32),
        })
    datasets.update(overrides)
    if drop:
        del datasets[drop]
    with h5py.File(path, "w") as handle:
        for key, value in datasets.items():
            handle.create_dataset(key, data=value)
    return path


@needs_h5py
def test_bfm2017_shape_only(tmp_path):
    path = write_bfm2017(tmp_path / "model2017-1_bfm_nomouth.h5", expressions=False)
    model = assert_no_warnings(load_bfm2017, path)
    check_model(model, STD_MM)
    assert model.num_expressions == 0 and model.metadata["format"] == "bfm-statismo-h5"
    assert model.metadata["expression_mean_in_mean"] is False


@needs_h5py
def test_a_plain_statismo_model_is_named_as_such_not_as_a_damaged_bfm_file(tmp_path):
    """Regression: scalismo's layout (model/ and representer/ at the top) was warned about as "unknown
    top-level groups ... is the file damaged?" and refused as "missing datasets"."""
    import warnings

    path = tmp_path / "femur.h5"
    with h5py.File(path, "w") as handle:
        handle["model/mean"] = GL_VERTICES_MM.reshape(-1).astype(np.float32)
        handle["model/pcaBasis"] = BASIS.astype(np.float32)
        handle["model/pcaVariance"] = (STD_MM**2).astype(np.float32)
        handle["representer/cells"] = CCW_FACES.T.astype(np.uint32)
        handle.create_group("modelinfo")
        handle["version/majorVersion"] = 0
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(ModelFileError, match=re.escape(f"{path}: a plain statismo shape model (top-level 'model' "
                                                           "and 'representer', as scalismo writes), not a BFM file")):
            load_bfm2017(path)


@needs_h5py
def test_bfm2017_expressions(tmp_path):
    path = write_bfm2017(tmp_path / "model2017-1_bfm_nomouth.h5")
    model = load_bfm2017(path)
    assert model.num_expressions == 3 and model.expression_names == ["expr_000", "expr_001", "expr_002"]
    # as in scalismo-faces: the mean includes the expression model's mean deformation
    mean = (GL_VERTICES_MM.reshape(-1) + EXPR_MEAN_MM).reshape(-1, 3) * TO_MODEL
    assert_close(model.mean, mean)
    # expression coefficients are standard normal: e_j = 1 moves by one standard deviation
    e = torch.tensor([[0.0, 1.0, 0.0]])
    y = torch.zeros(1, model.num_shape)
    assert_close(model(y, e)[0], mean + EXPR_STD_MM[1] * expected_component(EXPR_BASIS, 1), atol=1e-4, rtol=1e-5)
    assert_close(model.shape_std, STD_MM)
    neutral = load_bfm2017(path, expressions=False, num_shape=2)
    assert neutral.num_expressions == 0 and neutral.num_shape == 2
    assert_close(neutral.mean, expected_mean())
    assert load_bfm2017(path, num_expression=1).num_expressions == 1


@needs_h5py
def test_bfm2017_errors(tmp_path):
    good = write_bfm2017(tmp_path / "good.h5")
    with pytest.raises(ModelFileError, match="truncated_good.h5"):
        load_bfm2017(truncated_copy(good))
    with pytest.raises(ModelFileError, match=r"no_cells\.h5.*shape/representer/cells"):
        load_bfm2017(write_bfm2017(tmp_path / "no_cells.h5", drop="shape/representer/cells"))
    with pytest.raises(ModelFileError, match=r"missing\.h5.*not found"):
        load_bfm2017(tmp_path / "missing.h5")
    with pytest.raises(ModelFileError, match=r"cells_ft\.h5.*expected \(3, F\)"):
        load_bfm2017(write_bfm2017(tmp_path / "cells_ft.h5", **{"shape/representer/cells": CCW_FACES}))
    with pytest.raises(ModelFileError, match=r"points\.h5.*representer/points"):
        load_bfm2017(write_bfm2017(tmp_path / "points.h5", **{"shape/representer/points": GL_VERTICES_MM}))
    with pytest.raises(ModelFileError, match=r"expr\.h5.*expression/model/pcaVariance"):
        load_bfm2017(write_bfm2017(tmp_path / "expr.h5", drop="expression/model/pcaVariance"))
    # the shape model alone still loads from a file with a broken expression model
    assert load_bfm2017(tmp_path / "expr.h5", expressions=False).num_expressions == 0
    with pytest.raises(ModelFileError, match=r"not_h5\.h5"):
        (tmp_path / "not_h5.h5").write_bytes(b"\x00" * 100)
        load_bfm2017(tmp_path / "not_h5.h5")


@needs_h5py
def test_reversed_winding_is_turned_outward_with_a_warning(tmp_path):
    """A file wound against its format's convention (e.g. BFM triangles re-saved the other way) loads
    with outward triangles and a warning naming it; it used to load inside-out, and the fit then
    silently returned the mean head."""
    path = write_bfm2017(tmp_path / "flipped.h5", **{"shape/representer/cells": CCW_FACES[:, [0, 2, 1]].T})
    with pytest.warns(UserWarning, match=r"flipped\.h5: the triangles are wound the other way.*reversed them"):
        model = load_bfm2017(path)
    assert torch.equal(model.faces, load_bfm2017(write_bfm2017(tmp_path / "right.h5")).faces)


@needs_h5py
def test_num_expression_without_an_expression_model_is_refused(tmp_path):
    """It was ignored silently (load_flame refuses it)."""
    path = write_bfm2017(tmp_path / "bfm.h5", expressions=False)
    with pytest.raises(ValueError, match=r"num_expression: expected None \(the file has no expression model\), got 5"):
        load_bfm2017(path, num_expression=5)
    with pytest.raises(ValueError, match=r"num_expression: expected None \(expressions=False\), got 5"):
        load_bfm2017(write_bfm2017(tmp_path / "full.h5"), expressions=False, num_expression=5)


@needs_h5py
def test_a_damaged_hdf5_structure_names_the_file(tmp_path):
    """Regression: h5py raises RuntimeError (not OSError) for some damaged files, e.g. a local heap (the
    link names of a group) whose data segment lies past the end of the file; it escaped as a bare
    traceback from load_bfm2017 and load_model."""
    import struct

    from facenormals.models import load_model

    path = write_bfm2017(tmp_path / "damaged.h5")
    data = bytearray(path.read_bytes())
    heap = data.index(b"HEAP")  # the root group's local heap: signature, version, 3 reserved, size, free list
    struct.pack_into("<Q", data, heap + 24, 1 << 40)  # its data segment's address
    path.write_bytes(bytes(data))
    for load in (load_bfm2017, load_model):
        with pytest.raises(ModelFileError, match=r"damaged\.h5: cannot read BFM \.h5 file \(RuntimeError: "):
            load(path)


@needs_h5py
def test_a_damaged_group_name_in_a_bfm2017_file_is_refused(tmp_path):
    """Regression: a damaged byte turned the group name 'expression' into b'expressio\\x91'; the model
    loaded with no expressions and another mean (the expression mean was not added), without a word."""
    from facenormals.models import load_model

    for name, damaged, match in (
        ("bad.h5", b"expressio\x91", r"bad\.h5: damaged BFM \.h5 file: the top-level group name b'expressio\\x91' is "
                                     r"not printable text \(a statismo BFM file holds shape, expression, color"),
        ("renamed.h5", b"expressioo", r"renamed\.h5: damaged BFM \.h5 file\? it holds a model named 'expressioo' and "
                                      r"none named 'expression'"),
    ):
        path = write_bfm2017(tmp_path / name)
        data = path.read_bytes()
        assert data.count(b"expression") == 1  # the root group's link name
        path.write_bytes(data.replace(b"expression", damaged))
        for load in (load_bfm2017, load_model):
            with pytest.raises(ModelFileError, match=match):
                load(path)
    # the groups of genuine files load quietly; an unknown one is named in a warning
    path = write_bfm2017(tmp_path / "extra.h5")
    with h5py.File(path, "a") as handle:
        for group in ("catalog/shape", "metadata/parameters", "version", "color/model"):
            handle.create_group(group)
        handle["color/model"].create_dataset("mean", data=np.zeros(3 * NUM_VERTICES, np.float32))
    assert assert_no_warnings(load_bfm2017, path).num_expressions == 3
    with h5py.File(path, "a") as handle:
        handle.create_group("notes")
    with pytest.warns(UserWarning, match=r"extra\.h5: ignored the unknown top-level groups \['notes'\]"):
        assert load_bfm2017(path).num_expressions == 3


@needs_h5py
def test_non_unit_components_warn(tmp_path):
    path = write_bfm2017(tmp_path / "scaled.h5", **{"shape/model/pcaBasis": (BASIS * STD_MM).astype(np.float32)})
    with pytest.warns(UserWarning, match=r"scaled\.h5.*unit-norm"):
        load_bfm2017(path)


# --------------------------------------------------------------------------------------------------
# FLAME (a pickle with chumpy objects, loaded without chumpy)
# --------------------------------------------------------------------------------------------------

FLAME_SHAPE, FLAME_EXPR = 300, 100
_rng = np.random.default_rng(3)
# shapedirs in metres, already scaled by the standard deviations (FLAME's convention)
SHAPEDIRS_M = 1e-3 * _rng.standard_normal((NUM_VERTICES, 3, FLAME_SHAPE + FLAME_EXPR)) / np.sqrt(
    1.0 + np.arange(FLAME_SHAPE + FLAME_EXPR)
)


class _FakeCh:
    """Pickles like chumpy's ``Ch``: its state is ``__dict__`` less the caches, ``x`` the array."""

    def __init__(self, x):
        self.x = np.asarray(x, dtype=np.float64)
        self._dirty_vars = set()
        self._itr = None
        self._depends_on_deps = {}
        self._make_dense = False
        self._make_sparse = False
        self._parents = object()  # dropped by __getstate__, like chumpy's WeakKeyDictionary

    def __getstate__(self):
        state = dict(self.__dict__)
        del state["_parents"]
        return state


def write_flame(path: Path, *, protocol: int = 2, old_numpy_names: bool = False, drop: str | None = None,
                **overrides) -> Path:
    """Write a FLAME-like pickle with ``Ch`` objects of a module named ``chumpy.ch``, then forget it."""
    chumpy = types.ModuleType("chumpy")
    chumpy_ch = types.ModuleType("chumpy.ch")
    ch_class = type("Ch", (_FakeCh,), {"__module__": "chumpy.ch"})
    chumpy_ch.Ch = ch_class
    chumpy.ch = chumpy_ch
    sys.modules["chumpy"], sys.modules["chumpy.ch"] = chumpy, chumpy_ch
    try:
        data = {
            "v_template": ch_class(GL_VERTICES_MM / 1000.0),  # metres
            "shapedirs": ch_class(SHAPEDIRS_M),
            "f": CCW_FACES.astype(np.uint32),
            "posedirs": ch_class(np.zeros((NUM_VERTICES, 3, 36))),
            "J_regressor": scipy.sparse.csc_matrix(np.full((5, NUM_VERTICES), 1.0 / NUM_VERTICES)),
            "kintree_table": np.array([[4294967295, 0, 1, 1, 1], [0, 1, 2, 3, 4]], dtype=np.int64),
            "weights": ch_class(np.full((NUM_VERTICES, 5), 0.2)),
            "bs_style": "lbs",
            "bs_type": "lrotmin",
        }
        data.update(overrides)
        if drop:
            del data[drop]
        blob = pickle.dumps(data, protocol=protocol)
    finally:
        del sys.modules["chumpy"], sys.modules["chumpy.ch"]
    if old_numpy_names:  # as written by NumPy 1.x (and Python 2): numpy.core instead of numpy._core
        assert protocol <= 2
        blob = blob.replace(b"cnumpy._core.multiarray\n", b"cnumpy.core.multiarray\n")
        assert b"cnumpy.core.multiarray\n" in blob
    path.write_bytes(blob)
    return path


@pytest.mark.parametrize(
    "protocol,old_names", [(2, False), (2, True), (0, True), (4, False), (5, False)],
    ids=["p2", "p2-numpy1", "p0-numpy1", "p4", "p5"],
)
def test_flame(tmp_path, protocol, old_names):
    path = write_flame(tmp_path / "generic_model.pkl", protocol=protocol, old_numpy_names=old_names)
    assert "chumpy" not in sys.modules
    model = assert_no_warnings(load_flame, path)
    assert "chumpy" not in sys.modules and "chumpy.ch" not in sys.modules
    assert model.name == "flame" and model.metadata["format"] == "flame-pkl"
    assert model.num_shape == FLAME_SHAPE and model.num_expressions == FLAME_EXPR
    assert model.expression_names[0] == "expr_000" and model.expression_names[-1] == "expr_099"
    assert_close(model.mean, expected_mean())
    x, y, z = GL_VERTICES_MM[7]
    assert_close(model.mean[7], torch.tensor([x, -y, -z]))
    mesh = trimesh.Trimesh(model.mean.double().numpy(), model.faces.numpy(), process=False)
    assert mesh.volume > 0
    # FLAME's components are scaled by their standard deviations: shape_std = 1, betas used as-is
    assert_close(model.shape_std, torch.ones(FLAME_SHAPE))
    betas = torch.zeros(1, FLAME_SHAPE)
    betas[0, 10] = 1.5
    psi = torch.zeros(1, FLAME_EXPR)
    psi[0, 4] = -2.0
    expected = (GL_VERTICES_MM + 1000.0 * (1.5 * SHAPEDIRS_M[:, :, 10] - 2.0 * SHAPEDIRS_M[:, :, 304])) * TO_MODEL
    assert_close(model(betas, psi)[0], expected, atol=1e-4, rtol=1e-5)


def test_flame_truncation_and_dtype(tmp_path):
    path = write_flame(tmp_path / "flame2020.pkl")
    model = load_flame(path, num_shape=50, num_expression=10, dtype=torch.float64)
    assert model.num_shape == 50 and model.num_expressions == 10 and model.mean.dtype == torch.float64
    assert_close(model.shape_basis[3], 1000.0 * SHAPEDIRS_M[:, :, 3] * TO_MODEL)
    assert_close(model.expression_basis[9], 1000.0 * SHAPEDIRS_M[:, :, 309] * TO_MODEL)
    no_expr = load_flame(write_flame(tmp_path / "shape_only.pkl", shapedirs=SHAPEDIRS_M[:, :, :300]))
    assert no_expr.num_expressions == 0
    with pytest.raises(ValueError, match="num_shape"):
        load_flame(path, num_shape=301)


def test_flame_errors(tmp_path):
    good = write_flame(tmp_path / "good.pkl")
    for fraction in (0.1, 0.5, 0.9):
        with pytest.raises(ModelFileError, match="truncated_good.pkl"):
            load_flame(truncated_copy(good, fraction))
    with pytest.raises(ModelFileError, match=r"no_f\.pkl.*\['f'\]"):
        load_flame(write_flame(tmp_path / "no_f.pkl", drop="f"))
    with pytest.raises(ModelFileError, match=r"ghost\.pkl.*not found"):
        load_flame(tmp_path / "ghost.pkl")
    with pytest.raises(ModelFileError, match=r"few\.pkl.*shapedirs has 20 components"):
        load_flame(write_flame(tmp_path / "few.pkl", shapedirs=SHAPEDIRS_M[:, :, :20]))
    with pytest.raises(ModelFileError, match=r"verts\.pkl.*shapedirs has shape"):
        load_flame(write_flame(tmp_path / "verts.pkl", shapedirs=SHAPEDIRS_M[:-1]))
    with pytest.raises(ModelFileError, match=r"faces\.pkl.*outside"):
        load_flame(write_flame(tmp_path / "faces.pkl", f=CCW_FACES + NUM_VERTICES))
    list_pickle = tmp_path / "list.pkl"
    list_pickle.write_bytes(pickle.dumps([1, 2, 3]))
    with pytest.raises(ModelFileError, match=r"list\.pkl.*expected a FLAME dict"):
        load_flame(list_pickle)


def test_flame_pickle_runs_no_code(tmp_path):
    """Globals other than numpy's are never resolved: a pickle calling os.system loads inertly."""

    class Evil:
        def __reduce__(self):
            import os

            return (os.system, ("echo should-not-run > " + str(tmp_path / "ran.txt"),))

    path = write_flame(tmp_path / "evil.pkl", extra=Evil())
    load_flame(path)
    assert not (tmp_path / "ran.txt").exists()


def test_load_model_dispatches_by_format(tmp_path):
    """Bring your own model in one call: ``load_model(path)`` picks the loader."""
    from facenormals.models import builtin_head_model, load_model

    expected = {
        write_lyhm(tmp_path / "lyhm.mat"): "lyhm",
        write_bfm2009(tmp_path / "01_MorphableModel.mat"): "bfm2009",
        write_flame(tmp_path / "generic_model.pkl"): "flame",
    }
    if h5py is not None:
        expected[write_bfm2017(tmp_path / "model2017.h5")] = "bfm2017"
    saved = tmp_path / "mine.npz"
    builtin_head_model().save(saved)
    expected[saved] = "builtin"
    for path, name in expected.items():
        assert load_model(str(path)).name == name, path
    with pytest.raises(ModelFileError, match=r"unknown model format '\.xyz'"):
        (tmp_path / "m.xyz").write_text("x")
        load_model(str(tmp_path / "m.xyz"))


# --------------------------------------------------------------------------------------------------
# Damaged files: a clear error naming the file, never a crash or a silent wrong model
# --------------------------------------------------------------------------------------------------


def _tag(mdtype: int, count: int) -> bytes:
    """A MATLAB v5 element tag (little-endian, as savemat writes on this machine)."""
    import struct

    return struct.pack("<II", mdtype, count)


def _replace_first(data: bytes, old: bytes, new: bytes) -> bytes:
    assert old in data, f"{old!r} not found"
    return data.replace(old, new, 1)


def _damage_first_compressed_variable(path: Path, change) -> None:
    """Apply ``change`` to the decompressed content of ``path``'s first (miCOMPRESSED) variable and
    compress it again: a file whose damage sits inside its deflated data."""
    import struct
    import zlib

    data = path.read_bytes()
    mdtype, count = struct.unpack_from("<II", data, 128)
    assert mdtype == 15, "not a compressed variable"
    inner = zlib.compress(change(zlib.decompress(data[136:136 + count])))
    path.write_bytes(data[:128] + _tag(15, len(inner)) + inner + data[136 + count:])


def _damaged_mat_files(tmp_path: Path) -> dict[Path, str]:
    """MATLAB v5 files scipy.io.loadmat crashed on (segmentation fault), made from valid ones, and the
    damage to expect in the error: an element type outside MATLAB's, a matrix where numbers belong, in
    plain and compressed variables and in a struct (as LYHM files have), and a cell array whose class
    byte says double (scipy then read its first cell, an array, as numbers)."""
    real_part = _tag(7, 4 * 3 * NUM_VERTICES)  # shapeMU's (the first variable's): float32, 3N values
    files = {}
    for name, mdtype in (("type248.mat", 248), ("matrix_type.mat", 14)):
        path = write_bfm2009(tmp_path / name)
        path.write_bytes(_replace_first(path.read_bytes(), real_part, _tag(mdtype, 4 * 3 * NUM_VERTICES)))
        files[path] = f"real part.*data type {mdtype}.*at byte 184"
    path = write_bfm2009(tmp_path / "compressed.mat", compress=True)
    _damage_first_compressed_variable(path, lambda raw: _replace_first(raw, real_part, _tag(248, 4 * 3 * NUM_VERTICES)))
    files[path] = "real part: unknown data type 248 .*of the decompressed variable at byte 128"
    path = write_lyhm(tmp_path / "struct.mat")  # shp.eigVal: 4 doubles
    path.write_bytes(_replace_first(path.read_bytes(), _tag(9, 32), _tag(8, 32)))
    files[path] = "real part: unknown data type 8"
    cell = np.empty(1, dtype=object)  # tri.faces in a cell, which the loader refuses, had scipy got that far
    cell[0] = reversed_one_based(CCW_FACES)
    path = write_lyhm(tmp_path / "cell.mat", faces=cell)
    flags = _tag(6, 8) + b"\x01\0\0\0"  # array flags: miUINT32, 8 bytes, class 1 (a cell)
    path.write_bytes(_replace_first(path.read_bytes(), flags, _tag(6, 8) + b"\x06\0\0\0"))  # class 6: double
    files[path] = "real part of data type 14, expected numbers"
    return files


def test_a_damaged_matlab_element_type_is_refused_before_scipy_reads_it(tmp_path):
    """Regression: scipy.io.loadmat crashed the whole process (segmentation fault, exit 139) on a MATLAB
    v5 file whose element type byte was damaged: load_model, load_bfm2009, load_lyhm and `facenormals
    models show FILE` died. The structure is now checked first; the loads run in a child process so
    that a crash fails this test instead of ending the test run."""
    import subprocess

    files = _damaged_mat_files(tmp_path)
    code = (
        "import sys\n"
        "from facenormals import cli\n"
        "from facenormals.models import load_model\n"
        "from facenormals.models.formats import load_bfm2009, load_lyhm\n"
        "for path in sys.argv[1:]:\n"
        "    for load in (load_model, load_bfm2009, load_lyhm):\n"
        "        try:\n"
        "            load(path)\n"
        "            print('LOADED', path)\n"
        "        except Exception as error:\n"
        "            print(type(error).__name__, str(error).replace(chr(10), ' '))\n"
        "    print('CLI exit', cli.main(['models', 'show', path]))\n"
    )
    result = subprocess.run([sys.executable, "-c", code, *map(str, files)], capture_output=True, text=True,
                            timeout=300)
    assert result.returncode == 0, f"exit {result.returncode}: {result.stderr[-2000:]}"
    lines = result.stdout.splitlines()
    for path, damage in files.items():
        errors = [line for line in lines if str(path) in line and not line.startswith("CLI")]
        assert len(errors) == 3 and all(line.startswith(f"ModelFileError {path}: ") for line in errors), lines
        damaged = [line for line in errors if re.match(rf"ModelFileError {re.escape(str(path))}: damaged MATLAB file: "
                                                     rf".*{damage}", line)]
        assert len(damaged) == 2, errors  # load_model and the format's loader; the other reads no damaged variable
    assert lines.count("CLI exit 1") == len(files), lines
    assert str(tmp_path / "type248.mat") in result.stderr  # what the command line printed


def test_valid_matlab_files_of_every_kind_pass_the_structure_check(tmp_path):
    """The check walks what savemat writes, plain and compressed: numbers of each type, complex,
    logical, text, cells, structs (nested and arrays of them), sparse and empty arrays."""
    from facenormals.models.mat5 import check_mat5

    struct_array = np.zeros((2,), dtype=[("a", object), ("b", object)])
    struct_array[0] = (np.arange(3.0), "x")
    struct_array[1] = (np.eye(2), np.array([], dtype=np.float64))
    variables = {
        "f8": np.arange(12.0).reshape(3, 4), "f4": np.ones(5, np.float32), "i1": np.arange(-3, 3, dtype=np.int8),
        "u2": np.arange(7, dtype=np.uint16), "i8": np.arange(3, dtype=np.int64), "u8": np.arange(3, dtype=np.uint64),
        "z": np.arange(4) + 1j, "logical": np.array([True, False]), "text": "héllo wörld", "texts": ["ab", "cd"],
        "empty": np.zeros((0, 3)), "scalar": 2.5,
        "cell": np.array([np.arange(2.0), "t", np.zeros((2, 2))], dtype=object),
        "nested": {"inner": {"deep": np.arange(4.0)}, "n": 1}, "records": struct_array,
        "sparse": scipy.sparse.csc_matrix(np.eye(4)), "zsparse": scipy.sparse.csc_matrix(np.eye(3) * 1j),
    }
    for compress in (False, True):
        path = tmp_path / f"kinds_{compress}.mat"
        scipy.io.savemat(path, variables, do_compression=compress)
        check_mat5(path)
        assert set(scipy.io.whosmat(path)) and scipy.io.loadmat(path)["f8"].shape == (3, 4)
        lyhm = write_lyhm(tmp_path / f"lyhm_{compress}.mat")
        if compress:  # structs compressed, as MATLAB's default v7 files hold them
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                scipy.io.savemat(lyhm, scipy.io.loadmat(lyhm), do_compression=True)
        check_model(assert_no_warnings(load_lyhm, lyhm), STD_MM)
        check_model(load_bfm2009(write_bfm2009(tmp_path / f"bfm_{compress}.mat", compress=compress)), STD_MM)


def test_an_unknown_array_class_is_a_model_file_error(tmp_path, monkeypatch):
    """Regression: a damaged array class byte raised scipy's bare UnboundLocalError (from
    _mio5_utils); any exception scipy raises for a damaged file is now an error naming the file."""
    from facenormals.models import load_model

    path = write_bfm2009(tmp_path / "class.mat")
    data = bytearray(path.read_bytes())
    assert data[144] == 7  # shapeMU's array class: single
    data[144] ^= 0xFF
    path.write_bytes(bytes(data))
    for load in (load_bfm2009, load_model):
        with pytest.raises(ModelFileError,
                           match=r"class\.mat: damaged MATLAB file: unknown array class 248 \(at byte 136\)"):
            load(path)

    def unexpected(*args, **kwargs):
        raise UnboundLocalError("local variable 'arr' referenced before assignment")

    monkeypatch.setattr(scipy.io, "loadmat", unexpected)
    with pytest.raises(ModelFileError, match=r"good\.mat: cannot read BFM 2009 MATLAB file \(UnboundLocalError: local"):
        load_bfm2009(write_bfm2009(tmp_path / "good.mat"))


def test_a_matlab_file_whose_variables_cannot_be_listed_is_not_called_an_lyhm_file(tmp_path):
    """Regression: load_model sent a .mat whose variables could not be listed to the LYHM loader, which
    reported a damaged BFM 2009 file as "cannot read LYHM MATLAB file"."""
    from facenormals.models import load_model

    good = write_bfm2009(tmp_path / "bfm.mat")
    data = good.read_bytes()
    cut = tmp_path / "cut.mat"
    cut.write_bytes(data[:64])
    with pytest.raises(ModelFileError,
                       match=r"cut\.mat: cannot read MATLAB file \(tried as BFM 2009 and LYHM\): ") as caught:
        load_model(cut)
    assert "LYHM MATLAB" not in str(caught.value)
    # cut inside the header of its last variable (texMU, which no loader reads): it loads as with load_bfm2009
    end = tmp_path / "cut_in_texture.mat"
    end.write_bytes(data[:data.index(b"texMU") - 8])
    check_model(load_model(end), STD_MM)
    assert load_model(end).name == "bfm2009"


@pytest.mark.parametrize("length, error", [(1 << 62, "MemoryError"), ((1 << 63) + 5, "OverflowError")])
def test_a_damaged_pickle_length_names_the_file(tmp_path, length, error):
    """Regression: a damaged opcode or length in a FLAME pickle (e.g. BINPUT turned into BINBYTES8, whose
    length then comes from the bytes after it) raised a bare MemoryError or OverflowError ("BINBYTES
    exceeds system's maximum size"), naming no file; the command line printed a traceback."""
    import pickletools
    import struct

    from facenormals.models import load_model

    path = write_flame(tmp_path / "flame.pkl")
    data = bytearray(path.read_bytes())
    position = next(pos for op, _, pos in pickletools.genops(bytes(data)) if op.name == "BINPUT")
    data[position] = 0x8E  # BINBYTES8, then an 8-byte length
    data[position + 1:position + 9] = struct.pack("<Q", length)
    path.write_bytes(bytes(data))
    for load in (load_flame, load_model):
        with pytest.raises(ModelFileError, match=rf"flame\.pkl: cannot read FLAME pickle \({error}: .+\)"):
            load(path)
