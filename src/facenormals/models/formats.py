r"""Loaders for the morphable models users bring: LYHM, BFM 2009, BFM 2017/2019 and FLAME.

Each loader reads the file a model is distributed in and returns a :class:`MorphableModel` in the
library's conventions (``docs/conventions.md``): millimetres, model frame (x to image right, y down,
face along −z), triangles counter-clockwise seen from outside. All four formats store their
geometry in an OpenGL-style frame (+y up, +z out of the face), converted by the proper rotation
``(x, y, z) -> (x, -y, -z)``, which keeps outward normals outward.

Coefficient semantics are exact for every format:

.. math::  X = X_0 + \sum_k y_k W_k, \qquad y_k \sim \mathcal{N}(0, \sigma_k^2),

with ``shape_std`` holding :math:`\sigma_k` in the coefficient's own units. For the PCA formats
(LYHM, BFM) :math:`W_k` are the file's unit-norm principal components (rotated into the model frame)
and :math:`\sigma_k` the standard deviations in mm, so a face ``z`` standard deviations along
component ``k`` is ``y_k = z * shape_std[k]``. For FLAME, whose components are already scaled by their
standard deviations, :math:`W_k` is that scaled component (in mm) and :math:`\sigma_k = 1`.
Expression blendshapes are always scaled so that expression coefficients have unit variance.

A missing, truncated or corrupt file, or one of an unexpected layout, raises
:class:`ModelFileError` naming the file and what is wrong.
"""

from __future__ import annotations

import pickle
import struct
import warnings
import zlib
from pathlib import Path
from typing import Any

import numpy as np
import scipy.io
import torch

from facenormals.core.check import INWARD_SHARE, outward_share
from facenormals.models.ict import opengl_to_model_frame
from facenormals.models.mat5 import check_mat5
from facenormals.models.morphable import ModelFileError, MorphableModel, check_model_dtype

__all__ = ["load_bfm2009", "load_bfm2017", "load_flame", "load_lyhm"]

# Errors that reading a damaged or foreign file can raise in h5py and numpy (h5py raises RuntimeError for
# some damaged HDF5 structures; a damaged size can ask for more memory than there is). The MATLAB and
# FLAME readers catch every Exception: scipy.io and pickle raise almost any type for garbage.
_READ_ERRORS: tuple[type[BaseException], ...] = (
    OSError,
    RuntimeError,
    ValueError,
    EOFError,
    TypeError,
    LookupError,
    AttributeError,
    NotImplementedError,
    MemoryError,
    OverflowError,
    pickle.UnpicklingError,
    struct.error,
    zlib.error,
    scipy.io.matlab.MatReadError,
)


# --------------------------------------------------------------------------------------------------
# Shared helpers
# --------------------------------------------------------------------------------------------------


def _h5py(path: Path, what: str) -> Any:
    """The h5py module (an optional dependency), imported on first use."""
    try:
        import h5py
    except ImportError as error:
        raise ImportError(f"{path}: reading {what} files needs h5py (pip install h5py)") from error
    return h5py


def _is_hdf5(path: Path) -> bool:
    """Whether ``path`` is an HDF5 file: its signature at offset 0, 512, 1024, ... (MATLAB v7.3 files
    carry a 512-byte header before it)."""
    signature = b"\x89HDF\r\n\x1a\n"
    with open(path, "rb") as handle:
        for offset in (0, 512, 1024, 2048):
            handle.seek(offset)
            if handle.read(8) == signature:
                return True
    return False


def _check_exists(path: Path, what: str) -> None:
    if not path.exists():
        raise ModelFileError(f"{path}: {what} file not found")
    if not path.is_file():
        raise ModelFileError(f"{path}: {what} path is not a file")


def _work_dtype(dtype: torch.dtype) -> np.dtype:
    """NumPy dtype for the conversions: float64 when the model is float64, float32 otherwise."""
    check_model_dtype(dtype)
    return np.dtype(np.float64 if dtype == torch.float64 else np.float32)


def _float_array(path: Path, value: Any, name: str, work: np.dtype) -> np.ndarray:
    try:
        array = np.asarray(value)
        if not np.issubdtype(array.dtype, np.number) or np.issubdtype(array.dtype, np.complexfloating):
            raise TypeError(f"dtype {array.dtype}")
        array = array.astype(work, copy=False)
    except (TypeError, ValueError) as error:
        raise ModelFileError(f"{path}: {name} is not a numeric array ({error})") from error
    if not np.isfinite(array).all():
        raise ModelFileError(f"{path}: {name} holds NaN or infinite values")
    return array


def _check_interleaved(path: Path, mean: np.ndarray, name: str) -> np.ndarray:
    """``mean`` flattened, checked to hold ``x, y, z`` for each of ``N > 0`` vertices: a vector (of any
    singleton dimensions) or ``(N, 3)``; a ``(3, N)`` array holds the coordinates axis by axis and
    would be read as the wrong vertices."""
    extent = [size for size in mean.shape if size != 1]
    if len(extent) > 2 or (len(extent) == 2 and extent[1] != 3):
        raise ModelFileError(f"{path}: {name} has shape {mean.shape}, expected 3N values (x, y, z per vertex) or "
                             "(N, 3)" + ("; it looks stored axis by axis, (3, N): transpose it" if extent[0] == 3 else ""))
    mean = mean.ravel()
    if mean.size == 0 or mean.size % 3:
        raise ModelFileError(f"{path}: {name} has {mean.size} entries, expected 3N (x, y, z per vertex)")
    return mean


def _faces_array(path: Path, value: Any, name: str, num_vertices: int, one_based: bool) -> np.ndarray:
    """Triangles as an ``(F, 3)`` int64 array of 0-based indices, checked against ``num_vertices``."""
    try:
        faces = np.asarray(value)
        if not (np.issubdtype(faces.dtype, np.integer) or np.issubdtype(faces.dtype, np.floating)):
            raise TypeError(f"dtype {faces.dtype}")
    except (TypeError, ValueError) as error:
        raise ModelFileError(f"{path}: {name} is not a numeric array ({error})") from error
    if faces.ndim == 1 and faces.size == 3:  # one triangle, squeezed by loadmat
        faces = faces.reshape(1, 3)
    if faces.ndim != 2 or faces.shape[1] != 3 or faces.shape[0] == 0:
        raise ModelFileError(f"{path}: {name} has shape {faces.shape}, expected (F, 3) triangles")
    if np.issubdtype(faces.dtype, np.floating):
        if not np.isfinite(faces).all() or (faces != np.round(faces)).any():
            raise ModelFileError(f"{path}: {name} holds non-integer vertex indices")
    faces = faces.astype(np.int64)
    if one_based:
        if faces.min() < 1:
            raise ModelFileError(
                f"{path}: {name} holds index {int(faces.min())}, but the format's indices are 1-based"
            )
        faces = faces - 1
    if faces.min() < 0 or faces.max() >= num_vertices:
        base = 1 if one_based else 0
        raise ModelFileError(
            f"{path}: {name} holds indices in [{int(faces.min()) + base}, {int(faces.max()) + base}], "
            f"outside the {num_vertices} vertices of the mean ({base}-based)"
        )
    return faces


def _truncation(num: int | None, available: int, name: str) -> int:
    if num is None:
        return available
    if isinstance(num, bool) or not isinstance(num, (int, np.integer)) or not 1 <= num <= available:
        raise ValueError(f"{name}: expected an integer in 1..{available} or None, got {num!r}")
    return int(num)


def _outward_faces(path: Path, mean: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """``faces``, reversed with a warning if they face inward: the file's triangles are then wound
    the other way from its format's documented one (e.g. a BFM file whose ``tl`` was re-saved
    counter-clockwise), which the loader's own reversal turned inward."""
    if outward_share(torch.from_numpy(mean), torch.from_numpy(faces)) >= INWARD_SHARE:
        return faces
    warnings.warn(f"{path}: the triangles are wound the other way from the format's documented winding (their "
                  "normals pointed into the head); reversed them", stacklevel=3)
    return np.ascontiguousarray(faces[:, [0, 2, 1]])


def _check_unit_norm(path: Path, basis: np.ndarray) -> None:
    """Warn if principal components that should be unit-norm are not (``basis`` is ``(3N, K)``)."""
    norms = np.linalg.norm(basis, axis=0)
    if norms.size and np.abs(norms - 1.0).max() > 1e-2:
        warnings.warn(
            f"{path}: the principal components are not unit-norm (norms in [{norms.min():.4g}, "
            f"{norms.max():.4g}]); shape_std assumes unit-norm components",
            stacklevel=3,
        )


def _pca_model(
    path: Path,
    *,
    mean: np.ndarray,
    basis: np.ndarray,
    spread: np.ndarray,
    spread_is_variance: bool,
    faces: np.ndarray,
    scale: float,
    num_shape: int | None,
    dtype: torch.dtype,
    names: tuple[str, str, str],
    expression_basis: np.ndarray | None = None,
    name: str,
    metadata: dict[str, object],
) -> MorphableModel:
    """Assemble a model from a flat PCA shape model in an OpenGL-style frame.

    ``mean`` is the interleaved ``(3N,)`` mean, ``basis`` the ``(3N, K)`` unit-norm components and
    ``spread`` their ``(K,)`` variances (``spread_is_variance``) or standard deviations, in file units
    (times ``scale`` gives mm); ``faces`` are 0-based and already wound counter-clockwise. ``names``
    are the file's names of mean, basis and spread, for error messages. ``expression_basis`` is
    ``(E, N, 3)`` in mm in the model frame.
    """
    mean_name, basis_name, spread_name = names
    mean = _check_interleaved(path, mean, mean_name)
    num_vertices = mean.size // 3
    if basis.ndim == 1:  # a single component, squeezed by loadmat
        basis = basis.reshape(-1, 1)
    if basis.ndim != 2 or basis.shape[0] != mean.size:
        raise ModelFileError(
            f"{path}: {basis_name} has shape {basis.shape}, expected ({mean.size}, K) to match "
            f"{mean_name} of {mean.size} entries"
        )
    if spread.size != basis.shape[1]:
        raise ModelFileError(
            f"{path}: {spread_name} has {spread.size} entries but {basis_name} has {basis.shape[1]} components"
        )
    keep = _truncation(num_shape, basis.shape[1], "num_shape")
    basis, spread = basis[:, :keep], spread[:keep]
    if not (spread > 0).all():
        first = int(np.flatnonzero(~(spread > 0))[0])
        raise ModelFileError(
            f"{path}: {spread_name}[{first}] is {float(spread[first])!r}, not positive; "
            f"pass num_shape={first} or less to drop the degenerate components"
        )
    std = np.sqrt(spread) if spread_is_variance else spread
    _check_unit_norm(path, basis)
    mean_mm = opengl_to_model_frame(mean.reshape(num_vertices, 3), scale)
    # Unit-norm components stay unit-norm under the rotation; the unit change goes into std.
    basis_mm = opengl_to_model_frame(basis.T.reshape(keep, num_vertices, 3), 1.0)
    faces = _outward_faces(path, mean_mm, faces)
    try:
        return MorphableModel(
            torch.from_numpy(np.ascontiguousarray(mean_mm)).to(dtype),
            torch.from_numpy(np.ascontiguousarray(basis_mm)).to(dtype),
            torch.from_numpy(faces),
            shape_std=torch.from_numpy(np.ascontiguousarray(std * scale)).to(dtype),
            expression_basis=None if expression_basis is None else torch.from_numpy(expression_basis).to(dtype),
            expression_names=None
            if expression_basis is None
            else [f"expr_{j:03d}" for j in range(expression_basis.shape[0])],
            name=name,
            metadata=metadata,
        )
    except ValueError as error:
        raise ModelFileError(f"{path}: inconsistent model arrays: {error}") from error


# --------------------------------------------------------------------------------------------------
# MATLAB files (v5 through scipy, v7.3 through h5py)
# --------------------------------------------------------------------------------------------------


def _mat73_value(node: Any) -> Any:
    """A v7.3 variable as scipy would give it: groups (structs) become dicts, datasets arrays in
    MATLAB's shape (HDF5 stores MATLAB's column-major arrays with the dimensions reversed)."""
    if hasattr(node, "keys"):  # an h5py.Group
        return {key: _mat73_value(node[key]) for key in node.keys() if not key.startswith("#")}
    value = node[()]
    if isinstance(value, np.ndarray) and value.dtype.kind not in "biuf":
        raise ModelFileError(f"{node.file.filename}: variable {node.name} has unsupported dtype {value.dtype}")
    return np.asarray(value).T


def _read_mat(path: Path, names: list[str], what: str, checked: bool = False) -> dict[str, Any]:
    """The variables ``names`` (those present) of a MATLAB file, v5 or v7.3; a v5 file's structure is
    checked first (:func:`~facenormals.models.mat5.check_mat5`) unless ``checked`` says it was."""
    _check_exists(path, what)
    try:
        if _is_hdf5(path):  # MATLAB v7.3 files are HDF5 files with a 512-byte header
            with _h5py(path, "MATLAB v7.3 (HDF5)").File(path, "r") as handle:
                return {key: _mat73_value(handle[key]) for key in names if key in handle}
        if not checked:
            check_mat5(path, names)
        return scipy.io.loadmat(path, struct_as_record=False, squeeze_me=True, variable_names=names)
    except ModelFileError:
        raise
    except Exception as error:  # noqa: BLE001 - scipy raises many types for a damaged file (UnboundLocalError too)
        raise ModelFileError(
            f"{path}: cannot read {what} MATLAB file ({type(error).__name__}: {error})"
        ) from error


_LYHM_VARIABLES = ["shp", "tri"]
_BFM2009_VARIABLES = ["shapeMU", "shapePC", "shapeEV", "tl"]


def _field(container: Any, key: str) -> Any:
    """Field ``key`` of a loaded MATLAB struct (scipy ``mat_struct`` or a v7.3 dict); ``None`` if absent."""
    if isinstance(container, dict):
        return container.get(key)
    if isinstance(container, scipy.io.matlab.mat_struct):
        return getattr(container, key, None)
    return None


def _is_struct(value: Any) -> bool:
    return isinstance(value, (dict, scipy.io.matlab.mat_struct))


def _require(path: Path, value: Any, name: str) -> Any:
    if value is None:
        raise ModelFileError(f"{path}: missing {name}")
    return value


def load_lyhm(path: str | Path, num_shape: int | None = None, dtype: torch.dtype = torch.float32) -> MorphableModel:
    r"""Load the Liverpool-York Head Model (LYHM) from one of its MATLAB ``.mat`` files.

    Layout (as distributed, e.g. ``LYHM_global.mat``): a struct ``shp`` with ``mu`` (the mean,
    interleaved ``x, y, z`` per vertex, stored as a ``1 × 3N`` row; a column is accepted too),
    ``eigVec`` (``3N × K``, orthonormal columns) and ``eigVal`` (``K`` **variances**), and a struct
    ``tri`` with ``faces`` (``F × 3``, **1-based**, wound clockwise seen from outside, i.e. reversed
    relative to OpenGL; the loader swaps two indices per triangle). ``tri`` is also looked up inside
    ``shp``. The texture model ``tex`` is ignored. MATLAB v5/v7 files are read with scipy, v7.3
    (HDF5) files with h5py.

    Units and frame: millimetres, OpenGL-style (+y up, +z out of the face); converted to the model
    frame. Coefficients: ``shape_basis`` are the unit-norm ``eigVec`` columns and
    ``shape_std = sqrt(eigVal)`` in mm, so :math:`X = X_0 + \sum_k y_k W_k`, :math:`y_k \sim
    \mathcal{N}(0, \text{eigVal}_k)`.

    Licence: the LYHM is licensed by the University of York for non-commercial academic research;
    check the terms of your licence before sharing the file or models derived from it.

    Args:
        path: the ``.mat`` file.
        num_shape: keep the first ``num_shape`` components (default all).
        dtype: floating dtype of the model's buffers.

    Raises:
        ModelFileError: if the file is missing, unreadable, lacks a field or has inconsistent shapes.
        ValueError: if ``num_shape`` is out of range.
    """
    path = Path(path)
    return _lyhm_model(path, _read_mat(path, _LYHM_VARIABLES, "LYHM"), num_shape, dtype)


def _lyhm_model(path: Path, data: dict[str, Any], num_shape: int | None, dtype: torch.dtype) -> MorphableModel:
    shp = _require(path, data.get("shp"), "variable 'shp' (not an LYHM file?)")
    if not _is_struct(shp):
        raise ModelFileError(f"{path}: variable 'shp' is a {type(shp).__name__}, expected a struct")
    work = _work_dtype(dtype)
    mean = _float_array(path, _require(path, _field(shp, "mu"), "field shp.mu"), "shp.mu", work)
    mean = _check_interleaved(path, mean, "shp.mu")
    basis = _float_array(path, _require(path, _field(shp, "eigVec"), "field shp.eigVec"), "shp.eigVec", work)
    variance = _float_array(path, _require(path, _field(shp, "eigVal"), "field shp.eigVal"), "shp.eigVal", work)
    faces = _field(data.get("tri"), "faces")
    if faces is None:  # also accept the triangles inside shp
        faces = _field(_field(shp, "tri"), "faces")
    faces = _require(path, faces, "struct tri with field faces")
    faces = _faces_array(path, faces, "tri.faces", mean.size // 3, one_based=True)[:, [0, 2, 1]]
    return _pca_model(
        path,
        mean=mean,
        basis=basis,
        spread=variance.ravel(),
        spread_is_variance=True,
        faces=faces,
        scale=1.0,
        num_shape=num_shape,
        dtype=dtype,
        names=("shp.mu", "shp.eigVec", "shp.eigVal"),
        name="lyhm",
        metadata={
            "source": "Liverpool-York Head Model (LYHM), Dai, Pears, Smith and Duncan",
            "format": "lyhm-mat",
            "license": "University of York licence for non-commercial academic research; check its terms",
            "file": str(path),
            "file_units": "mm",
            "file_frame": "+y up, +z out of the face, triangles reversed (clockwise)",
            "coefficients": "y_k ~ N(0, shape_std_k^2), shape_std = sqrt(eigVal) in mm, unit-norm components",
        },
    )


def load_bfm2009(path: str | Path, num_shape: int | None = None, dtype: torch.dtype = torch.float32) -> MorphableModel:
    r"""Load the Basel Face Model 2009 from ``01_MorphableModel.mat`` (the ``PublicMM1`` download).

    Layout: ``shapeMU`` (``3N × 1`` mean, interleaved ``x, y, z``), ``shapePC`` (``3N × K``
    orthonormal principal components), ``shapeEV`` (``K × 1`` **standard deviations**, not
    variances: BFM's ``coef2object`` computes ``shapeMU + shapePC * (coef .* shapeEV)``) and ``tl``
    (``F × 3``, **1-based**, wound clockwise seen from outside; BFM's own ``plywrite`` swaps two
    indices, and so does the loader). Texture and segment variables are not read (nor checked).

    Units and frame: **micrometres** (converted to mm), OpenGL-style (+y up, +z out of the face);
    converted to the model frame. Coefficients: ``shape_basis`` are the unit-norm ``shapePC`` columns
    and ``shape_std = shapeEV / 1000`` in mm, so BFM's coefficient ``alpha_k`` (in standard
    deviations) is ``y_k = alpha_k * shape_std[k]``.

    Licence: the BFM is licensed by the University of Basel for non-commercial research; check the
    terms of your download before sharing the file or models derived from it.

    Args:
        path: the ``.mat`` file (MATLAB v5/v7 through scipy, v7.3 through h5py).
        num_shape: keep the first ``num_shape`` of the 199 components (default all).
        dtype: floating dtype of the model's buffers.

    Raises:
        ModelFileError: if the file is missing, unreadable, lacks a variable or has inconsistent shapes.
        ValueError: if ``num_shape`` is out of range.
    """
    path = Path(path)
    return _bfm2009_model(path, _read_mat(path, _BFM2009_VARIABLES, "BFM 2009"), num_shape, dtype)


def _bfm2009_model(path: Path, data: dict[str, Any], num_shape: int | None, dtype: torch.dtype) -> MorphableModel:
    missing = [key for key in _BFM2009_VARIABLES if data.get(key) is None]
    if missing:
        raise ModelFileError(f"{path}: not a BFM 2009 01_MorphableModel.mat, missing variables {missing}")
    work = _work_dtype(dtype)
    mean = _check_interleaved(path, _float_array(path, data["shapeMU"], "shapeMU", work), "shapeMU")
    faces = _faces_array(path, data["tl"], "tl", mean.size // 3, one_based=True)[:, [0, 2, 1]]
    return _pca_model(
        path,
        mean=mean,
        basis=_float_array(path, data["shapePC"], "shapePC", work),
        spread=_float_array(path, data["shapeEV"], "shapeEV", work).ravel(),
        spread_is_variance=False,
        faces=faces,
        scale=1e-3,
        num_shape=num_shape,
        dtype=dtype,
        names=("shapeMU", "shapePC", "shapeEV"),
        name="bfm2009",
        metadata={
            "source": "Basel Face Model 2009 (Paysan et al., University of Basel), 01_MorphableModel.mat",
            "format": "bfm2009-mat",
            "license": "University of Basel BFM licence for non-commercial research; check its terms",
            "file": str(path),
            "file_units": "um",
            "file_frame": "+y up, +z out of the face, triangles reversed (clockwise)",
            "coefficients": "y_k ~ N(0, shape_std_k^2), shape_std = shapeEV / 1000 in mm, unit-norm components",
        },
    )


def _load_matlab_model(path: str | Path, dtype: torch.dtype = torch.float32) -> MorphableModel:
    """Load a BFM 2009 or an LYHM ``.mat`` file, telling them apart by their variables (``shapeMU``, ``shp``).

    A v5 file's structure is checked once (:func:`~facenormals.models.mat5.check_mat5`). When its variables cannot be listed
    (a damaged or truncated file), each format's own variables are read in turn, which works when the
    damage lies in variables neither reads; otherwise the error says that both formats were tried.

    Raises:
        ModelFileError: naming the file if it is missing, damaged, of neither layout, or its model is invalid.
    """
    path = Path(path)
    _check_exists(path, "MATLAB")
    names: set[str] | None = None
    try:
        if _is_hdf5(path):  # MATLAB v7.3
            with _h5py(path, "MATLAB v7.3 (HDF5)").File(path, "r") as handle:
                names = set(handle.keys())
        else:
            check_mat5(path, _BFM2009_VARIABLES + _LYHM_VARIABLES)  # before scipy reads (a bad type crashed it)
            names = {entry[0] for entry in scipy.io.whosmat(path)}
    except ModelFileError:
        raise
    except Exception as error:  # noqa: BLE001 - damaged files: scipy and h5py raise many types
        reason = f"{type(error).__name__}: {error}"
    if names is not None:
        if "shapeMU" in names:
            return _bfm2009_model(path, _read_mat(path, _BFM2009_VARIABLES, "BFM 2009", checked=True), None, dtype)
        if "shp" in names:
            return _lyhm_model(path, _read_mat(path, _LYHM_VARIABLES, "LYHM", checked=True), None, dtype)
        raise ModelFileError(f"{path}: neither a BFM 2009 model (variable 'shapeMU') nor an LYHM one ('shp'); "
                             f"it holds {sorted(names)[:8]}")
    for variables, key, build in ((_BFM2009_VARIABLES, "shapeMU", _bfm2009_model),
                                  (_LYHM_VARIABLES, "shp", _lyhm_model)):
        try:
            data = _read_mat(path, variables, "MATLAB", checked=True)
        except ModelFileError:
            continue
        if data.get(key) is not None:
            return build(path, data, None, dtype)
    raise ModelFileError(f"{path}: cannot read MATLAB file (tried as BFM 2009 and LYHM): {reason}")


# --------------------------------------------------------------------------------------------------
# Statismo HDF5 (BFM 2017 / 2019)
# --------------------------------------------------------------------------------------------------


#: The top-level groups of a statismo BFM file (2009 .h5, 2017, 2019).
_STATISMO_GROUPS = ("shape", "expression", "color", "catalog", "metadata", "version")


def _check_statismo_groups(path: Path, handle: Any, h5py: Any) -> None:
    """Refuse a BFM .h5 file whose top-level names show damage; warn about other unknown ones.

    A damaged byte in a group's name hides the group: ``expression`` turned into ``b'expressio\\x91'``
    and the model loaded with no expressions and another mean, without a word. Names that are not
    printable text, and a model group of unknown name where ``expression`` is missing, are refused.
    """
    names = list(handle.keys())
    if "shape" not in names and "model" in names and "representer" in names:
        raise ModelFileError(f"{path}: a plain statismo shape model (top-level 'model' and 'representer', as scalismo "
                             "writes), not a BFM file (its model under 'shape'): its frame and units are unknown here; "
                             "build a MorphableModel in the model frame of docs/conventions.md (millimetres, face "
                             "along -z) and save it as a facenormals .npz")
    for name in names:  # h5py gives bytes for a name that is not UTF-8
        if not isinstance(name, str) or not name.isprintable():
            raise ModelFileError(f"{path}: damaged BFM .h5 file: the top-level group name {name!r} is not printable "
                                 f"text (a statismo BFM file holds {', '.join(_STATISMO_GROUPS)})")
    unknown = [name for name in names if name not in _STATISMO_GROUPS]
    models = [name for name in unknown if isinstance(handle[name], h5py.Group) and "model" in handle[name]]
    if models and "expression" not in handle:
        raise ModelFileError(f"{path}: damaged BFM .h5 file? it holds a model named {models[0]!r} and none named "
                             f"'expression' (a statismo BFM file holds {', '.join(_STATISMO_GROUPS)})")
    if unknown:
        warnings.warn(f"{path}: ignored the unknown top-level groups {unknown} (a statismo BFM file holds "
                      f"{', '.join(_STATISMO_GROUPS)}): is the file damaged?", stacklevel=3)


def load_bfm2017(
    path: str | Path,
    num_shape: int | None = None,
    dtype: torch.dtype = torch.float32,
    *,
    expressions: bool = True,
    num_expression: int | None = None,
) -> MorphableModel:
    r"""Load a Basel Face Model 2017 or 2019 statismo ``.h5`` file (e.g. ``model2017-1_bfm_nomouth.h5``).

    Layout (statismo): ``shape/model/mean`` (``3N``, interleaved ``x, y, z``),
    ``shape/model/pcaBasis`` (``3N × K``, orthonormal columns), ``shape/model/pcaVariance`` (``K``
    **variances**), ``shape/representer/cells`` (``3 × F``, 0-based, counter-clockwise seen from
    outside) and ``shape/representer/points`` (``3 × N`` reference, used to check ``N``). The
    optional ``expression/model`` group has the same ``mean``/``pcaBasis``/``pcaVariance`` layout and
    is a model of *deformations*; ``noiseVariance`` and the colour model are ignored.

    Units and frame: millimetres, OpenGL-style (+y up, +z out of the face); converted to the model
    frame. Coefficients: ``shape_basis`` are the unit-norm ``pcaBasis`` columns and
    ``shape_std = sqrt(pcaVariance)`` in mm. With ``expressions`` (and an expression model in the
    file) the expression blendshapes are ``pcaBasis_j * sqrt(pcaVariance_j)``, so expression
    coefficients are standard normal, and — as in scalismo-faces' reference implementation — the
    expression model's mean deformation is **added to** ``mean``: ``mean`` is then the average face
    with the average expression, and the neutral shape mean is ``mean - expression mean``. Without
    expressions, ``mean`` is the shape model's (neutral) mean.

    The statismo BFM 2009 (``model2009-publicmm1-bfm.h5``, in mm) has the same layout.

    Licence: the BFM is licensed by the University of Basel for non-commercial research; check the
    terms of your download.

    Args:
        path: the ``.h5`` file.
        num_shape: keep the first ``num_shape`` shape components (default all).
        dtype: floating dtype of the model's buffers.
        expressions: load the expression model if the file has one.
        num_expression: keep the first ``num_expression`` expression components (default all).

    Raises:
        ModelFileError: if the file is missing, unreadable, lacks a dataset or has inconsistent shapes.
        ValueError: if ``num_shape`` or ``num_expression`` is out of range.
    """
    path = Path(path)
    _check_exists(path, "BFM .h5")
    h5py = _h5py(path, "BFM .h5")
    keys = ["shape/model/mean", "shape/model/pcaBasis", "shape/model/pcaVariance", "shape/representer/cells"]
    expr_keys = ["expression/model/mean", "expression/model/pcaBasis", "expression/model/pcaVariance"]
    try:
        with h5py.File(path, "r") as handle:
            _check_statismo_groups(path, handle, h5py)
            missing = [key for key in keys if key not in handle]
            if missing:
                raise ModelFileError(f"{path}: not a statismo BFM model file, missing datasets {missing}")
            arrays = {key: handle[key][()] for key in keys}
            if "shape/representer/points" in handle:
                arrays["points"] = handle["shape/representer/points"][()]
            has_expr = expressions and "expression/model" in handle
            if has_expr:
                missing = [key for key in expr_keys if key not in handle]
                if missing:
                    raise ModelFileError(f"{path}: incomplete expression model, missing datasets {missing}")
                arrays.update({key: handle[key][()] for key in expr_keys})
    except ModelFileError:
        raise
    except _READ_ERRORS as error:
        raise ModelFileError(f"{path}: cannot read BFM .h5 file ({type(error).__name__}: {error})") from error

    work = _work_dtype(dtype)
    mean = _float_array(path, arrays["shape/model/mean"], "shape/model/mean", work)
    mean = _check_interleaved(path, mean, "shape/model/mean")
    num_vertices = mean.size // 3
    cells = np.asarray(arrays["shape/representer/cells"])
    if cells.ndim != 2 or cells.shape[0] != 3:
        raise ModelFileError(f"{path}: shape/representer/cells has shape {cells.shape}, expected (3, F)")
    faces = _faces_array(path, cells.T, "shape/representer/cells", num_vertices, one_based=False)
    if "points" in arrays and np.shape(arrays["points"]) != (3, num_vertices):
        raise ModelFileError(
            f"{path}: shape/representer/points has shape {np.shape(arrays['points'])}, "
            f"expected (3, {num_vertices}) to match shape/model/mean"
        )
    variance = _float_array(path, arrays["shape/model/pcaVariance"], "shape/model/pcaVariance", work).ravel()
    expression_basis = None
    if num_expression is not None and not has_expr:
        why = "expressions=False" if not expressions else "the file has no expression model"
        raise ValueError(f"num_expression: expected None ({why}), got {num_expression!r}")
    if has_expr:
        expr_mean = _float_array(path, arrays["expression/model/mean"], "expression/model/mean", work).ravel()
        expr_pcs = _float_array(path, arrays["expression/model/pcaBasis"], "expression/model/pcaBasis", work)
        expr_var = _float_array(path, arrays["expression/model/pcaVariance"], "expression/model/pcaVariance", work)
        expr_var = expr_var.ravel()
        if expr_mean.size != mean.size:
            raise ModelFileError(
                f"{path}: expression/model/mean has {expr_mean.size} entries, expected {mean.size}"
            )
        if expr_pcs.ndim != 2 or expr_pcs.shape[0] != mean.size or expr_pcs.shape[1] != expr_var.size:
            raise ModelFileError(
                f"{path}: expression/model/pcaBasis has shape {expr_pcs.shape}, expected "
                f"({mean.size}, {expr_var.size}) to match the mean and pcaVariance"
            )
        keep = _truncation(num_expression, expr_var.size, "num_expression")
        if not (expr_var[:keep] >= 0).all():
            raise ModelFileError(f"{path}: expression/model/pcaVariance holds negative variances")
        scaled = expr_pcs[:, :keep] * np.sqrt(expr_var[:keep])
        expression_basis = np.ascontiguousarray(opengl_to_model_frame(scaled.T.reshape(keep, num_vertices, 3), 1.0))
        mean = mean + expr_mean
    return _pca_model(
        path,
        mean=mean,
        basis=_float_array(path, arrays["shape/model/pcaBasis"], "shape/model/pcaBasis", work),
        spread=variance,
        spread_is_variance=True,
        faces=faces,
        scale=1.0,
        num_shape=num_shape,
        dtype=dtype,
        names=("shape/model/mean", "shape/model/pcaBasis", "shape/model/pcaVariance"),
        expression_basis=expression_basis,
        name="bfm2017",
        metadata={
            "source": "Basel Face Model 2017/2019 (Gerig et al., University of Basel), statismo .h5",
            "format": "bfm-statismo-h5",
            "license": "University of Basel BFM licence: non-commercial research; check the terms of your download",
            "file": str(path),
            "file_units": "mm",
            "file_frame": "+y up, +z out of the face, triangles counter-clockwise",
            "coefficients": "y_k ~ N(0, shape_std_k^2), shape_std = sqrt(pcaVariance) in mm, unit-norm "
            "components; expression coefficients ~ N(0, 1)",
            "expression_mean_in_mean": bool(has_expr),
        },
    )


# --------------------------------------------------------------------------------------------------
# FLAME pickles (chumpy objects, without chumpy)
# --------------------------------------------------------------------------------------------------


class _StandIn:
    """Inert stand-in for a class named by a pickle that the loader does not need (chumpy's ``Ch``,
    scipy's sparse matrices, ...). It records constructor arguments and pickled state and runs no
    code of the original class."""

    origin = "?"
    args: tuple = ()
    state: Any = None

    def __new__(cls, *args: Any, **kwargs: Any) -> "_StandIn":
        obj = object.__new__(cls)
        obj.args = args
        return obj

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        pass

    def __setstate__(self, state: Any) -> None:
        self.state = state


# Globals the FLAME unpickler resolves for real (numpy arrays and plain values); everything else
# becomes a _StandIn subclass. Python 2 spellings are listed too; pickle maps them when resolving.
_NUMPY_CORE = "numpy._core" if int(np.__version__.split(".")[0]) >= 2 else "numpy.core"
_ALLOWED_GLOBALS = {
    ("numpy", "ndarray"),
    ("numpy", "dtype"),
    (f"{_NUMPY_CORE}.multiarray", "_reconstruct"),
    (f"{_NUMPY_CORE}.multiarray", "scalar"),
    (f"{_NUMPY_CORE}.numeric", "_frombuffer"),
    ("_codecs", "encode"),
    ("copyreg", "_reconstructor"),
    ("copy_reg", "_reconstructor"),
    ("builtins", "object"),
    ("__builtin__", "object"),
    ("builtins", "set"),
    ("__builtin__", "set"),
    ("builtins", "frozenset"),
    ("__builtin__", "frozenset"),
    ("collections", "OrderedDict"),
}


class _FlameUnpickler(pickle.Unpickler):
    """Unpickler that rebuilds numpy arrays but replaces every other class by an inert stand-in, so
    that FLAME pickles load without chumpy (or scipy) installed and without running their code."""

    def __init__(self, file: Any) -> None:
        super().__init__(file, encoding="latin1")
        self._stand_ins: dict[tuple[str, str], type] = {}

    def find_class(self, module: str, name: str) -> Any:
        for prefix in ("numpy.core", "numpy._core"):  # NumPy 1.x and 2.x spellings
            if module == prefix or module.startswith(prefix + "."):
                module = _NUMPY_CORE + module[len(prefix):]
        if (module, name) in _ALLOWED_GLOBALS:
            return super().find_class(module, name)
        key = (module, name)
        if key not in self._stand_ins:
            self._stand_ins[key] = type(name, (_StandIn,), {"origin": f"{module}.{name}"})
        return self._stand_ins[key]


def _unpickled_array(path: Path, value: Any, key: str) -> np.ndarray:
    """The array held by a pickled value: an ndarray, or a chumpy ``Ch`` (its ``x``)."""
    if isinstance(value, _StandIn):
        state = value.state
        if isinstance(state, dict) and "x" in state:
            return _unpickled_array(path, state["x"], key)
        raise ModelFileError(
            f"{path}: '{key}' is a {value.origin} object that cannot be evaluated without its library "
            "(expected an array or a plain chumpy Ch holding one)"
        )
    if isinstance(value, np.ndarray):
        return value
    raise ModelFileError(f"{path}: '{key}' is a {type(value).__name__}, expected an array")


def load_flame(
    path: str | Path,
    num_shape: int | None = None,
    dtype: torch.dtype = torch.float32,
    *,
    num_identity: int = 300,
    num_expression: int | None = None,
) -> MorphableModel:
    r"""Load a FLAME model pickle (``generic_model.pkl``, ``flame2020``/``flame2023`` ``.pkl``).

    Layout: a dict with ``v_template`` (``N × 3``), ``shapedirs`` (``N × 3 × D``: the first
    ``num_identity`` = 300 columns are identity shape, the rest (100 in FLAME 2017–2023) expression),
    ``f`` (``F × 3``, 0-based, counter-clockwise seen from outside) and the articulation data
    (``posedirs``, ``J_regressor`` (scipy sparse), ``weights``, ``kintree_table``), which is ignored:
    the returned linear model is the template in its zero pose (jaw, neck and eyeballs closed or
    straight). The arrays may be chumpy ``Ch`` objects and the pickle may come from Python 2; it is
    read with a restricted unpickler that rebuilds numpy arrays and replaces chumpy and scipy classes
    by inert stand-ins, so neither needs to be installed and no code from the file is run.

    Units and frame: metres, OpenGL-style (+y up, +z out of the face); converted to mm in the model
    frame. Coefficients: FLAME's components are already scaled by their standard deviations
    (shape and expression parameters are standard normal), so ``shape_basis`` is
    ``shapedirs[..., :num_identity]`` (in mm), ``shape_std = 1`` and FLAME's ``betas`` can be used as
    ``y`` directly. The expression columns become ``expression_basis`` named ``expr_000`` ...

    Licence: FLAME is licensed by the Max Planck Institute for Intelligent Systems
    (flame.is.tue.mpg.de); terms differ between releases, check the licence of your download.

    Args:
        path: the ``.pkl`` file.
        num_shape: keep the first ``num_shape`` identity components (default all ``num_identity``).
        dtype: floating dtype of the model's buffers.
        num_identity: how many leading ``shapedirs`` columns are identity components.
        num_expression: keep the first ``num_expression`` expression components (default all).

    Raises:
        ModelFileError: if the file is missing, unreadable, lacks a key or has inconsistent shapes.
        ValueError: if ``num_shape``, ``num_identity`` or ``num_expression`` is out of range.
    """
    path = Path(path)
    _check_exists(path, "FLAME")
    try:
        with open(path, "rb") as handle:
            data = _FlameUnpickler(handle).load()
    except Exception as error:  # noqa: BLE001 - garbage makes pickle raise anything (the unpickler runs no code)
        reason = str(error) or ("a length in the file asks for more memory than there is: a damaged pickle?"
                                if isinstance(error, MemoryError) else "")
        raise ModelFileError(f"{path}: cannot read FLAME pickle ({type(error).__name__}: {reason})") from error
    if not isinstance(data, dict):
        raise ModelFileError(f"{path}: the pickle holds a {type(data).__name__}, expected a FLAME dict")
    missing = [key for key in ("v_template", "shapedirs", "f") if key not in data]
    if missing:
        raise ModelFileError(f"{path}: not a FLAME model, missing keys {missing}")
    work = _work_dtype(dtype)
    template = _float_array(path, _unpickled_array(path, data["v_template"], "v_template"), "v_template", work)
    dirs = _float_array(path, _unpickled_array(path, data["shapedirs"], "shapedirs"), "shapedirs", work)
    if template.ndim != 2 or template.shape[1] != 3 or template.shape[0] == 0:
        raise ModelFileError(f"{path}: v_template has shape {template.shape}, expected (N, 3)")
    num_vertices = template.shape[0]
    if dirs.ndim != 3 or dirs.shape[:2] != (num_vertices, 3):
        raise ModelFileError(
            f"{path}: shapedirs has shape {dirs.shape}, expected ({num_vertices}, 3, D) to match v_template"
        )
    if isinstance(num_identity, bool) or not isinstance(num_identity, (int, np.integer)) or num_identity < 1:
        raise ValueError(f"num_identity: expected a positive integer, got {num_identity!r}")
    if dirs.shape[2] < num_identity:
        raise ModelFileError(
            f"{path}: shapedirs has {dirs.shape[2]} components, fewer than num_identity={num_identity}"
        )
    faces = _faces_array(path, _unpickled_array(path, data["f"], "f"), "f", num_vertices, one_based=False)
    keep = _truncation(num_shape, num_identity, "num_shape")
    shape_basis = opengl_to_model_frame(np.moveaxis(dirs[:, :, :keep], 2, 0), 1000.0)
    num_expr_available = dirs.shape[2] - num_identity
    expression_basis = None
    if num_expr_available:
        keep_expr = _truncation(num_expression, num_expr_available, "num_expression")
        expr = dirs[:, :, num_identity : num_identity + keep_expr]
        expression_basis = opengl_to_model_frame(np.moveaxis(expr, 2, 0), 1000.0)
    elif num_expression is not None:
        raise ValueError(f"num_expression: the file has no expression components, got {num_expression!r}")
    mean = opengl_to_model_frame(template, 1000.0)
    faces = _outward_faces(path, mean, faces)
    try:
        return MorphableModel(
            torch.from_numpy(np.ascontiguousarray(mean)).to(dtype),
            torch.from_numpy(np.ascontiguousarray(shape_basis)).to(dtype),
            torch.from_numpy(faces),
            shape_std=torch.ones(keep, dtype=dtype),
            expression_basis=None
            if expression_basis is None
            else torch.from_numpy(np.ascontiguousarray(expression_basis)).to(dtype),
            expression_names=None
            if expression_basis is None
            else [f"expr_{j:03d}" for j in range(expression_basis.shape[0])],
            name="flame",
            metadata={
                "source": "FLAME (Li, Bolkart, Black, Li and Romero; MPI for Intelligent Systems)",
                "format": "flame-pkl",
                "license": "MPI-IS FLAME licence (flame.is.tue.mpg.de); terms differ between releases, "
                "check those of your download",
                "file": str(path),
                "file_units": "m",
                "file_frame": "+y up, +z out of the face, triangles counter-clockwise",
                "coefficients": "shapedirs scaled by the standard deviations: shape_std = 1, FLAME betas "
                "and expression parameters ~ N(0, 1); zero pose",
            },
        )
    except ValueError as error:
        raise ModelFileError(f"{path}: inconsistent model arrays: {error}") from error
