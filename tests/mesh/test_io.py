import re
import struct

import pytest
import torch

from facenormals.mesh import load_mesh, save_mesh
from facenormals.models import builtin_head_model


@pytest.mark.parametrize("suffix", [".ply", ".obj"])
def test_round_trip_keeps_vertex_order(tmp_path, suffix):
    model = builtin_head_model()
    path = save_mesh(tmp_path / f"head{suffix}", model.mean[None], model.faces)
    vertices, faces = load_mesh(path)
    assert torch.allclose(vertices, model.mean, atol=1e-4)
    assert torch.equal(faces, model.faces)


def test_model_export(tmp_path):
    model = builtin_head_model()
    model.export_mesh(tmp_path / "mean.obj")
    model.export_mesh(tmp_path / "sample.ply", model.shape_std)
    v, _ = load_mesh(tmp_path / "sample.ply")
    assert torch.allclose(v, model(model.shape_std[None])[0], atol=1e-4)


def test_errors_name_the_file(tmp_path):
    with pytest.raises(ValueError, match="missing.ply: mesh file not found"):
        load_mesh(tmp_path / "missing.ply")
    with pytest.raises(ValueError, match="is a folder, expected a mesh file"):
        load_mesh(tmp_path)
    bad = tmp_path / "bad.ply"
    bad.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 100\nproperty float x\nend_header\n\x00\x01")
    with pytest.raises(ValueError, match="bad.ply"):
        load_mesh(bad)
    with pytest.raises(ValueError, match=r"vertices: expected shape \(N, 3\)"):
        save_mesh(tmp_path / "x.ply", torch.zeros(4, 2), torch.tensor([[0, 1, 2]]))


@pytest.mark.parametrize("suffix", [".ply", ".obj", ".off"])
def test_unused_vertices_and_their_order_survive_a_round_trip(tmp_path, suffix):
    vertices = torch.tensor([[5.0, 5, 5], [0, 0, 0], [1, 0, 0], [0, 1, 0], [9, 9, 9], [0, 0, 1]])
    faces = torch.tensor([[3, 1, 2], [1, 5, 2]])  # vertices 0 and 4 are in no face
    loaded_vertices, loaded_faces = load_mesh(save_mesh(tmp_path / f"m{suffix}", vertices, faces))
    assert torch.equal(loaded_vertices, vertices)
    assert torch.equal(loaded_faces, faces)


def test_faces_must_index_the_vertices(tmp_path):
    vertices = torch.rand(6, 3)
    with pytest.raises(ValueError, match=r"faces: expected vertex indices in \[0, 6\), got values in \[0, 10\]"):
        save_mesh(tmp_path / "b.ply", vertices, torch.tensor([[0, 1, 10]]))
    with pytest.raises(ValueError, match="faces: expected an integer tensor"):
        save_mesh(tmp_path / "f.ply", vertices, torch.tensor([[0.7, 1.2, 2.9]]))
    assert list(tmp_path.iterdir()) == []
    bad = tmp_path / "bad.ply"
    bad.write_text("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n"
                   "element face 2\nproperty list uchar int vertex_indices\nend_header\n0 0 0\n1 0 0\n0 1 0\n"
                   "3 0 1 2\n3 0 1 9\n")
    with pytest.raises(ValueError, match=r"bad.ply: faces: expected vertex indices in \[0, 3\), got values in \[0, 9\]"):
        load_mesh(bad)
    # OBJ indices start at 1: trimesh reads a 0 as the last vertex, a degenerate triangle, silently
    for name, face in (("zero.obj", "f 0 1 2"), ("before_first.obj", "f 1 2 -4")):
        path = tmp_path / name
        path.write_text("v 0 0 0\nv 1 0 0\nv 1 1 0\n" + face + "\n")
        with pytest.raises(ValueError, match=name + ": a face refers to vertex index 0 or to one before the first"):
            load_mesh(path)
    with pytest.raises(ValueError, match=r"faces: expected at least one triangle, got shape \(0, 3\)"):
        save_mesh(tmp_path / "empty.ply", vertices, torch.zeros(0, 3, dtype=torch.long))  # load_mesh refuses it
    assert not (tmp_path / "empty.ply").exists()


def test_load_mesh_dtype_must_be_floating(tmp_path):
    path = save_mesh(tmp_path / "m.ply", torch.eye(3), torch.tensor([[0, 1, 2]]))
    with pytest.raises(ValueError, match="dtype: expected a floating torch.dtype"):
        load_mesh(path, dtype=torch.int64)
    assert load_mesh(path, dtype=torch.float64)[0].dtype == torch.float64


def test_obj_with_normals_keeps_its_trailing_unused_vertices(tmp_path):
    path = tmp_path / "other_tool.obj"
    path.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 1 1 0\nv 9 9 9\nvn 0 0 1\nf 1//1 2//1 3//1\nf 2//1 4//1 3//1\n")
    vertices, faces = load_mesh(path)
    assert vertices.shape == (5, 3) and vertices[4].tolist() == [9.0, 9.0, 9.0]
    assert faces.tolist() == [[0, 1, 2], [1, 3, 2]]


def test_save_mesh_refuses_point_formats_and_nan(tmp_path):
    vertices, faces = torch.eye(3), torch.tensor([[0, 1, 2]])
    with pytest.raises(ValueError, match=r"x.xyz: expected a mesh file name ending in one of .ply, .obj, .off, .glb, "
                                         r".stl, got '.xyz'"):
        save_mesh(tmp_path / "x.xyz", vertices, faces)
    with pytest.raises(ValueError, match="no suffix"):
        save_mesh(tmp_path / "mesh", vertices, faces)
    with pytest.raises(ValueError, match="vertices: expected finite values, got 1 NaN"):
        save_mesh(tmp_path / "x.ply", torch.tensor([[0.0, 0, 0], [1, 0, float("nan")], [0, 1, 0]]), faces)
    assert not list(tmp_path.iterdir())  # nothing written


def test_ply_is_binary_little_endian_with_the_documented_layout(tmp_path):
    import numpy as np

    vertices = torch.tensor([[1.5, -2.25, 3.0], [0.1, 0.2, 0.3], [7.0, 8.0, 9.0], [1e-3, 1e5, -4.0]],
                            dtype=torch.float64)
    faces = torch.tensor([[0, 1, 2], [2, 3, 0]])
    data = save_mesh(tmp_path / "m.ply", vertices, faces).read_bytes()
    header, body = data.split(b"end_header\n", 1)
    assert b"format binary_little_endian 1.0" in header and b"element vertex 4" in header
    assert b"element face 2" in header and b"property list uchar int vertex_indices" in header
    points = np.frombuffer(body[: 4 * 24], "<f8").reshape(4, 3)
    assert (points == vertices.numpy()).all()  # float64 coordinates: exact
    records = np.frombuffer(body[4 * 24 :], [("n", "u1"), ("i", "<i4", (3,))])
    assert (records["n"] == 3).all() and (records["i"] == faces.numpy()).all()


def test_obj_text_is_exact_for_float32_and_one_based(tmp_path):
    g = torch.Generator().manual_seed(0)
    vertices = torch.randn(50, 3, generator=g) * 100
    faces = torch.randint(0, 50, (20, 3), generator=g)
    path = save_mesh(tmp_path / "m.obj", vertices, faces)
    lines = path.read_text().splitlines()
    v = torch.tensor([[float(x) for x in line.split()[1:]] for line in lines if line.startswith("v ")])
    f = torch.tensor([[int(x) for x in line.split()[1:]] for line in lines if line.startswith("f ")])
    assert torch.equal(v.float(), vertices) and torch.equal(f - 1, faces)
    assert torch.equal(load_mesh(path)[0], vertices)


def test_writing_and_reading_ply_and_obj_does_not_import_trimesh(tmp_path):
    # trimesh's import costs about half a second of every `facenormals reconstruct` and `evaluate`
    import subprocess
    import sys

    code = ("import sys, torch; from facenormals.mesh import load_mesh, save_mesh; "
            f"save_mesh({str(tmp_path / 'a.ply')!r}, torch.eye(3), torch.tensor([[0, 1, 2]])); "
            f"save_mesh({str(tmp_path / 'a.obj')!r}, torch.eye(3), torch.tensor([[0, 1, 2]])); "
            f"load_mesh({str(tmp_path / 'a.ply')!r}); load_mesh({str(tmp_path / 'a.obj')!r}); "
            "print('trimesh' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "False"


def _trimesh_reading(path):
    import trimesh

    mesh = trimesh.load(path, process=False, maintain_order=True, force="mesh")
    return torch.as_tensor(mesh.vertices, dtype=torch.float64), torch.as_tensor(mesh.faces, dtype=torch.long)


_OBJ_VARIANTS = {
    "plain": "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 1 1 0.5\nf 1 2 3\nf 2 4 3\n",
    "texture and normal indices": ("# made by another tool\nmtllib m.mtl\no head\nv 0 0 0\nv 1 0 0\nv 0 1 0\n"
                                   "v 1 1 0.5\nvt 0 0\nvt 1 0\nvt 0 1\nvn 0 0 1\ng part\nusemtl skin\ns 1\n"
                                   "f 1/1/1 2/2/1 3/3/1\nf 2/2/1 4/1/1 3/3/1\n"),
    "normal indices only": "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 1 1 0.5\nvn 0 0 1\nf 1//1 2//1 3//1\nf 2//1 4//1 3//1\n",
    "vertex colours": "v 0 0 0 1 0 0\nv 1 0 0 0 1 0\nv 0 1 0 0 0 1\nv 1 1 0.5 1 1 1\nf 1 2 3\nf 2 4 3\n",
    "windows line ends": "v 0 0 0\r\nv 1 0 0\r\nv 0 1 0\r\nv 1 1 0.5\r\nf 1 2 3\r\nf 2 4 3\r\n",
    "a quad": "v 0 0 0\nv 1 0 0\nv 1 1 0.5\nv 0 1 0\nf 1 2 3 4\n",
    "a pentagon": "v 0 0 0\nv 1 0 0\nv 2 1 0\nv 1 2 0\nv 0 1 0\nf 1 2 3 4 5\n",
    "relative indices": "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 1 1 0.5\nf -4 -3 -2\nf -3 -1 -2\nf 1 -3 3\n",
}


def test_polygons_of_several_materials_keep_the_files_vertices(tmp_path):
    """Regression: such files went to trimesh, which copies the vertices per material (the raw
    ICT-FaceKit OBJ, 26,719 v lines and 12 materials, read as 257,701 vertices), so a mesh in a model's
    topology lost its vertex order."""
    path = tmp_path / "two.obj"
    path.write_text("v 0 0 0\nv 100 0 0\nv 100 100 0\nv 0 100 0\nv 0 0 100\nv 100 0 100\n"
                    "usemtl a\nf 1 2 3 4\nusemtl b\nf 1/1 2/1 6/1 5/1\n")
    vertices, faces = load_mesh(path, dtype=torch.float64)
    assert vertices.shape == (6, 3) and vertices[5].tolist() == [100.0, 0.0, 100.0]
    assert faces.tolist() == [[0, 1, 2], [2, 3, 0], [0, 1, 5], [5, 4, 0]]
    # a relative index counts back from the last vertex read so far (trimesh counts from the file's end)
    path.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf -3 -2 -1\nv 1 1 0.5\nf -3 -1 -2\n")
    assert load_mesh(path)[1].tolist() == [[0, 1, 2], [1, 3, 2]]


def test_ply_reading_agrees_with_trimesh(tmp_path):
    import trimesh

    model = builtin_head_model()
    mesh = trimesh.Trimesh(model.mean.double().numpy() + 0.123456789, model.faces.numpy(), process=False)
    mesh.visual.vertex_colors = [200, 150, 100, 255]  # more vertex properties than x y z
    variants = {"binary float32 with colours": mesh.export(file_type="ply"),  # trimesh writes float32 x y z
                "ascii": mesh.export(file_type="ply", encoding="ascii"),
                "ours": save_mesh(tmp_path / "ours.ply", model.mean.double() + 0.123456789, model.faces).read_bytes()}
    for name, data in variants.items():
        path = tmp_path / f"{name}.ply"
        path.write_bytes(data)
        vertices, faces = load_mesh(path, dtype=torch.float64)
        reference_vertices, reference_faces = _trimesh_reading(path)
        assert torch.equal(vertices, reference_vertices), name
        assert torch.equal(faces, reference_faces), name


def test_a_quad_ply_is_triangulated_and_a_truncated_one_is_named(tmp_path):
    header = ("ply\nformat binary_little_endian 1.0\nelement vertex 4\nproperty float x\nproperty float y\n"
              "property float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n").encode()
    points = torch.tensor([[0.0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]]).numpy().tobytes()
    quad = bytes([4]) + torch.tensor([0, 1, 2, 3], dtype=torch.int32).numpy().tobytes()
    path = tmp_path / "quad.ply"
    path.write_bytes(header + points + quad)
    vertices, faces = load_mesh(path)
    assert vertices.shape == (4, 3) and faces.shape == (2, 3)
    assert torch.equal(faces, _trimesh_reading(path)[1])
    path.write_bytes(header + points[:-5])
    with pytest.raises(ValueError, match="quad.ply"):
        load_mesh(path)


_MALFORMED = {  # files the direct readers must not read differently from trimesh (which fails on most)
    "ragged vertex lines.obj": b"v 0 0 0 1\nv 1 0\nv 0 1 0\nf 1 2 3\n",
    "two vertices on one line.obj": b"v 0 0 0 v 1 0 0\nv 0 1 0\nv 1 1 1\nf 1 2 3\n",
    "junk after a vertex.obj": b"v 0 0 0 junk\nv 1 0 0\nv 0 1 0\nf 1 2 3\n",
    "digit separators.obj": b"v 1_0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n",
    "an index too large.obj": b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 99999999999999999999\n",
    "a property named twice.ply": (b"ply\nformat binary_little_endian 1.0\nelement vertex 3\nproperty float x\n"
                                   b"property float x\nproperty float z\nelement face 1\n"
                                   b"property list uchar int vertex_indices\nend_header\n" + bytes(36)
                                   + bytes([3]) + bytes(12)),
}


@pytest.mark.parametrize("name", list(_MALFORMED))
def test_malformed_files_are_never_read_differently_from_trimesh(tmp_path, name):
    path = tmp_path / name
    path.write_bytes(_MALFORMED[name])
    try:
        reference = _trimesh_reading(path)
    except Exception:  # noqa: BLE001 - trimesh refuses it: so must load_mesh, naming the file
        reference = None
    if reference is None or reference[0].shape[1:] != (3,):
        with pytest.raises(ValueError, match=re.escape(name)):
            load_mesh(path, dtype=torch.float64)
        return
    try:
        vertices, faces = load_mesh(path, dtype=torch.float64)
    except ValueError as error:
        assert name in str(error)
        return
    assert torch.equal(vertices, reference[0]) and torch.equal(faces, reference[1])


def test_an_obj_with_comments_after_data_reads_its_numbers(tmp_path):
    path = tmp_path / "commented.obj"
    path.write_text("v 0 0 0 # origin\nv 1e0 0 0 # vertex_1\nv 0 1.0E+0 0\nf 1 2 3 # one triangle, face_0\n")
    vertices, faces = load_mesh(path)
    assert vertices.tolist() == [[0, 0, 0], [1, 0, 0], [0, 1, 0]] and faces.tolist() == [[0, 1, 2]]


_PLY_HEADER = (b"ply\nformat %s 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n"
               b"element face 1\nproperty list uchar %s vertex_indices\nend_header\n")


@pytest.mark.parametrize("name, data, match", [
    ("float indices.ply", _PLY_HEADER % (b"binary_little_endian", b"float") + bytes(36)
     + struct.pack("<B3f", 3, 0, 1, 1.9), "expected integer face indices, got 'property list uchar float vertex_indices'"),
    ("float indices big endian.ply", _PLY_HEADER % (b"binary_big_endian", b"double") + bytes(36)
     + struct.pack(">B3d", 3, 0, 1, 1.9), "expected integer face indices, got 'property list uchar double vertex_ind"),
    ("float indices ascii.ply", _PLY_HEADER % (b"ascii", b"float") + b"0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n",
     "expected integer face indices, got 'property list uchar float vertex_indices'"),
    ("fractional index.ply", _PLY_HEADER % (b"ascii", b"int") + b"0 0 0\n1 0 0\n0 1 0\n3 0 1 1.9\n",
     "line 13: expected integers for property 'vertex_indices', got '3 0 1 1.9'"),
    ("count beyond indices.ply", _PLY_HEADER % (b"ascii", b"int") + b"0 0 0\n1 0 0\n0 1 0\n4 0 1 2\n",
     "line 13: expected 4 number(s) for property 'vertex_indices', got '4 0 1 2'"),
    ("shifted number.ply", _PLY_HEADER % (b"ascii", b"int") + b"0 0 0 1\n1 0\n0 1 0\n3 0 1 2\n",
     "line 10: expected 3 numbers, got '0 0 0 1'"),
    ("short face.obj", b"v 0 0 0\nv 1 0 0\nv 0 1 0\nv 1 1 0\nf 2 4 3\nf 1 2", "a face line with fewer than 3 vertices"),
    ("short trailing vertex.obj", b"v 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\nf 1/1 2/1 3/1\nv 4 5 6\nv 7 8\n",
     "line 7: expected a vertex of 3 numbers, got 'v 7 8'"),
    ("extra data.ply", b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
     b"property float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n"
     b"0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n3 2 1 0\n9 9\n", "the PLY header announces 4 data lines, the file holds 6"),
])
def test_damage_that_trimesh_reads_silently_is_named(tmp_path, name, data, match):
    """trimesh dropped a face line cut short, ignored data lines beyond an ASCII PLY's counts, and a
    short trailing vertex line failed inside numpy without the file's name; float face indices were
    truncated (0, 1, 1.9 read as 0, 1, 1), and an ASCII line's numbers were taken whatever its list
    length said (``4 0 1 2`` read as the triangle 0 1 2)."""
    path = tmp_path / name
    path.write_bytes(data)
    with pytest.raises(ValueError, match=re.escape(f"{path}: ") + ".*" + re.escape(match)):
        load_mesh(path)


def _head_file(tmp_path, suffix):
    """The built-in head (10,242 vertices, 20,480 triangles) written by save_mesh: its bytes."""
    model = builtin_head_model()
    return save_mesh(tmp_path / f"head{suffix}", model.mean, model.faces).read_bytes()


@pytest.mark.parametrize("suffix", [".off", ".glb", ".stl"])
def test_the_head_survives_a_round_trip_through_trimesh_formats(tmp_path, suffix):
    model = builtin_head_model()
    vertices, faces = load_mesh(save_mesh(tmp_path / f"head{suffix}", model.mean, model.faces))
    if suffix == ".stl":  # unindexed triangles: the corners, three per face
        assert torch.allclose(vertices[faces], model.mean[model.faces], atol=1e-4)
        return
    assert torch.allclose(vertices, model.mean, atol=1e-4) and torch.equal(faces, model.faces)


_OFF_VARIANTS = {
    "plain": "OFF\n4 2 0\n0 0 0\n1 0 0\n0 1 0\n1 1 0.5\n3 0 1 2\n3 1 3 2\n",
    "counts on the keyword line": "OFF 4 2 0\n0 0 0\n1 0 0\n0 1 0\n1 1 0.5\n3 0 1 2\n3 1 3 2\n",
    "no edge count": "OFF\n4 2\n0 0 0\n1 0 0\n0 1 0\n1 1 0.5\n3 0 1 2\n3 1 3 2\n",
    "comments and blank lines first": "# made by another tool\n\nOFF\n# counts\n4 2 0\n\n0 0 0\n1 0 0\n0 1 0\n"
                                      "1 1 0.5\n3 0 1 2\n3 1 3 2\n",
    "windows line ends": "OFF\r\n4 2 0\r\n0 0 0\r\n1 0 0\r\n0 1 0\r\n1 1 0.5\r\n3 0 1 2\r\n3 1 3 2\r\n",
    "quads and triangles": "OFF\n6 3 0\n0 0 0\n1 0 0\n2 1 0\n1 2 0\n0 1 0\n3 3 3\n4 0 1 2 3\n3 0 1 5\n4 1 2 5 4\n",
    "vertex and face colours": ("COFF\n4 2 0\n0 0 0 255 0 0 255\n1 0 0 0 255 0 255\n0 1 0 0 0 255 255\n"
                                "1 1 0.5 9 9 9 255\n3 0 1 2 0.5 0.5 0.5\n3 1 3 2 1 0 0\n"),
    "signed and exponent numbers": "OFF\n3 1 0\n-1.5e+1 +0.25 .5\n1E-3 2. -0\n0 1 0\n3 0 1 2\n",
}


@pytest.mark.parametrize("suffix,variant", [(".obj", v) for v in _OBJ_VARIANTS] + [(".off", v) for v in _OFF_VARIANTS])
def test_reading_agrees_with_trimesh(tmp_path, suffix, variant):
    path = tmp_path / f"m{suffix}"
    path.write_bytes({".obj": _OBJ_VARIANTS, ".off": _OFF_VARIANTS}[suffix][variant].encode())
    vertices, faces = load_mesh(path, dtype=torch.float64)
    reference_vertices, reference_faces = _trimesh_reading(path)
    assert torch.equal(vertices, reference_vertices)
    assert torch.equal(faces, reference_faces)


def test_an_off_comment_after_the_first_line_does_not_shift_the_data(tmp_path):
    """Regression: trimesh strips comments by copying the text before the first '#' twice when that
    text spans lines, so the counts line was read again as a vertex and the faces shifted away
    (``4 2 0 # counts`` read a vertex (4, 2, 0) and dropped the last face)."""
    path = tmp_path / "commented.off"
    path.write_text("OFF\n4 2 0 # counts\n0 0 0\n1 0 0\n0 1 0 # third\n1 1 0.5\n3 0 1 2\n3 1 3 2  # last face\n")
    vertices, faces = load_mesh(path)
    assert vertices.tolist() == [[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0.5]]
    assert faces.tolist() == [[0, 1, 2], [1, 3, 2]]


def _edit_line(number, edit):
    """A damage that replaces line ``number`` (from 1) of a file by ``edit(line)``."""
    def damage(data):
        lines = data.split(b"\n")
        lines[number - 1] = edit(lines[number - 1])
        return b"\n".join(lines)
    return damage


# the head's OFF file: line 1 "OFF", line 2 "10242 20480 0", lines 3 to 10244 vertices, then faces "3 i j k"
_DAMAGED_OFF = {
    "cut in the faces": (lambda data: b"\n".join(data.split(b"\n")[: 2 + 10242 + 1716]) + b"\n",
                         "the OFF header announces 10242 vertices and 20480 faces, the file holds 10242 vertex "
                         "lines and 1716 face lines"),
    "a face count too large": (lambda data: data.replace(b"10242 20480 0", b"10242 21480 0", 1),
                               "the OFF header announces 10242 vertices and 21480 faces, the file holds 10242 vertex "
                               "lines and 20480 face lines"),
    "a space flipped to '!'": (_edit_line(10252, lambda line: line.replace(b" ", b"!", 2).replace(b"!", b" ", 1)),
                               "line 10252: expected a polygon: its number of corners (3 or more), then as many "
                               "vertex indices, got '3 "),
    "a corner count of 4 with 3 indices": (_edit_line(10248, lambda line: b"4" + line[1:]),
                                           "line 10248: expected a polygon"),
    "a non-ASCII byte in a coordinate": (_edit_line(102, lambda line: line.replace(b".", b".\xc8", 1)),
                                         "line 102: expected ASCII text, got byte 0xc8 at column"),
    "a non-ASCII byte in a face index": (_edit_line(10345, lambda line: line[:-1] + b"\xc9"),
                                         "line 10345: expected ASCII text, got byte 0xc9 at column"),
    "a vertex split in two": (_edit_line(43, lambda line: line.replace(b".", b" ", 1)),
                              "line 43: expected a vertex of 3 numbers like the first one, got"),
}


@pytest.mark.parametrize("damage", list(_DAMAGED_OFF))
def test_damaged_off_files_are_named(tmp_path, damage):
    """trimesh read these without an error: the faces of a file cut short dropped (1,716 of 20,480),
    a polygon line whose indices do not match its corner count skipped or cut, a byte that is not
    ASCII dropped from its number ('-96.1808\\xc800562' read as -96.180800562, '938\\xc9' as 938), a
    face count beyond the file's faces ignored."""
    damaged, match = _DAMAGED_OFF[damage]
    path = tmp_path / "head.off"
    path.write_bytes(damaged(_head_file(tmp_path, ".off")))
    with pytest.raises(ValueError, match=re.escape(f"{path}: {match}")):
        load_mesh(path)


# the head's OBJ file: line 1 "# facenormals", lines 2 to 10243 vertices "v x y z", then faces "f i j k"
_NON_ASCII_OBJ = {
    "in a face index": (_edit_line(12605, lambda line: b"f 39\xc67 1026 3994" if line == b"f 3997 1026 3994" else line),
                        "line 12605: expected ASCII text in a vertex or face line, got byte 0xc6 at column 5 in "
                        "'f 39\ufffd7 1026 3994'"),
    "in a coordinate": (_edit_line(101, lambda line: line[:-2] + b"\xc8" + line[-1:]),
                        "line 101: expected ASCII text in a vertex or face line, got byte 0xc8"),
    "in the keyword of a vertex line": (_edit_line(50, lambda line: b"\x89" + line[1:]),
                                        "line 50: expected ASCII text in a vertex or face line, got byte 0x89 at "
                                        "column 1"),
}


@pytest.mark.parametrize("where", list(_NON_ASCII_OBJ))
def test_a_byte_that_is_not_ascii_in_obj_geometry_is_named(tmp_path, where):
    """Regression: the direct reader gave such a file to trimesh, which dropped the byte ('f 39\\xc67'
    read as vertex 397 instead of 3997) or the line (a vertex, shifting all later ones), no error."""
    damage, match = _NON_ASCII_OBJ[where]
    data = _head_file(tmp_path, ".obj")
    assert b"\nf 3997 1026 3994\n" in data
    path = tmp_path / "head.obj"
    path.write_bytes(damage(data))
    assert path.read_bytes() != data
    with pytest.raises(ValueError, match=re.escape(f"{path}: {match}")):
        load_mesh(path)


def test_obj_names_and_comments_may_be_utf8(tmp_path):
    path = tmp_path / "named.obj"
    path.write_text("# tête, modélisée\no tête\nmtllib matériaux.mtl\nusemtl peau_éclairée\ng joue\n"
                    "v 0 0 0 # l'origine\nv 1 0 0\nv 0 1 0\nf 1 2 3 # première face\n", encoding="utf-8")
    vertices, faces = load_mesh(path)
    assert vertices.tolist() == [[0, 0, 0], [1, 0, 0], [0, 1, 0]] and faces.tolist() == [[0, 1, 2]]


def _glb_json_offset(data: bytes) -> tuple[int, int]:
    """Where the JSON chunk of a GLB file starts and ends."""
    return 20, 20 + struct.unpack("<I", data[12:16])[0]


_DAMAGED_GLB = {
    "invalid UTF-8 in the JSON": (lambda data: data.replace(b'"indices"', b'"indi\x9ces"', 1),
                                  "the GLB JSON chunk is not UTF-8 text (byte 0x9c at offset "),
    "bytes appended": (lambda data: data + bytes(8), "the GLB header declares 369400 bytes, the file holds 369408"),
    "cut short": (lambda data: data[:-100], "the GLB header declares 369400 bytes, the file holds 369300"),
    "a damaged magic": (lambda data: b"glTX" + data[4:], "not a GLB file (expected the magic bytes b'glTF'"),
    "version 1": (lambda data: data[:4] + struct.pack("<I", 1) + data[8:],
                  "expected a GLB file of glTF version 2, got version 1"),
    "a first chunk that is not JSON": (lambda data: data[:16] + b"BIN\x00" + data[20:],
                                       "expected the first GLB chunk to be of type b'JSON', got b'BIN\\x00'"),
    "a JSON chunk beyond the file": (lambda data: data[:12] + struct.pack("<I", len(data)) + data[16:],
                                     "the GLB JSON chunk declares 369400 bytes, beyond the end of the file"),
    "a binary chunk beyond the file": (lambda data: data[: _glb_json_offset(data)[1]]
                                       + struct.pack("<I", len(data)) + data[_glb_json_offset(data)[1] + 4 :],
                                       "the GLB chunk at byte "),
    "invalid JSON": (lambda data: data.replace(b'"indices":', b'"indices";', 1),
                     "the GLB JSON chunk is not valid JSON"),
}


@pytest.mark.parametrize("name,warning", [
    (b'"indhces"', "the GLB JSON gives meshes[0].primitives[0] the unknown property 'indhces', which the reader ignores"),
    (b'"byteOffsed"', "the GLB JSON gives bufferViews[1] the unknown property 'byteOffsed', which the reader ignores"),
])
def test_unknown_glb_property_names_are_warned_about(tmp_path, name, warning):
    """A damaged name ("indhces") was read as absent without a word (3,414 unindexed triangles instead
    of 20,480 indexed ones); glTF lets exporters add properties of their own, so it is a warning."""
    data = _head_file(tmp_path, ".glb")
    original = b'"indices"' if b"indhces" in name else b'"byteOffset":245760'
    replacement = name if b"indhces" in name else b'"byteOffsed":245760'
    path = tmp_path / "head.glb"
    path.write_bytes(data.replace(original, replacement, 1))
    with pytest.warns(RuntimeWarning, match=re.escape(f"{path}: {warning}")):
        load_mesh(path)


@pytest.mark.parametrize("damage", list(_DAMAGED_GLB))
def test_damaged_glb_files_are_named(tmp_path, damage):
    """Regression: trimesh dropped the bytes of a JSON chunk that is not UTF-8 and took a damaged
    property name for an absent one: both read the head's 20,480 indexed triangles as 3,414
    unindexed ones, no error; it also ignored bytes beyond the declared length."""
    damaged, match = _DAMAGED_GLB[damage]
    data = _head_file(tmp_path, ".glb")
    assert len(data) == 369400 and b'"indices"' in data and b'"byteOffset":245760' in data
    path = tmp_path / "head.glb"
    path.write_bytes(damaged(data))
    assert path.read_bytes() != data
    with pytest.raises(ValueError, match=re.escape(f"{path}: {match}")):
        load_mesh(path)
