"""ICT-FaceKit, the MIT-licensed full-head model (face, head, neck and ears).

Two sources are read:

- the converted archive ``ict_face_head.npz`` (:func:`load_ict_npz`), what the library uses at runtime;
- the original repository layout ``FaceXModel/`` of https://github.com/ICT-VGL/ICT-FaceKit
  (:func:`load_ict_raw`), one ``.obj`` per identity mode and expression, which
  :func:`ict_npz_from_raw` converts into the archive.

Only the face and head-and-neck regions of the original are kept: vertices ``0..11247`` and polygons
``0..11143`` (the quads split into triangles ``(a, b, c), (a, c, d)``). Mouth socket, eyeballs, teeth,
eyelashes etc. are dropped.
"""

from __future__ import annotations

import json
import re
import zipfile
from pathlib import Path, PurePosixPath
from typing import Callable

import numpy as np
import torch

from facenormals.core.check import check_integer
from facenormals.core.files import atomic_write
from facenormals.models.landmarks import ict_landmark_indices
from facenormals.models.morphable import (FACE_CROP_RADIUS_MM, NPZ_READ_ERRORS, ModelFileError, MorphableModel,
                                         check_model_dtype, read_npz)

__all__ = ["ict_npz_from_raw", "load_ict_npz", "load_ict_raw", "opengl_to_model_frame"]

ICT_KEYS = ("mean", "faces", "identity_basis", "expression_basis", "expression_names", "landmarks_ibug68")

#: Vertex and polygon counts of the full ICT-FaceKit topology (all 17 geometries).
ICT_FULL_VERTEX_COUNT = 26719
ICT_FULL_POLYGON_COUNT = 26384
#: The kept face + head-and-neck regions (#0 and #1): the first vertices and polygons of the mesh.
ICT_HEAD_VERTEX_COUNT = 11248
ICT_HEAD_POLYGON_COUNT = 11144
#: The face area (region #0) is the first 9409 vertices.
ICT_FACE_VERTEX_COUNT = 9409
#: Identity and expression components of the full release (fewer in a copy converted from a subset).
ICT_FULL_IDENTITIES = 100
ICT_FULL_EXPRESSIONS = 53
ICT_NEUTRAL = "generic_neutral_mesh.obj"
ICT_CONFIG = "vertex_indices.json"
ICT_FOLDER = "FaceXModel"

_IDENTITY_RE = re.compile(r"^identity(\d{3})\.obj$")
_VERTEX_LINE_RE = re.compile(rb"^v[ \t]+(.*)", re.MULTILINE)
_FACE_LINE_RE = re.compile(rb"^f[ \t]+(.*)", re.MULTILINE)


def opengl_to_model_frame(points: np.ndarray, scale: float) -> np.ndarray:
    """Convert ``(..., 3)`` points from an OpenGL-style frame (+y up, +z out of the face) to the
    library's model frame (y down, face along −z) and multiply by ``scale`` (to mm)."""
    return points * np.array([scale, -scale, -scale], dtype=points.dtype)


def load_ict_npz(path: str | Path, num_shape: int | None = None, dtype: torch.dtype = torch.float32) -> MorphableModel:
    """Load the converted ICT-FaceKit archive (``ict_face_head.npz``, see ``shared/data/README.md``).

    The archive is in centimetres in an OpenGL-style frame; the model is returned in millimetres in the
    library's model frame. Identity coefficients have unit variance (``shape_std = 1``). The paper's 24
    landmarks are attached (iBUG points and scripted ear vertices, see ``docs/models.md``); the 68 iBUG
    indices are kept in ``metadata["landmarks_ibug68"]``. The face region is ICT's face area (region
    #0, the first 9,409 vertices) within 95 mm of the nose tip.

    Args:
        path: the ``.npz`` file.
        num_shape: how many identity components to keep; ``None`` keeps all of them (100 in the full
            model; fewer in an archive converted from a partial ``FaceXModel`` folder).
        dtype: floating dtype of the model's buffers.

    Raises:
        ModelFileError: if the file is missing, corrupt or lacks the expected arrays.
        ValueError: if ``num_shape`` is outside ``1..`` the number of identity components.
    """
    check_model_dtype(dtype)
    path = Path(path)
    if not path.exists():
        raise ModelFileError(f"{path}: ICT-FaceKit archive not found")
    try:  # each member read whole and CRC-checked: np.load stopped where a damaged .npy header said
        arrays = read_npz(path, (*ICT_KEYS, "units", "face_vertex_count"))
    except NPZ_READ_ERRORS as error:
        raise ModelFileError(f"{path}: cannot read ICT-FaceKit archive ({type(error).__name__}: {error})") from error
    missing = [k for k in ICT_KEYS if k not in arrays]
    if missing:
        raise ModelFileError(f"{path}: not an ICT-FaceKit archive, missing arrays {missing}")
    units = str(arrays.pop("units")) if "units" in arrays else "cm"
    scale = {"cm": 10.0, "mm": 1.0, "m": 1000.0}.get(units)
    if scale is None:
        raise ModelFileError(f"{path}: unknown units {units!r}, expected 'cm', 'mm' or 'm'")
    _check_ict_arrays(arrays, path)
    available = arrays["identity_basis"].shape[0]
    if num_shape is None:
        num_shape = available
    if isinstance(num_shape, bool) or not isinstance(num_shape, (int, np.integer)) or not 1 <= num_shape <= available:
        raise ValueError(f"num_shape: expected an integer in 1..{available}, got {num_shape!r}")
    arrays["identity_basis"] = arrays["identity_basis"][:num_shape]
    try:
        return _ict_model(arrays, scale, dtype, str(path))
    except (ValueError, IndexError) as error:  # arrays that do not fit together
        raise ModelFileError(f"{path}: inconsistent ICT-FaceKit archive ({type(error).__name__}: {error})") from None


def _check_ict_arrays(arrays: dict, path: Path) -> None:
    """Raise ``ModelFileError`` naming ``path`` unless the archive's arrays have the kinds and ranks
    :func:`_ict_model` needs: numbers where numbers belong, whole numbers for indices (a fractional
    landmark index would be truncated silently), a list of expression names, at least one identity
    mode, a face area of 1 to all vertices."""
    for key, rank in (("mean", 2), ("identity_basis", 3), ("expression_basis", 3), ("faces", 2),
                      ("landmarks_ibug68", 1), ("face_vertex_count", 0)):
        if key not in arrays:
            continue
        value = np.asarray(arrays[key])
        if value.dtype.kind not in "iuf" or value.ndim != rank:
            raise ModelFileError(f"{path}: array {key!r} has dtype {value.dtype} and shape {value.shape}, expected "
                                 f"{'a number' if rank == 0 else f'{rank}-D numbers'}")
        if key in ("faces", "landmarks_ibug68", "face_vertex_count") and value.dtype.kind == "f":
            if not np.array_equal(value, np.round(value)):  # NaN included
                raise ModelFileError(f"{path}: array {key!r} holds indices that are not whole numbers")
    names = np.asarray(arrays["expression_names"])
    if names.ndim != 1:  # a single name (0-d) is no list
        raise ModelFileError(f"{path}: array 'expression_names' has shape {names.shape}, expected a 1-D list")
    if arrays["identity_basis"].shape[0] == 0:
        raise ModelFileError(f"{path}: the archive has no identity modes (identity_basis of shape "
                             f"{arrays['identity_basis'].shape})")
    if "face_vertex_count" in arrays:  # the face area is the first vertices: none or too many is no face area
        count, num_vertices = np.asarray(arrays["face_vertex_count"]).item(), np.asarray(arrays["mean"]).shape[0]
        if not 1 <= count <= num_vertices:
            raise ModelFileError(f"{path}: face_vertex_count is {count}, expected 1 to the {num_vertices} vertices")


def _ict_model(arrays: dict, scale: float, dtype: torch.dtype, file: str) -> MorphableModel:
    """The :class:`MorphableModel` of ICT arrays in the archive's units and OpenGL-style frame; shared by
    :func:`load_ict_npz` and :func:`load_ict_raw` so that both give the same model."""

    def to_model(key: str) -> torch.Tensor:
        return torch.from_numpy(opengl_to_model_frame(np.asarray(arrays[key]), scale)).to(dtype)

    ibug68 = [int(v) for v in arrays["landmarks_ibug68"]]
    num_vertices = np.asarray(arrays["mean"]).shape[0]
    face_count = int(arrays.get("face_vertex_count", ICT_FACE_VERTEX_COUNT))
    # The evaluation face region: ICT's face area (region #0) within 95 mm of the nose tip, the crop
    # radius of common face-reconstruction benchmarks (region #0 alone reaches down the neck).
    mean_cm = np.asarray(arrays["mean"], dtype=np.float64)
    nose = mean_cm[ibug68[30]]
    near = np.linalg.norm(mean_cm - nose, axis=1) * scale < FACE_CROP_RADIUS_MM
    face_region = torch.from_numpy(near & (np.arange(num_vertices) < face_count))
    return MorphableModel(
        to_model("mean"),
        to_model("identity_basis"),
        torch.from_numpy(np.asarray(arrays["faces"]).astype(np.int64)),
        expression_basis=to_model("expression_basis"),
        landmarks=ict_landmark_indices(ibug68),
        expression_names=[str(n) for n in arrays["expression_names"]],
        name="ict",
        metadata={"source": "ICT-FaceKit (USC ICT), face + head-and-neck regions", "license": "MIT",
                  "file": file, "landmarks_ibug68": ibug68},
        face_region=face_region,
    )


# ----------------------------------------------------------------------------------------------------
# The original FaceXModel layout
# ----------------------------------------------------------------------------------------------------


class _FaceXSource:
    """The files of one ``FaceXModel`` folder, either on disk or inside the repository's ``.zip``."""

    def __init__(
        self,
        location: str,
        names: list[str],
        read: Callable[[str], bytes],
        label: Callable[[str], str],
    ) -> None:
        self.location = location
        self.names = set(names)
        self._read = read
        self.label = label

    def read(self, name: str) -> bytes:
        if name not in self.names:
            raise ModelFileError(f"{self.label(name)}: file not found")
        try:
            return self._read(name)
        except NPZ_READ_ERRORS as error:  # the repository .zip: the same errors
            raise ModelFileError(f"{self.label(name)}: cannot read ({type(error).__name__}: {error})") from error


def _folder_source(folder: Path) -> _FaceXSource:
    names = [p.name for p in folder.iterdir() if p.is_file()]
    return _FaceXSource(str(folder), names, lambda n: (folder / n).read_bytes(), lambda n: str(folder / n))


def _zip_source(path: Path, archive: zipfile.ZipFile) -> _FaceXSource:
    """The ``FaceXModel/`` folder inside a repository zip (the shallowest one if several)."""
    folders: dict[str, dict[str, zipfile.ZipInfo]] = {}
    for info in archive.infolist():
        member = PurePosixPath(info.filename)
        if info.is_dir() or member.parent.name != ICT_FOLDER:
            continue
        folders.setdefault(str(member.parent), {})[member.name] = info
    candidates = [k for k, v in folders.items() if ICT_NEUTRAL in v]
    if not candidates:
        raise ModelFileError(f"{path}: no {ICT_FOLDER}/{ICT_NEUTRAL} inside the zip archive")
    prefix = min(candidates, key=lambda k: (k.count("/"), k))
    members = folders[prefix]
    return _FaceXSource(
        f"{path}:{prefix}",
        list(members),
        lambda n: archive.read(members[n]),
        lambda n: f"{path}:{prefix}/{n}",
    )


def _find_facex_folder(path: str | Path) -> Path:
    """The ``FaceXModel`` folder given the folder itself, the repository root containing it, or a folder
    holding one extracted repository (``ICT-FaceKit-master/FaceXModel``).

    Raises:
        ModelFileError: if ``path`` is missing or no ``generic_neutral_mesh.obj`` is found.
    """
    path = Path(path)
    if not path.exists():
        raise ModelFileError(f"{path}: ICT-FaceKit folder not found")
    if not path.is_dir():
        raise ModelFileError(f"{path}: expected the ICT-FaceKit FaceXModel folder or the repository folder")
    for candidate in (path, path / ICT_FOLDER):
        if (candidate / ICT_NEUTRAL).is_file():
            return candidate
    nested = sorted(p.parent for p in path.glob(f"*/{ICT_FOLDER}/{ICT_NEUTRAL}"))
    if len(nested) == 1:
        return nested[0]
    raise ModelFileError(
        f"{path}: not an ICT-FaceKit folder: no {ICT_NEUTRAL} in it or in {path / ICT_FOLDER}"
    )


def _open_source(path: str | Path, stack: list) -> _FaceXSource:
    """A folder (``FaceXModel``, the repository root, or its parent) or the repository ``.zip``."""
    path = Path(path)
    if path.is_file() and zipfile.is_zipfile(path):
        try:
            archive = zipfile.ZipFile(path)
        except (OSError, zipfile.BadZipFile) as error:
            raise ModelFileError(f"{path}: cannot read zip archive ({type(error).__name__}: {error})") from error
        stack.append(archive)
        return _zip_source(path, archive)
    if path.is_file() and path.suffix.lower() == ".zip":
        raise ModelFileError(f"{path}: not a valid zip archive (truncated or corrupt download?)")
    return _folder_source(_find_facex_folder(path))


def _check_lfs(data: bytes, label: str) -> None:
    if data.startswith(b"version https://git-lfs"):
        raise ModelFileError(
            f"{label}: is a Git LFS pointer, not the mesh; fetch the real files (git lfs pull) first"
        )


def _line_number(data: bytes, offset: int) -> int:
    return data.count(b"\n", 0, offset) + 1


def _parse_obj_vertices(data: bytes, label: str, expected: int | None = None) -> np.ndarray:
    """The ``v`` lines of an OBJ file as a float64 ``(N, 3)`` array (extra components such as ``w`` or
    vertex colours are dropped)."""
    _check_lfs(data, label)
    payloads = _VERTEX_LINE_RE.findall(data)
    tokens = b" ; ".join(payloads).split()  # every line has x y z exactly when each 4th token is the ";"
    vertices = None
    if len(tokens) == 4 * len(payloads) - 1 and tokens[3::4].count(b";") == len(payloads) - 1:
        del tokens[3::4]
        try:
            vertices = np.array(tokens, dtype=np.float64).reshape(-1, 3)
        except ValueError:
            vertices = None
    if vertices is None:  # slow path: irregular lines, or locate the unparsable one
        rows = []
        for match in _VERTEX_LINE_RE.finditer(data):
            values = match.group(1).split()
            try:
                if len(values) < 3:
                    raise ValueError("fewer than 3 coordinates")
                rows.append([float(v) for v in values[:3]])
            except ValueError as error:
                line = match.group(0).decode("utf-8", "replace").strip()
                raise ModelFileError(
                    f"{label}: line {_line_number(data, match.start())}: cannot parse vertex {line!r} ({error})"
                ) from None
        vertices = np.array(rows, dtype=np.float64).reshape(-1, 3)
    if expected is not None and vertices.shape[0] != expected:
        raise ModelFileError(
            f"{label}: has {vertices.shape[0]} vertices, expected {expected} (truncated or not an ICT-FaceKit mesh?)"
        )
    if not np.isfinite(vertices).all():
        raise ModelFileError(f"{label}: vertex coordinates are not all finite")
    return vertices


def _parse_obj_polygons(data: bytes, label: str, num_vertices: int) -> list[list[int]]:
    """The ``f`` lines of an OBJ file as 0-based vertex indices (texture / normal indices dropped)."""
    polygons = []
    for match in _FACE_LINE_RE.finditer(data):
        try:
            polygon = [int(token.split(b"/", 1)[0]) - 1 for token in match.group(1).split()]
            if len(polygon) < 3:
                raise ValueError("fewer than 3 vertices")
            if min(polygon) < 0 or max(polygon) >= num_vertices:
                raise ValueError(f"vertex index outside 1..{num_vertices} (relative indices are not supported)")
        except ValueError as error:
            line = match.group(0).decode("utf-8", "replace").strip()
            raise ModelFileError(
                f"{label}: line {_line_number(data, match.start())}: cannot parse face {line!r} ({error})"
            ) from None
        polygons.append(polygon)
    return polygons


def _count_polygons(data: bytes) -> int:
    """The number of ``f`` lines (cheap: a truncated file has fewer than the neutral mesh)."""
    return sum(data.count(b"\n" + start) + data.startswith(start) for start in (b"f ", b"f\t"))


def _triangulate(polygons: list[list[int]]) -> np.ndarray:
    """Fan triangulation ``(a, b, c), (a, c, d), ...``: quads split as (a,b,c),(a,c,d)."""
    triangles = [(p[0], p[i], p[i + 1]) for p in polygons for i in range(1, len(p) - 1)]
    return np.array(triangles, dtype=np.int64).reshape(-1, 3)


def _read_config(source: _FaceXSource) -> dict:
    label = source.label(ICT_CONFIG)
    try:
        config = json.loads(source.read(ICT_CONFIG).decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as error:
        raise ModelFileError(f"{label}: not valid JSON ({error})") from error
    if not isinstance(config, dict):
        raise ModelFileError(f"{label}: expected a JSON object")
    for key in ("expressions", "idx_to_landmark_verts"):
        if not isinstance(config.get(key), list):
            raise ModelFileError(f"{label}: missing the list {key!r}")
    if not all(isinstance(n, str) for n in config["expressions"]):
        raise ModelFileError(f"{label}: 'expressions' must be a list of names")
    landmarks = config["idx_to_landmark_verts"]
    if len(landmarks) != 68 or not all(isinstance(i, int) and 0 <= i < ICT_HEAD_VERTEX_COUNT for i in landmarks):
        raise ModelFileError(
            f"{label}: 'idx_to_landmark_verts' must hold 68 vertex indices in [0, {ICT_HEAD_VERTEX_COUNT})"
        )
    return config


def _identity_names(source: _FaceXSource, num_shape: int | None) -> list[str]:
    if num_shape is not None:
        num_shape = check_integer(num_shape, "num_shape", minimum=1)
    numbers = sorted(int(m.group(1)) for m in map(_IDENTITY_RE.match, source.names) if m)
    present = 0
    while present in numbers:
        present += 1
    if num_shape is None:
        beyond = [n for n in numbers if n > present]
        if beyond:
            raise ModelFileError(
                f"{source.label(f'identity{present:03d}.obj')}: file not found, although identity{beyond[0]:03d}.obj "
                "is present (incomplete copy?)"
            )
        if present == 0:
            raise ModelFileError(f"{source.label('identity000.obj')}: file not found (no identity modes)")
        num_shape = present
    elif num_shape > present:
        raise ModelFileError(
            f"{source.location}: num_shape={num_shape} but only {present} identity files "
            f"(identity000.obj..identity{max(present - 1, 0):03d}.obj) are present"
            + ("" if present else " (none)")
        )
    return [f"identity{k:03d}.obj" for k in range(num_shape)]


def _read_ict_raw(path: str | Path, num_shape: int | None) -> dict:
    """Arrays of the kept regions in the original units (cm) and OpenGL-style frame, float64."""
    stack: list = []
    try:
        source = _open_source(path, stack)
        config = _read_config(source)
        identity_files = _identity_names(source, num_shape)
        expression_names = [n for n in config["expressions"] if f"{n}.obj" in source.names]
        label = source.label(ICT_NEUTRAL)
        data = source.read(ICT_NEUTRAL)
        neutral = _parse_obj_vertices(data, label, ICT_FULL_VERTEX_COUNT)
        polygons = _parse_obj_polygons(data, label, ICT_FULL_VERTEX_COUNT)
        if len(polygons) != ICT_FULL_POLYGON_COUNT:
            raise ModelFileError(
                f"{label}: has {len(polygons)} polygons, expected {ICT_FULL_POLYGON_COUNT} (truncated?)"
            )
        faces = _triangulate(polygons[:ICT_HEAD_POLYGON_COUNT])
        if faces.max() >= ICT_HEAD_VERTEX_COUNT:
            raise ModelFileError(
                f"{label}: the first {ICT_HEAD_POLYGON_COUNT} polygons use vertices beyond "
                f"{ICT_HEAD_VERTEX_COUNT - 1}; not the ICT-FaceKit topology"
            )
        neutral = neutral[:ICT_HEAD_VERTEX_COUNT]

        def deltas(files: list[str]) -> np.ndarray:
            out = np.empty((len(files), ICT_HEAD_VERTEX_COUNT, 3), dtype=np.float64)
            for k, name in enumerate(files):
                blob = source.read(name)
                target = _parse_obj_vertices(blob, source.label(name), ICT_FULL_VERTEX_COUNT)
                count = _count_polygons(blob)
                if count != ICT_FULL_POLYGON_COUNT:
                    raise ModelFileError(
                        f"{source.label(name)}: has {count} polygons, expected {ICT_FULL_POLYGON_COUNT} (truncated?)"
                    )
                out[k] = target[:ICT_HEAD_VERTEX_COUNT] - neutral
            return out

        return {
            "mean": neutral,
            "faces": faces,
            "identity_basis": deltas(identity_files),
            "expression_basis": deltas([f"{n}.obj" for n in expression_names]),
            "expression_names": expression_names,
            "landmarks_ibug68": np.array(config["idx_to_landmark_verts"], dtype=np.int64),
            "location": source.location,
        }
    finally:
        for archive in stack:
            archive.close()


def load_ict_raw(
    folder: str | Path, num_shape: int | None = None, dtype: torch.dtype = torch.float32
) -> MorphableModel:
    """Load ICT-FaceKit from the original repository layout (``FaceXModel/``).

    The folder holds ``generic_neutral_mesh.obj``, ``identity000.obj`` ... ``identity099.obj``, one
    ``.obj`` per expression and ``vertex_indices.json``. Identity modes are ``identityNNN.obj`` minus the
    neutral mesh, with unit-variance coefficients (``shape_std = 1``); expression blendshapes are
    ``<name>.obj`` minus the neutral mesh, for the names listed under ``"expressions"`` in
    ``vertex_indices.json`` whose file is present (all 53 in the full model). The 24 landmarks are built
    from the 68 iBUG landmarks of ``"idx_to_landmark_verts"`` as in :func:`load_ict_npz`. Only the face and
    head-and-neck regions are kept (11,248 vertices, 22,288 triangles), converted from centimetres to
    millimetres and from the OpenGL-style frame to the library's model frame. The result equals
    :func:`load_ict_npz` on the converted archive.

    This parses about 150 OBJ files (a few seconds); use :func:`ict_npz_from_raw` once and load the
    archive at runtime.

    Args:
        folder: the ``FaceXModel`` folder, the repository folder containing it, or the repository's
            ``.zip`` as downloaded from GitHub.
        num_shape: how many identity modes to use (``identity000`` ... in order). ``None`` uses every
            ``identityNNN.obj`` present (numbered consecutively from ``000``, as the original loader).
        dtype: floating dtype of the model's buffers.

    Raises:
        ModelFileError: if the folder or a required file is missing, an OBJ is truncated, unparsable or has
            the wrong vertex count, or ``num_shape`` is larger than the number of identity files present.
        ValueError: if ``num_shape < 1``.
    """
    check_model_dtype(dtype)
    raw = _read_ict_raw(folder, num_shape)
    return _ict_model(raw, 10.0, dtype, raw["location"])  # cm -> mm


def ict_npz_from_raw(folder: str | Path, out_path: str | Path, num_shape: int | None = None) -> Path:
    """Convert the original ``FaceXModel`` layout into the ``ict_face_head.npz`` archive read by
    :func:`load_ict_npz`.

    The archive keeps the original centimetres and OpenGL-style frame (``units = "cm"``), float32
    vertices, int32 triangles: the layout of ``shared/data/ict_facekit/ict_face_head.npz`` (keys
    ``mean``, ``faces``, ``identity_basis``, ``expression_basis``, ``expression_names``,
    ``landmarks_ibug68``, ``face_vertex_count``, ``units``). It is written to a temporary file beside
    ``out_path`` and renamed, so ``out_path`` never holds a partial archive.

    Args:
        folder: as for :func:`load_ict_raw` (folder, repository folder or repository ``.zip``).
        out_path: the ``.npz`` to write; its folder is created.
        num_shape: as for :func:`load_ict_raw`; ``None`` converts every identity present.

    Returns:
        ``out_path``.

    Raises:
        ModelFileError: as :func:`load_ict_raw`.
        OSError: if ``out_path`` cannot be written.
    """
    raw = _read_ict_raw(folder, num_shape)
    arrays = {
        "mean": raw["mean"].astype(np.float32),
        "faces": raw["faces"].astype(np.int32),
        "identity_basis": raw["identity_basis"].astype(np.float32),
        "expression_basis": raw["expression_basis"].astype(np.float32),
        "expression_names": np.array(raw["expression_names"], dtype=str),
        "landmarks_ibug68": raw["landmarks_ibug68"].astype(np.int64),
        "face_vertex_count": np.array(ICT_FACE_VERTEX_COUNT, dtype=np.int64),
        "units": np.array("cm"),
    }
    out_path = Path(out_path)
    out_path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_write(out_path) as part, open(part, "wb") as handle:
        np.savez(handle, **arrays)
    return out_path
