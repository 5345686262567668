"""Reading and writing triangle meshes (``.ply``, ``.obj``, ... through trimesh)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from facenormals.core.check import check_faces, check_finite, check_shape
from facenormals.core.files import atomic_write

__all__ = ["load_mesh", "save_mesh"]

#: The file suffixes :func:`save_mesh` writes (through trimesh).
_MESH_FORMATS = ("ply", "obj", "off", "glb", "stl")


def save_mesh(path: str | Path, vertices: Tensor, faces: Tensor) -> Path:
    """Write a mesh; the format follows the extension (``.ply``, ``.obj``, ``.off``, ``.glb``: indexed
    formats, which :func:`load_mesh` reads back with the same vertices and faces; ``.stl`` stores
    unindexed triangles and loses the topology).

    ``.ply`` (binary, float64 coordinates) and ``.obj`` (text, 9 significant digits: exact for
    float32) are written directly, the other formats through trimesh, whose import alone takes
    about half a second.

    The file is replaced atomically (:func:`~facenormals.core.atomic_write`): an error midway leaves
    an existing file as it was.

    Args:
        path: output file; its folder is created.
        vertices: ``(N, 3)`` or ``(1, N, 3)`` vertices (mm).
        faces: ``(F, 3)`` integer triangles indexing ``vertices``.

    Returns:
        The path written.

    Example:
        >>> import tempfile, os
        >>> out = save_mesh(os.path.join(tempfile.mkdtemp(), "t.ply"), torch.eye(3), torch.tensor([[0, 1, 2]]))
        >>> out.suffix
        '.ply'
    """
    if isinstance(vertices, Tensor) and vertices.dim() == 3:
        check_shape(vertices, [1, "N", 3], "vertices")
        vertices = vertices[0]
    check_shape(vertices, ["N", 3], "vertices")
    check_finite(vertices, "vertices")  # load_mesh would refuse the file
    check_faces(faces, vertices.shape[0], "faces")
    path = Path(path)
    suffix = path.suffix.lstrip(".").lower()
    if suffix not in _MESH_FORMATS:
        raise ValueError(f"{path}: expected a mesh file name ending in one of "
                         f"{', '.join('.' + f for f in _MESH_FORMATS)}, got {path.suffix or 'no suffix'!r}")
    path.parent.mkdir(parents=True, exist_ok=True)
    points = vertices.detach().cpu().double().numpy()
    triangles = faces.detach().cpu().numpy().astype(np.int64)
    with atomic_write(path) as part:
        if suffix == "ply":
            _write_ply(part, points, triangles)
        elif suffix == "obj":
            _write_obj(part, points, triangles)
        else:
            import trimesh

            trimesh.Trimesh(points, triangles, process=False).export(part, file_type=suffix)
    return path


def _write_ply(path: Path, points: np.ndarray, triangles: np.ndarray) -> None:
    header = (f"ply\nformat binary_little_endian 1.0\ncomment facenormals\nelement vertex {len(points)}\n"
              "property double x\nproperty double y\nproperty double z\n"
              f"element face {len(triangles)}\nproperty list uchar int vertex_indices\nend_header\n")
    records = np.empty(len(triangles), dtype=[("count", "u1"), ("indices", "<i4", (3,))])
    records["count"], records["indices"] = 3, triangles
    with open(path, "wb") as file:
        file.write(header.encode("ascii"))
        file.write(points.astype("<f8").tobytes())
        file.write(records.tobytes())


def _write_obj(path: Path, points: np.ndarray, triangles: np.ndarray) -> None:
    # one %-format over all numbers: five times faster than np.savetxt's loop over rows
    text = ("# facenormals\n" + ("v %.9g %.9g %.9g\n" * len(points)) % tuple(points.ravel().tolist())
            + ("f %d %d %d\n" * len(triangles)) % tuple((triangles + 1).ravel().tolist()))
    with open(path, "w", encoding="ascii") as file:
        file.write(text)


def load_mesh(path: str | Path, dtype: torch.dtype = torch.float32) -> tuple[Tensor, Tensor]:
    """Read a triangle mesh as ``(vertices (N, 3), faces (F, 3))`` without reordering vertices or
    dropping unused ones, so a mesh written by :func:`save_mesh` in an indexed format keeps its
    topology (per-vertex correspondence with its model).

    Raises:
        ValueError: naming the file when it is missing, unreadable, not a triangle mesh, holds
            non-finite coordinates or faces indexing missing vertices.
    """
    import trimesh

    if not (isinstance(dtype, torch.dtype) and dtype.is_floating_point):
        raise ValueError(f"dtype: expected a floating torch.dtype for the vertices, got {dtype!r}")
    path = Path(path)
    if path.is_dir():
        raise ValueError(f"{path}: is a folder, expected a mesh file")
    if not path.is_file():
        raise ValueError(f"{path}: mesh file not found")
    try:
        mesh = trimesh.load(path, process=False, maintain_order=True, force="mesh")
    except Exception as error:  # trimesh raises many types for corrupt files
        raise ValueError(f"{path}: cannot read mesh ({type(error).__name__}: {error})") from error
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.vertices) == 0 or len(mesh.faces) == 0:
        raise ValueError(f"{path}: not a triangle mesh with vertices and faces")
    points = np.asarray(mesh.vertices)
    if path.suffix.lower() == ".obj":
        points = _obj_trailing_vertices(path, points)
    vertices = torch.as_tensor(points, dtype=dtype)
    if not bool(torch.isfinite(vertices).all()):
        raise ValueError(f"{path}: mesh has NaN or infinite vertex coordinates")
    faces = torch.as_tensor(np.asarray(mesh.faces), dtype=torch.long)
    try:
        check_faces(faces, len(vertices), "faces")
    except ValueError as error:
        raise ValueError(f"{path}: {error}") from None
    return vertices, faces


def _obj_trailing_vertices(path: Path, points: np.ndarray) -> np.ndarray:
    """trimesh keeps an OBJ's vertex order but, with ``vt``/``vn`` lines, drops the vertices after the
    last one a face uses; read the ``v`` lines back so that a model's topology keeps all its vertices."""
    rows = []
    with open(path, "rb") as handle:
        for line in handle:
            if line.startswith(b"v ") or line.startswith(b"v\t"):
                rows.append([float(x) for x in line.split()[1:4]])
    if len(rows) <= len(points):
        return points
    full = np.asarray(rows, dtype=np.float64)
    if full.shape[1] != 3 or not np.allclose(full[: len(points)], points, rtol=0, atol=1e-6 * (1 + np.abs(points).max())):
        return points  # not the simple case: keep trimesh's reading
    return full
