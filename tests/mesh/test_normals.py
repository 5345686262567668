"""Tests for facenormals.mesh.normals: vertex normals of triangle meshes."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import trimesh

from facenormals.mesh import VertexNormals, vertex_normals
from tests.conftest import assert_close

MODES = ["ring", "area"]


# --- meshes -------------------------------------------------------------------------------------


def closed_mesh(subdivisions: int = 2, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """A perturbed icosphere: closed, every vertex has a closed ring."""
    sphere = trimesh.creation.icosphere(subdivisions=subdivisions)
    rng = np.random.default_rng(seed)
    vertices = sphere.vertices * rng.uniform(0.8, 1.2, (len(sphere.vertices), 1))
    vertices = vertices + 0.02 * rng.standard_normal(vertices.shape)
    return vertices, np.asarray(sphere.faces)


def open_sphere(seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """The perturbed icosphere with a cap and a band of faces removed: two holes, open rings."""
    vertices, faces = closed_mesh(seed=seed)
    centroids = vertices[faces].mean(1)
    keep = (centroids[:, 2] < 0.6) & (np.abs(centroids[:, 0]) > 0.15)
    return vertices, faces[keep]


def grid_patch(n: int = 6, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """A bumpy height field z = f(x, y) over an n x n grid, faces wound CCW seen from +z."""
    x, y = np.meshgrid(np.linspace(-1, 1, n), np.linspace(-1, 1, n), indexing="xy")
    rng = np.random.default_rng(seed)
    z = 0.3 * np.sin(2 * x) * np.cos(3 * y) + 0.05 * rng.standard_normal(x.shape)
    vertices = np.stack([x, y, z], -1).reshape(-1, 3)
    faces = []
    for i in range(n - 1):
        for j in range(n - 1):
            a, b, c, d = i * n + j, i * n + j + 1, (i + 1) * n + j, (i + 1) * n + j + 1
            faces += [[a, b, d], [a, d, c]]
    return vertices, np.asarray(faces)


MESHES = {"closed": closed_mesh, "open_sphere": open_sphere, "grid": grid_patch}


def as_torch(vertices: np.ndarray, faces: np.ndarray, dtype=torch.float64, device="cpu"):
    return (
        torch.as_tensor(vertices, dtype=dtype, device=device)[None],
        torch.as_tensor(faces, dtype=torch.long, device=device),
    )


# --- naive reference: the paper's estimator, one vertex at a time ---------------------------------


def ordered_fans(vertex: int, faces: np.ndarray) -> list[tuple[list[int], bool]]:
    """The one-ring of ``vertex`` as CCW-ordered fans, each with whether it is closed.

    Each incident face, rotated so that ``vertex`` comes first, ``(vertex, a, b)``, says that
    ``b`` follows ``a`` going CCW around the vertex. A manifold vertex has one fan: closed
    inside the mesh, open on a boundary, where it starts at the neighbour that follows no other
    one. (A vertex where two holes touch has several open fans.)
    """
    following: dict[int, int] = {}
    for face in faces:
        face = [int(i) for i in face]
        if vertex in face:
            k = face.index(vertex)
            a, b = face[(k + 1) % 3], face[(k + 2) % 3]
            assert a not in following, "non-manifold edge"
            following[a] = b
    fans = []
    while following:
        starts = set(following) - set(following.values())
        start = min(starts) if starts else min(following)
        ring = [start]
        while ring[-1] in following:
            nxt = following.pop(ring[-1])
            if nxt == start:
                break
            ring.append(nxt)
        fans.append((ring, not starts))
    return fans


def naive_ring_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    out = np.zeros_like(vertices)
    for v in range(len(vertices)):
        total = np.zeros(3)
        for ring, closed in ordered_fans(v, faces):
            pairs = list(zip(ring[:-1], ring[1:])) + ([(ring[-1], ring[0])] if closed else [])
            for a, b in pairs:
                c = np.cross(vertices[a] - vertices[v], vertices[b] - vertices[v])
                total += c / np.linalg.norm(c)
        norm = np.linalg.norm(total)
        out[v] = total / norm if norm > 0 else 0.0
    return out


def test_ordered_fans():
    faces = np.array([[0, 1, 2], [0, 2, 3], [0, 3, 1]])  # a closed fan around 0
    assert ordered_fans(0, faces) == [([1, 2, 3], True)]
    assert ordered_fans(0, faces[:2]) == [([1, 2, 3], False)]  # open: no pair (3, 1)
    assert ordered_fans(0, faces[[1, 2]]) == [([2, 3, 1], False)]
    assert ordered_fans(4, faces) == []


# --- against references ------------------------------------------------------------------------


@pytest.mark.parametrize("mesh", list(MESHES))
def test_ring_matches_naive_one_ring(mesh):
    vertices, faces = MESHES[mesh]()
    expected = naive_ring_normals(vertices, faces)
    v, f = as_torch(vertices, faces)
    assert_close(vertex_normals(v, f, mode="ring")[0], expected)
    closed = [all(c for _, c in ordered_fans(i, faces)) for i in range(len(vertices))]
    assert all(closed) == (mesh == "closed")  # the open meshes really have open rings


@pytest.mark.parametrize("mesh", list(MESHES))
def test_against_trimesh(mesh):
    vertices, faces = MESHES[mesh]()
    tm = trimesh.Trimesh(vertices, faces, process=False)
    v, f = as_torch(vertices, faces)
    # trimesh's Trimesh.vertex_normals is angle-weighted (checked in trimesh 5.2.0), so build the references
    # from mean_vertex_normals (normalised sum of the given face vectors) instead.
    area = trimesh.geometry.mean_vertex_normals(len(vertices), faces, tm.face_normals * tm.area_faces[:, None])
    ring = trimesh.geometry.mean_vertex_normals(len(vertices), faces, tm.face_normals)
    assert_close(vertex_normals(v, f, mode="area")[0], area)
    assert_close(vertex_normals(v, f, mode="ring")[0], ring)


def test_closed_mesh_normals_point_outwards():
    vertices, faces = closed_mesh()
    v, f = as_torch(vertices, faces)
    for mode in MODES:
        n = vertex_normals(v, f, mode=mode)[0]
        assert ((n * v[0]).sum(-1) > 0).all()


def test_ict_head(ict_npz):
    data = np.load(ict_npz)
    v = torch.from_numpy(np.asarray(data["mean"], dtype=np.float32))[None]
    f = torch.from_numpy(data["faces"])
    for mode in MODES:
        n = VertexNormals(f, v.shape[1], mode=mode)(v)
        assert_close(n, vertex_normals(v, f, mode=mode))
        assert torch.isfinite(n).all()
        used = torch.zeros(v.shape[1], dtype=torch.bool)
        used[f.long().reshape(-1)] = True
        assert_close(n[0, used].norm(dim=-1), torch.ones(int(used.sum())))
        # outwards on average: the eye sockets and the mouth cavity face inwards, the rest out
        outward = ((v[0] - v[0].mean(0)) * n[0]).sum(-1) > 0
        assert outward.float().mean() > 0.75


# --- edge cases ----------------------------------------------------------------------------------


@pytest.mark.parametrize("mode", MODES)
def test_isolated_and_degenerate(mode):
    vertices = torch.tensor(
        [[[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [2, 0, 0], [5, 5, 5], [9, 9, 9]]], dtype=torch.float64
    ).requires_grad_()
    # face 1 is collinear (zero area), face 2 repeats a vertex; vertex 5 is used by no face
    faces = torch.tensor([[0, 1, 2], [0, 1, 3], [4, 4, 0]])
    g = torch.Generator().manual_seed(0)
    for op in (lambda v: vertex_normals(v, faces, mode), VertexNormals(faces, 6, mode)):
        n = op(vertices)
        assert torch.isfinite(n).all()
        assert_close(n[0, [0, 1, 2]], torch.tensor([[0.0, 0, 1]] * 3, dtype=torch.float64))
        assert_close(n[0, 3:], torch.zeros(3, 3, dtype=torch.float64))
        (grad,) = torch.autograd.grad((n * torch.randn(n.shape, generator=g, dtype=n.dtype)).sum(), vertices)
        assert torch.isfinite(grad).all()


@pytest.mark.parametrize("mode", MODES)
def test_degenerate_faces_pass_no_gradient(mode):
    """Regression: at a vertex of a collinear face only, both normalisations sat on their eps clamp
    and the gradient was 6e24 (1/eps²) in ring mode, 1e12 in area mode; in ring mode a degenerate
    face beside good ones moved their gradients by rounding times 1/eps. Below eps, a normalisation
    now gives 0 and no gradient. (In area mode a degenerate face's area has a true derivative.)"""
    vertices = torch.tensor([[[0.0, 0, 0], [1, 0, 0], [2, 0, 0], [0, 1, 0], [1, 1, 0.5], [3, 0, 0]]],
                            dtype=torch.float64).requires_grad_()
    good = torch.tensor([[0, 1, 3], [1, 4, 3]])
    degenerate = torch.tensor([[1, 2, 5], [3, 4, 4]])  # collinear [1, 2, 5] alone at 2 and 5; [3, 4, 4] repeats
    faces = torch.cat([good, degenerate])
    weights = torch.randn(1, 6, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    for op in (lambda v: vertex_normals(v, faces, mode), VertexNormals(faces, 6, mode)):
        n = op(vertices)
        assert torch.equal(n[0, [2, 5]], torch.zeros(2, 3, dtype=torch.float64))
        (grad,) = torch.autograd.grad((n[:, [2, 5]] * weights[:, [2, 5]]).sum(), vertices, retain_graph=True)
        assert torch.equal(grad, torch.zeros_like(grad))
        if mode == "ring":
            (grad,) = torch.autograd.grad((n * weights).sum(), vertices)
            (reference,) = torch.autograd.grad((vertex_normals(vertices, good) * weights).sum(), vertices)
            assert torch.equal(grad, reference)


def test_empty_faces():
    v = torch.randn(2, 4, 3, generator=torch.Generator().manual_seed(0))
    faces = torch.zeros(0, 3, dtype=torch.long)
    assert torch.equal(vertex_normals(v, faces), torch.zeros(2, 4, 3))
    assert torch.equal(VertexNormals(faces, 4)(v), torch.zeros(2, 4, 3))


def test_int32_faces_and_default_num_vertices():
    vertices, faces = closed_mesh(1)
    v, f = as_torch(vertices, faces)
    module = VertexNormals(f.int())
    assert module.num_vertices == v.shape[1]
    assert_close(module(v), vertex_normals(v, f.int()))


# --- autograd, batching, dtype, device, compile --------------------------------------------------


@pytest.mark.parametrize("mode", MODES)
def test_gradcheck(mode):
    vertices, faces = closed_mesh(0)  # 12 vertices
    v, f = as_torch(vertices, faces)
    v = (v + 0.0).repeat(2, 1, 1).requires_grad_()
    torch.autograd.gradcheck(lambda x: vertex_normals(x, f, mode), (v,))
    torch.autograd.gradcheck(VertexNormals(f, mode=mode), (v,))


@pytest.mark.parametrize("mode", MODES)
def test_gradcheck_open_mesh(mode):
    v, f = as_torch(*grid_patch(4))
    torch.autograd.gradcheck(lambda x: vertex_normals(x, f, mode), (v.requires_grad_(),))


@pytest.mark.parametrize("mode", MODES)
def test_module_equals_function_and_batch(mode, dtype, device):
    vertices, faces = open_sphere()
    v, f = as_torch(vertices, faces, dtype, device)
    batch = torch.cat([v, v * 1.5 + 0.1, v.flip(-1)])  # flip(-1) mirrors: a different mesh
    module = VertexNormals(f.cpu(), v.shape[1], mode=mode).to(device)
    out = vertex_normals(batch, f, mode)
    assert out.dtype == dtype and out.device == batch.device and out.shape == batch.shape
    assert out.is_contiguous()
    assert_close(module(batch), out)
    for i in range(batch.shape[0]):
        assert_close(out[i : i + 1], vertex_normals(batch[i : i + 1], f, mode))
    # the batch matters: a mirrored mesh does not have the same normals
    assert not torch.allclose(out[0], out[2])


def test_module_buffers_follow_device_and_state_dict(device):
    f = torch.as_tensor(closed_mesh(0)[1])
    module = VertexNormals(f).to(device)
    assert module.corners.device.type == device.type
    assert module.state_dict() == {}
    assert "mode='ring'" in repr(module)


def test_compile_smoke():
    vertices, faces = closed_mesh(1)
    v, f = as_torch(vertices, faces, torch.float32)
    v = torch.cat([v, 1.1 * v])
    for mode in MODES:
        torch._dynamo.reset()
        compiled = torch.compile(vertex_normals, fullgraph=True)
        assert_close(compiled(v, f, mode), vertex_normals(v, f, mode))
        module = VertexNormals(f, mode=mode)
        assert_close(torch.compile(module, fullgraph=True)(v), module(v))


# --- input checks ------------------------------------------------------------------------------


def test_bad_inputs():
    v = torch.randn(1, 4, 3)
    faces = torch.tensor([[0, 1, 2], [0, 2, 3]])
    with pytest.raises(ValueError, match="vertices: expected shape"):
        vertex_normals(v[0], faces)  # wrong rank
    with pytest.raises(ValueError, match="vertices: expected shape"):
        vertex_normals(torch.randn(1, 4, 2), faces)  # wrong trailing dim
    with pytest.raises(ValueError, match="vertices: expected a floating-point"):
        vertex_normals(v.long(), faces)
    with pytest.raises(ValueError, match="vertices: expected a torch.Tensor"):
        vertex_normals(v.numpy(), faces)
    with pytest.raises(ValueError, match="faces: expected shape"):
        vertex_normals(v, faces[:, :2])
    with pytest.raises(ValueError, match="faces: expected shape"):
        vertex_normals(v, faces[None])
    with pytest.raises(ValueError, match=r"faces: expected vertex indices in \[0, 4\)"):
        vertex_normals(v, faces + 1)
    with pytest.raises(ValueError, match=r"faces: expected vertex indices in \[0, 4\)"):
        vertex_normals(v, faces - 1)
    with pytest.raises(ValueError, match="faces: expected an integer"):
        vertex_normals(v, faces.float())
    with pytest.raises(ValueError, match="faces: expected an integer"):
        vertex_normals(v, faces.bool())
    with pytest.raises(ValueError, match="mode: expected one of"):
        vertex_normals(v, faces, mode="angle")
    for eps in (float("nan"), -1e-12, 0.0, "1e-12"):  # NaN made every normal NaN
        with pytest.raises(ValueError, match="eps: expected a"):
            vertex_normals(v, faces, eps=eps)
        with pytest.raises(ValueError, match="eps: expected a"):
            VertexNormals(faces, eps=eps)
    with pytest.raises(ValueError, match="mode: expected one of"):
        VertexNormals(faces, mode="Ring")
    with pytest.raises(ValueError, match="faces: expected an integer"):
        VertexNormals(faces.double())
    with pytest.raises(ValueError, match=r"faces: expected vertex indices in \[0, 3\)"):
        VertexNormals(faces, num_vertices=3)
    module = VertexNormals(faces)
    with pytest.raises(ValueError, match="vertices: expected shape"):
        module(torch.randn(1, 5, 3))  # N differs from the module's
    with pytest.raises(ValueError, match="vertices: expected shape"):
        module(torch.randn(4, 3))


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
@pytest.mark.parametrize("mode", ["ring", "area"])
@pytest.mark.parametrize("edge", [20.0, 300.0])
def test_half_precision_normals_of_head_sized_faces(dtype, mode, edge):
    """Edges of 20 mm: the squared norm of the face normal (1.6e5) would overflow float16; of 300 mm
    (a head's span), the cross product itself (9e4): the normals were NaN."""
    vertices = torch.tensor([[[0.0, 0, 0], [edge, 0, 0], [0, edge, 0]]], dtype=dtype)
    normals = vertex_normals(vertices, torch.tensor([[0, 1, 2]]), mode=mode)
    assert normals.dtype == dtype
    assert_close(normals.float(), torch.tensor([[[0.0, 0, 1]] * 3]), atol=1e-3, rtol=0)


def test_non_finite_vertices_are_named():
    """Regression: a NaN vertex spread NaN normals over its ring, silently (documented as never NaN)."""
    from facenormals.mesh import VertexNormalsJacobian, vertex_normals_jvp

    vertices = torch.tensor([[[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]]])
    faces = torch.tensor([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    bad = vertices.clone()
    bad[0, 3, 1] = float("nan")
    tangents = torch.ones(2, 4, 3)
    for call in (lambda v: vertex_normals(v, faces), VertexNormals(faces), lambda v: vertex_normals_jvp(v, faces, tangents),
                 VertexNormalsJacobian(faces, tangents), VertexNormalsJacobian(faces, tangents).subset(torch.tensor([0]))):
        call(vertices)
        with pytest.raises(ValueError, match="vertices: expected finite values, got 1 NaN or infinite entries"):
            call(bad)
    with pytest.raises(ValueError, match="tangents: expected finite values"):
        vertex_normals_jvp(vertices, faces, tangents * float("inf"))
    with pytest.raises(ValueError, match="basis: expected finite values"):
        VertexNormalsJacobian(faces, tangents * float("nan"))
