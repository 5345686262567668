"""Reading and writing triangle meshes (``.ply``, ``.obj``, ... through trimesh)."""

from __future__ import annotations

import codecs
import io
import json
import re
import struct
import warnings
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
        faces: ``(F, 3)`` integer triangles indexing ``vertices``, ``F >= 1``.

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
    if faces.shape[0] == 0:  # load_mesh would refuse the file
        raise ValueError(f"faces: expected at least one triangle, got shape {tuple(faces.shape)}")
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

    Binary little-endian ``.ply`` files of triangles and ``.obj`` files of faces (what
    :func:`save_mesh` and most tools write; polygons are split on the diagonals trimesh uses) are read
    directly, without importing trimesh (about half a second); anything else (polygon PLY, ASCII
    PLY, other formats) is read and triangulated by trimesh. (An OBJ with several ``usemtl``
    materials keeps its vertices as in the file; trimesh duplicates them per material.)

    Example:
        >>> import tempfile, os
        >>> path = save_mesh(os.path.join(tempfile.mkdtemp(), "t.obj"), torch.eye(3), torch.tensor([[0, 1, 2]]))
        >>> vertices, faces = load_mesh(path)
        >>> vertices.shape, faces.tolist()
        (torch.Size([3, 3]), [[0, 1, 2]])

    Raises:
        ValueError: naming the file when it is missing, unreadable, not a triangle mesh, holds
            non-finite coordinates, faces indexing missing vertices or face indices of a float
            type, (ASCII PLY) a data line whose numbers do not fit the header's properties, (OFF) a
            byte that is not ASCII, lines that do not match the header's counts or a polygon line
            that does not match its corner count, (OBJ) a byte that is not ASCII in a vertex or face
            line, or (GLB) a damaged container: its header, chunk lengths, or a JSON chunk that is
            not UTF-8 JSON or names a property glTF 2.0 does not define for a mesh's objects.
    """
    if not (isinstance(dtype, torch.dtype) and dtype.is_floating_point):
        raise ValueError(f"dtype: expected a floating torch.dtype for the vertices, got {dtype!r}")
    path = Path(path)
    if path.is_dir():
        raise ValueError(f"{path}: is a folder, expected a mesh file")
    if not path.is_file():
        raise ValueError(f"{path}: mesh file not found")
    suffix = path.suffix.lower()
    read_directly = {".ply": _read_triangle_ply, ".obj": _read_obj}.get(suffix)
    arrays = read_directly(path) if read_directly is not None else None
    if arrays is None:
        points, triangles = _read_with_trimesh(path)
    else:
        points, triangles = arrays
    if len(points) == 0 or len(triangles) == 0:
        raise ValueError(f"{path}: not a triangle mesh with vertices and faces")
    if points.ndim != 2 or points.shape[1] != 3:  # trimesh reads "v x y" lines as 2-D points
        raise ValueError(f"{path}: expected vertices of 3 coordinates, got an array of shape {points.shape}")
    vertices = torch.as_tensor(points, dtype=dtype)
    if not bool(torch.isfinite(vertices).all()):
        raise ValueError(f"{path}: mesh has NaN or infinite vertex coordinates")
    faces = torch.as_tensor(triangles, dtype=torch.long)
    try:
        check_faces(faces, len(vertices), "faces")
    except ValueError as error:
        raise ValueError(f"{path}: {error}") from None
    return vertices, faces


def _read_with_trimesh(path: Path) -> tuple[np.ndarray, np.ndarray]:
    import trimesh

    suffix = path.suffix.lower()
    source: Path | io.BytesIO = path
    if suffix == ".ply":
        _check_ply(path)
    elif suffix == ".glb":
        _check_glb(path)
    elif suffix == ".off":
        text, num_vertices, num_triangles = _check_off(path)
        source = io.BytesIO(text)
    try:
        mesh = trimesh.load(source, file_type=None if source is path else "off", process=False,
                            maintain_order=True, force="mesh")
    except Exception as error:  # trimesh raises many types for corrupt files
        raise ValueError(f"{path}: cannot read mesh ({type(error).__name__}: {error})") from error
    if not isinstance(mesh, trimesh.Trimesh):
        raise ValueError(f"{path}: not a triangle mesh with vertices and faces")
    if suffix == ".off" and (len(mesh.vertices), len(mesh.faces)) != (num_vertices, num_triangles):
        raise ValueError(f"{path}: the OFF file holds {num_vertices} vertices and {num_triangles} triangles, "
                         f"trimesh read {len(mesh.vertices)} and {len(mesh.faces)}")
    points = np.asarray(mesh.vertices)
    if suffix == ".obj" and len(points):
        points = _obj_trailing_vertices(path, points)
    return points, np.asarray(mesh.faces)


def _first_non_ascii(data: bytes) -> str:
    """``"byte 0x.. at column n"`` for the first byte of ``data`` that is not ASCII."""
    column = next(i for i, byte in enumerate(data) if byte >= 0x80)
    return f"byte 0x{data[column]:02x} at column {column + 1}"


#: The OFF keywords whose vertex lines start with ``x y z`` (then texture coordinates, a colour, a
#: normal); trimesh would read the ``4OFF`` and ``nOFF`` variants (other dimensions) wrongly.
_OFF_KEYWORD = re.compile(r"(ST)?C?N?OFF")
_NUMBER_TEXT = re.compile(r"[+-]?(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][+-]?[0-9]+)?")
_INTEGER_TEXT = re.compile(r"[+-]?[0-9]+")


def _check_off(path: Path) -> tuple[bytes, int, int]:
    """Refuse what trimesh reads silently wrong in an OFF file; return the file's data lines without
    comments (for trimesh to read: a comment after the first line made it read lines twice) and the
    numbers of vertices and triangles it must read from them.

    trimesh dropped bytes that are not ASCII (``938\\xc9`` read as 938), skipped a polygon line whose
    indices do not match its corner count (``3 5646!5649 1441``) and ignored the face lines missing
    from a file cut short (1,716 faces read where the header announced 20,480)."""
    with open(path, "rb") as file:
        data = file.read()
    if data.startswith(codecs.BOM_UTF8):
        data = data[len(codecs.BOM_UTF8):]
    rows: list[tuple[int, list[str]]] = []  # (line number, words) of each line holding data
    for number, line in enumerate(data.split(b"\n"), 1):
        content = line.split(b"#", 1)[0]
        if not content.isascii():
            raise ValueError(f"{path}: line {number}: expected ASCII text, got {_first_non_ascii(content)} in "
                             f"{line.decode(errors='replace').strip()[:80]!r}")
        for piece in content.decode("ascii").splitlines():  # also at "\r", "\v", "\f", as trimesh
            if piece.split():
                rows.append((number, piece.split()))
    keyword = rows[0][1][0] if rows else ""
    if not _OFF_KEYWORD.fullmatch(keyword):
        raise ValueError(f"{path}: expected an OFF file starting with the keyword OFF (or COFF, NOFF, STOFF, ...), "
                         f"got {keyword[:40]!r}")
    if len(rows[0][1]) > 1:  # "OFF 8 12 0"
        number, counts, body = rows[0][0], rows[0][1][1:], rows[1:]
    elif len(rows) > 1:
        number, counts, body = rows[1][0], rows[1][1], rows[2:]
    else:
        raise ValueError(f"{path}: the OFF file ends before its vertex and face counts")
    if not 2 <= len(counts) <= 3 or not all(word.isdigit() for word in counts):
        raise ValueError(f"{path}: line {number}: expected the numbers of vertices, faces (and edges), got "
                         f"{' '.join(counts)[:80]!r}")
    num_vertices, num_faces = int(counts[0]), int(counts[1])
    if len(body) != num_vertices + num_faces:
        found = min(len(body), num_vertices)
        raise ValueError(f"{path}: the OFF header announces {num_vertices} vertices and {num_faces} faces, the "
                         f"file holds {found} vertex lines and {len(body) - found} face lines")
    width = len(body[0][1]) if num_vertices else 3  # x y z, and as many more numbers on every line
    for number, words in body[:num_vertices]:
        if len(words) != width or width < 3 or not all(_NUMBER_TEXT.fullmatch(word) for word in words):
            expected = f"{width} numbers like the first one" if width >= 3 else "at least 3 numbers"
            raise ValueError(f"{path}: line {number}: expected a vertex of {expected}, got {' '.join(words)[:80]!r}")
    num_triangles = 0
    for number, words in body[num_vertices:]:
        corners = int(words[0]) if words[0].isdigit() else 0
        if corners < 3 or len(words) <= corners or not all(_INTEGER_TEXT.fullmatch(w) for w in words[1 : corners + 1]):
            raise ValueError(f"{path}: line {number}: expected a polygon: its number of corners (3 or more), then "
                             f"as many vertex indices, got {' '.join(words)[:80]!r}")
        num_triangles += corners - 2
    lines = [keyword, " ".join(counts)] + [" ".join(words) for _, words in body]
    return ("\n".join(lines) + "\n").encode("ascii"), num_vertices, num_triangles


#: The properties the glTF 2.0 schema defines for the objects trimesh builds a mesh from: trimesh
#: ignores any other, so a damaged name (``"indhces"``) silently takes the default (no indices).
_GLTF_PROPERTIES = {
    "accessors": {"bufferView", "byteOffset", "componentType", "normalized", "count", "type", "max", "min",
                  "sparse", "name"},
    "bufferViews": {"buffer", "byteOffset", "byteLength", "byteStride", "target", "name"},
    "meshes": {"primitives", "weights", "name"},
    "nodes": {"camera", "children", "skin", "matrix", "mesh", "rotation", "scale", "translation", "weights", "name"},
}  # fmt: skip
_GLTF_PRIMITIVE_PROPERTIES = {"attributes", "indices", "material", "mode", "targets"}


def _check_glb(path: Path) -> None:
    """Refuse a GLB file whose container trimesh would read silently wrong: a JSON chunk that is not
    UTF-8 (trimesh drops the bytes: ``"indi\\x9ces"`` read as a primitive without indices, 3,414
    triangles instead of 20,480), a declared length other than the file's, chunks that do not fill
    it. An unknown property name in an accessor, buffer view, mesh, primitive or node is warned
    about (RuntimeWarning naming the file): glTF lets exporters add their own, but a damaged name
    (``"indhces"``) is read as absent."""
    size = path.stat().st_size
    with open(path, "rb") as file:
        head = file.read(20)
        if len(head) < 20 or head[:4] != b"glTF":
            raise ValueError(f"{path}: not a GLB file (expected the magic bytes b'glTF' and a 20-byte header, got "
                             f"{head[:4]!r} in a file of {size} bytes)")
        version, length, json_length = struct.unpack("<3I", head[4:16])
        if version != 2:
            raise ValueError(f"{path}: expected a GLB file of glTF version 2, got version {version}")
        if length != size:
            raise ValueError(f"{path}: the GLB header declares {length} bytes, the file holds {size} "
                             "(truncated or damaged)")
        if head[16:20] != b"JSON":
            raise ValueError(f"{path}: expected the first GLB chunk to be of type b'JSON', got {head[16:20]!r}")
        position = 20 + json_length
        if position > size:
            raise ValueError(f"{path}: the GLB JSON chunk declares {json_length} bytes, beyond the end of the file")
        chunk = file.read(json_length)
        while position < size:  # the other chunks (BIN): an 8-byte header (length, type), then the data
            file.seek(position)
            chunk_head = file.read(8)
            chunk_length = struct.unpack("<I", chunk_head[:4])[0] if len(chunk_head) == 8 else size
            if position + 8 + chunk_length > size:
                raise ValueError(f"{path}: the GLB chunk at byte {position} runs beyond the end of the file")
            position += 8 + chunk_length
    try:
        document = json.loads(chunk.decode("utf-8"))
    except UnicodeDecodeError as error:
        raise ValueError(f"{path}: the GLB JSON chunk is not UTF-8 text (byte 0x{chunk[error.start]:02x} at "
                         f"offset {20 + error.start})") from None
    except json.JSONDecodeError as error:
        raise ValueError(f"{path}: the GLB JSON chunk is not valid JSON ({error})") from None
    if not isinstance(document, dict):
        raise ValueError(f"{path}: expected a JSON object in the GLB JSON chunk, got {type(document).__name__}")
    for kind, known in _GLTF_PROPERTIES.items():
        items = document.get(kind)
        for index, item in enumerate(items if isinstance(items, list) else ()):
            objects = [(f"{kind}[{index}]", item, known)]
            if kind == "meshes" and isinstance(item, dict) and isinstance(item.get("primitives"), list):
                objects += [(f"{kind}[{index}].primitives[{i}]", primitive, _GLTF_PRIMITIVE_PROPERTIES)
                            for i, primitive in enumerate(item["primitives"])]
            for where, obj, names in objects:
                unknown = sorted(set(obj) - names - {"extensions", "extras"}) if isinstance(obj, dict) else []
                if unknown:
                    warnings.warn(f"{path}: the GLB JSON gives {where} the unknown propert"
                                  f"{'ies' if len(unknown) > 1 else 'y'} {', '.join(map(repr, unknown))}, which "
                                  "the reader ignores (a damaged name? glTF 2.0 defines no such one)", RuntimeWarning,
                                  stacklevel=4)


#: PLY scalar type names and their little-endian numpy types.
_PLY_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "<i2", "int16": "<i2",
              "ushort": "<u2", "uint16": "<u2", "int": "<i4", "int32": "<i4", "uint": "<u4", "uint32": "<u4",
              "float": "<f4", "float32": "<f4", "double": "<f8", "float64": "<f8"}
_PLY_INTEGERS = {name for name, code in _PLY_TYPES.items() if code[-2] in "iu"}
_INTEGER = re.compile(rb"[+-]?[0-9]+")


def _ply_header(header: str) -> tuple[list[str], list[tuple[str, int, list[list[str]]]]] | None:
    """The format line's words and the elements ``(name, count, properties)`` of a PLY header (its
    text before ``end_header``), each property as its words after ``property``; ``None`` if a line
    is none of these."""
    lines = [line.split() for line in header.splitlines()[1:]]
    lines = [line for line in lines if line and line[0] not in ("comment", "obj_info")]
    if not lines or lines[0][0] != "format":
        return None
    elements: list[tuple[str, int, list[list[str]]]] = []
    for line in lines[1:]:
        if line[0] == "element" and len(line) == 3 and line[2].isdigit():
            elements.append((line[1], int(line[2]), []))
        elif line[0] == "property" and elements:
            elements[-1][2].append(line[1:])
        else:
            return None
    return lines[0], elements


def _check_index_types(path: Path, face_property: list[str]) -> None:
    """Refuse a face list whose count or indices have a float type: read as integers, truncated."""
    if face_property[0] == "list" and len(face_property) == 4 and not set(face_property[1:3]) <= _PLY_INTEGERS:
        raise ValueError(f"{path}: expected integer face indices, got 'property {' '.join(face_property)}'")


def _check_ply(path: Path) -> None:
    """Refuse what trimesh reads silently wrong: face indices of a float type, and in an ASCII PLY a
    body of more or fewer lines than the header counts (trimesh ignores the rest) or a line whose
    numbers do not fit its element's properties (``4 0 1 2`` read as ``0 1 2``, an index ``1.9`` as 1)."""
    with open(path, "rb") as file:
        head = file.read(65536)
    end = head.find(b"end_header")
    parsed = _ply_header(head[:end].decode("ascii", "replace")) if head.startswith(b"ply") and end >= 0 else None
    if parsed is None:
        return  # trimesh's errors
    form, elements = parsed
    for name, _, properties in elements:
        for face_property in properties if name == "face" else ():
            if len(properties) == 1 or face_property[-1] in ("vertex_indices", "vertex_index"):  # trimesh's faces
                _check_index_types(path, face_property)
    if form[1:2] != ["ascii"]:
        return  # binary: trimesh checks its length
    with open(path, "rb") as file:
        body = file.read().split(b"end_header", 1)[1].splitlines()[1:]
    first = head[:end].count(b"\n") + 2  # the line number of body[0]
    rows = [(number, line.split()) for number, line in enumerate(body, first) if line.strip()]
    total = sum(count for _, count, _ in elements)
    if len(rows) != total:
        raise ValueError(f"{path}: the PLY header announces {total} data lines, the file holds {len(rows)}")
    start = 0
    for _, count, properties in elements:
        for number, words in rows[start : start + count]:
            problem = _ascii_row_problem(words, properties)
            if problem is not None:
                line = b" ".join(words).decode(errors="replace")
                raise ValueError(f"{path}: line {number}: expected {problem}, got {line!r}")
        start += count


def _ascii_row_problem(words: list[bytes], properties: list[list[str]]) -> str | None:
    """What the numbers ``words`` of an ASCII PLY line lack to fit ``properties``; ``None`` if they do."""
    at = 0
    for prop in properties:
        if prop[0] == "list":
            if at == len(words) or not words[at].isdigit():
                return f"a list length for property {prop[-1]!r}"
            kind, size = prop[2], int(words[at])
            at += 1
        else:
            kind, size = prop[0], 1
        values = words[at : at + size]
        if len(values) < size:
            return f"{size} number(s) for property {prop[-1]!r}"
        if kind in _PLY_INTEGERS and not all(_INTEGER.fullmatch(value) for value in values):
            return f"integers for property {prop[-1]!r}"
        at += size
    return None if at == len(words) else f"{at} numbers"


def _read_triangle_ply(path: Path) -> tuple[np.ndarray, np.ndarray] | None:
    """A binary little-endian PLY of one vertex element (with ``x``, ``y``, ``z`` among scalar
    properties) then one face element of one list property of triangles; ``None`` for any other
    PLY, which trimesh then reads."""
    with open(path, "rb") as file:
        data = file.read()
    end = data.find(b"end_header\n", 0, 65536)
    if not data.startswith(b"ply\n") or end < 0:
        return None
    body = end + len(b"end_header\n")
    parsed = _ply_header(data[:end].decode("ascii", "replace"))
    if parsed is None or parsed[0] != ["format", "binary_little_endian", "1.0"]:
        return None
    elements = parsed[1]
    if [name for name, _, _ in elements] != ["vertex", "face"]:
        return None
    (_, num_vertices, vertex_properties), (_, num_faces, face_properties) = elements
    if any(len(p) != 2 or p[0] not in _PLY_TYPES for p in vertex_properties):
        return None
    if len({name for _, name in vertex_properties}) != len(vertex_properties):
        return None  # a property named twice
    vertex_type = np.dtype([(name, _PLY_TYPES[kind]) for kind, name in vertex_properties])
    if not {"x", "y", "z"} <= set(vertex_type.names or ()) or len(face_properties) != 1:
        return None
    face_property = face_properties[0]
    if len(face_property) != 4 or face_property[0] != "list":
        return None
    _check_index_types(path, face_property)
    count_kind, index_kind = face_property[1:3]
    if count_kind not in _PLY_TYPES or index_kind not in _PLY_TYPES:
        return None
    face_type = np.dtype([("count", _PLY_TYPES[count_kind]), ("indices", _PLY_TYPES[index_kind], (3,))])
    if len(data) - body != num_vertices * vertex_type.itemsize + num_faces * face_type.itemsize:
        return None  # polygons other than triangles, or a damaged file: trimesh's reading and errors
    vertex_records = np.frombuffer(data, vertex_type, num_vertices, body)
    face_records = np.frombuffer(data, face_type, num_faces, body + num_vertices * vertex_type.itemsize)
    if not np.all(face_records["count"] == 3):
        return None
    points = np.stack([vertex_records[c].astype(np.float64) for c in "xyz"], axis=1)
    return points, face_records["indices"].astype(np.int64)


#: OBJ statements that carry no triangle geometry, which the direct reader skips.
_OBJ_SKIPPED = {b"vt", b"vn", b"vp", b"o", b"g", b"s", b"usemtl", b"mtllib"}


def _read_obj(path: Path) -> tuple[np.ndarray, np.ndarray] | None:
    """An OBJ of faces (``f a b c ...``, ``a/t/n``, ``a//n``, negative indices counting back from the
    last vertex), polygons split into the triangles trimesh makes of them (a quad ``a b c d`` into
    ``a b c`` and ``c d a``, larger ones into a fan around the first corner), listed polygon by
    polygon (trimesh lists the first triangles of all quads, then the second); ``None`` for anything
    else (lines, line continuations, numbers that are not plain decimals), which trimesh then reads.
    Unlike trimesh, the vertices stay those of the ``v`` lines when several materials share them."""
    with open(path, "rb") as file:
        data = file.read()
    vertex_rows, face_rows = [], []
    for number, line in enumerate(data.splitlines(), 1):
        content = line.split(b"#", 1)[0]  # a comment may hold anything, e.g. "# vertex_0"
        words = content.split()
        if not words:
            continue
        if words[-1].endswith(b"\\"):
            return None  # continued on the next line
        key = words[0]
        if not content.isascii() and (key in (b"v", b"f") or not key.isascii()):
            # trimesh drops the byte: "f 39\xc67" read as vertex 397, not an error
            raise ValueError(f"{path}: line {number}: expected ASCII text in a vertex or face line, got "
                             f"{_first_non_ascii(content)} in {line.decode(errors='replace').strip()[:80]!r}")
        if key in (b"v", b"f") and b"_" in content:
            return None  # "1_0" parses as 10
        if key == b"v":
            if not 4 <= len(words) <= 8:  # x y z, then w or r g b (or w r g b)
                return None
            vertex_rows.append(words[1:])
        elif key == b"f":
            if len(words) < 4:  # trimesh would drop it silently, e.g. a file cut short in its last line
                raise ValueError(f"{path}: a face line with fewer than 3 vertices: {line.decode(errors='replace')!r}")
            corners = [word.split(b"/", 1)[0] for word in words[1:]]
            if b"-" in content:  # relative indices: -1 is the last vertex so far
                try:
                    corners = [c if int(c) > 0 else str(len(vertex_rows) + int(c) + 1).encode() for c in corners]
                except ValueError:
                    return None
            if len(corners) == 3:
                face_rows.append(corners)
            elif len(corners) == 4:
                face_rows += [corners[:3], [corners[2], corners[3], corners[0]]]
            else:
                face_rows += [[corners[0], corners[i], corners[i + 1]] for i in range(1, len(corners) - 1)]
        elif key not in _OBJ_SKIPPED:
            return None  # lines, curves, ...
    try:
        values = np.array([word for row in vertex_rows for word in row], dtype=np.float64)  # all numbers
        lengths = np.fromiter(map(len, vertex_rows), np.int64, len(vertex_rows))
        points = values[(np.cumsum(lengths) - lengths)[:, None] + np.arange(3)]  # x y z of each line
        triangles = np.array(face_rows, dtype=np.int64).reshape(-1, 3)
    except (ValueError, OverflowError):
        return None  # not numbers: trimesh's reading and errors
    if triangles.size and triangles.min() < 1:  # trimesh would read index 0 as the last vertex
        raise ValueError(f"{path}: a face refers to vertex index 0 or to one before the first vertex "
                         "(OBJ indices start at 1; negative ones count back from the last vertex)")
    return points, triangles - 1


def _obj_trailing_vertices(path: Path, points: np.ndarray) -> np.ndarray:
    """trimesh keeps an OBJ's vertex order but, with ``vt``/``vn`` lines, drops the vertices after the
    last one a face uses; read the ``v`` lines back so that a model's topology keeps all its vertices."""
    rows = []
    with open(path, "rb") as handle:
        for number, line in enumerate(handle, 1):
            if line.startswith(b"v ") or line.startswith(b"v\t"):
                try:
                    row = [float(x) for x in line.split()[1:4]]
                except ValueError:
                    row = []
                if len(row) != 3:
                    raise ValueError(f"{path}: line {number}: expected a vertex of 3 numbers, got "
                                     f"{line.decode(errors='replace').strip()!r}")
                rows.append(row)
    if len(rows) <= len(points):
        return points
    full = np.asarray(rows, dtype=np.float64)
    if not np.allclose(full[: len(points)], points, rtol=0, atol=1e-6 * (1 + np.abs(points).max())):
        return points  # not the simple case: keep trimesh's reading
    return full
