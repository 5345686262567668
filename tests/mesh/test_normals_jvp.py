import pytest
import torch
import trimesh

from facenormals.mesh import VertexNormalsJacobian, vertex_normals, vertex_normals_jvp
from facenormals.models import builtin_head_model
from tests.conftest import assert_close


def open_mesh(dtype=torch.float64):
    sphere = trimesh.creation.icosphere(subdivisions=2)
    faces = torch.as_tensor(sphere.faces[10:], dtype=torch.long)  # holes: boundary vertices
    g = torch.Generator().manual_seed(0)
    v = torch.as_tensor(sphere.vertices, dtype=dtype) * (1 + 0.1 * torch.rand(len(sphere.vertices), 1, generator=g, dtype=dtype))
    return v, faces


@pytest.mark.parametrize("shared", [True, False])
def test_matches_autograd_jvp(shared):
    v, faces = open_mesh()
    g = torch.Generator().manual_seed(1)
    vertices = torch.stack([v, v * 1.1 + 0.05])  # B = 2
    tangents = torch.randn((4, *v.shape) if shared else (2, 4, *v.shape), generator=g, dtype=torch.float64)
    n, dn = vertex_normals_jvp(vertices, faces, tangents)
    assert_close(n, vertex_normals(vertices, faces))
    for k in range(4):
        t = tangents[k].expand_as(vertices) if shared else tangents[:, k]
        _, ref = torch.func.jvp(lambda x: vertex_normals(x, faces), (vertices,), (t,))
        assert_close(dn[..., k], ref, rtol=1e-8, atol=1e-10)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_a_degenerate_face_adds_no_normal(dtype):
    """A face ``[a, b, b]`` has no normal in vertex_normals (its cross product is exactly 0); the jvp
    path agrees (torch.linalg.cross left ~1e-5 there in float32, which the normalisation turned into
    a unit normal in an arbitrary direction). Derivatives: see the next test."""
    g = torch.Generator().manual_seed(1)
    vertices = torch.randn(1, 4, 3, generator=g, dtype=dtype) * 50
    tangents = torch.randn(2, 4, 3, generator=g, dtype=dtype)
    faces = torch.tensor([[0, 1, 2], [1, 3, 3]])
    n, dn = vertex_normals_jvp(vertices, faces, tangents)
    reference = vertex_normals(vertices, faces)
    assert torch.equal(reference[0, 3], torch.zeros(3, dtype=dtype))  # used by the degenerate face alone
    tolerance = dict(rtol=1e-4, atol=1e-5) if dtype == torch.float32 else dict(rtol=1e-10, atol=1e-12)
    assert_close(n, reference, **tolerance)
    for k in range(2):
        _, ref = torch.func.jvp(lambda x: vertex_normals(x, faces), (vertices,), (tangents[k].expand_as(vertices),))
        assert_close(dn[:, [0, 2], :, k], ref[:, [0, 2]], **tolerance)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_a_degenerate_face_has_the_derivative_of_autograd(dtype):
    """Regression: at a face ``[a, b, b]`` autograd's ċ is exactly 0, the analytic sum of four products
    left rounding noise, divided by |c| clamped at eps: 2.7e5 in float32 beside derivatives below 1.
    A face or vertex sum below eps now has no derivative, in both (vertex 4 is in such a face only)."""
    vertices = torch.tensor([[[0.0, 0, 0], [10, 0, 1], [0, 10, 2], [10, 10, 0], [5, 5, 5]]], dtype=dtype)
    faces = torch.tensor([[0, 1, 2], [1, 3, 2], [0, 1, 1], [4, 2, 4]])
    tangents = torch.randn(3, 5, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64).to(dtype)
    _, dn = vertex_normals_jvp(vertices, faces, tangents)
    _, subset_dn = VertexNormalsJacobian(faces, tangents).subset(torch.arange(5))(vertices)
    tolerance = dict(rtol=1e-5, atol=1e-6) if dtype == torch.float32 else dict(rtol=1e-10, atol=1e-12)
    for k in range(3):
        _, ref = torch.func.jvp(lambda x: vertex_normals(x, faces), (vertices,), (tangents[k][None],))
        assert_close(dn[..., k], ref, **tolerance)
        assert_close(subset_dn[..., k], ref, **tolerance)
    assert torch.equal(dn[0, 4], torch.zeros_like(dn[0, 4]))


def test_module_on_a_model_matches_finite_differences():
    model = builtin_head_model(dtype=torch.float64)
    jac = VertexNormalsJacobian(model.faces, model.shape_basis[:3])
    y = 0.5 * model.shape_std[None].clone()
    n, dn = jac(model(y))
    h = 1e-6
    for k in range(3):
        step = torch.zeros_like(y)
        step[0, k] = h
        fd = (vertex_normals(model(y + step), model.faces) - vertex_normals(model(y - step), model.faces)) / (2 * h)
        assert_close(dn[..., k], fd, rtol=1e-5, atol=1e-6)
    assert "components=3" in repr(jac)


def test_float32_and_bad_input():
    v, faces = open_mesh(torch.float32)
    n, dn = vertex_normals_jvp(v[None], faces, torch.ones(2, *v.shape))
    assert n.dtype == dn.dtype == torch.float32 and dn.shape == (1, *v.shape, 2)
    with pytest.raises(ValueError, match=r"tangents: expected shape \(K, 162, 3\)"):
        vertex_normals_jvp(v[None], faces, torch.ones(2, 5, 3))
    with pytest.raises(ValueError, match="vertices"):
        vertex_normals_jvp(v, faces, torch.ones(2, *v.shape))
    with pytest.raises(ValueError, match="eps: expected a finite number > 0, got 0"):
        vertex_normals_jvp(v[None], faces, torch.ones(2, *v.shape), eps=0)
    with pytest.raises(ValueError, match="eps: expected a finite number, got nan"):
        VertexNormalsJacobian(faces, torch.ones(2, *v.shape), eps=float("nan"))


def test_faces_and_vertex_count_are_checked():
    """Faces out of range or of a float dtype, and vertices of another mesh, are named errors rather
    than an IndexError from the gather or a silently truncated face list."""
    v, faces = open_mesh(torch.float64)
    tangents = torch.ones(2, *v.shape, dtype=torch.float64)
    bad = faces.clone()
    bad[0, 0] = v.shape[0]
    with pytest.raises(ValueError, match=rf"faces: expected vertex indices in \[0, {v.shape[0]}\)"):
        vertex_normals_jvp(v[None], bad, tangents)
    with pytest.raises(ValueError, match=rf"faces: expected vertex indices in \[0, {v.shape[0]}\)"):
        VertexNormalsJacobian(bad, tangents)
    with pytest.raises(ValueError, match="faces: expected an integer tensor"):
        VertexNormalsJacobian(faces.double() + 0.9, tangents)
    jac = VertexNormalsJacobian(faces, tangents)
    with pytest.raises(ValueError, match=rf"vertices: expected shape \(B, {v.shape[0]}, 3\), got \(1, {v.shape[0] + 1}, 3\)"):
        jac(torch.cat([v, v[:1]])[None])


def test_subset_rows_match_the_full_jacobian_for_any_index():
    """Arbitrary order, repeats, and a vertex in no face (zero normal, zero rows)."""
    v, faces = open_mesh()
    unused = torch.tensor([[0.3, 0.2, 0.1]], dtype=torch.float64)
    vertices = torch.cat([v, unused])[None].expand(2, -1, -1) * torch.tensor([1.0, 1.2], dtype=torch.float64)[:, None, None]
    g = torch.Generator().manual_seed(3)
    basis = torch.randn(3, vertices.shape[1], 3, generator=g, dtype=torch.float64)
    jac = VertexNormalsJacobian(faces, basis)
    full_n, full_dn = jac(vertices)
    index = torch.tensor([40, 7, 40, v.shape[0], 0, 7])
    n, dn = jac.subset(index)(vertices)
    assert_close(n, full_n[:, index])
    assert_close(dn, full_dn[:, index])
    assert float(n[:, 3].abs().max()) == 0.0 and float(dn[:, 3].abs().max()) == 0.0
    empty = jac.subset(index)(vertices[:0])
    assert empty[0].shape == (0, 6, 3) and empty[1].shape == (0, 6, 3, 3)


def test_subset_checks_its_index_and_vertices():
    v, faces = open_mesh()
    jac = VertexNormalsJacobian(faces, torch.ones(2, *v.shape, dtype=torch.float64))
    with pytest.raises(ValueError, match=r"vertex_index: expected vertex indices in \[0, 162\), got values in \[-1, 3\]"):
        jac.subset(torch.tensor([3, -1]))
    with pytest.raises(ValueError, match=r"vertex_index: expected vertex indices in \[0, 162\), got values in \[5, 162\]"):
        jac.subset(torch.tensor([5, 162]))
    with pytest.raises(ValueError, match="vertex_index: expected an integer tensor"):
        jac.subset(torch.tensor([1.7]))
    with pytest.raises(ValueError, match=r"vertices: expected shape \(B, 162, 3\), got \(1, 3, 3\)"):
        jac.subset(torch.tensor([1]))(v[None, :3])


def test_values_for_vertices_that_require_grad_and_empty_batches():
    v, faces = open_mesh()
    tangents = torch.randn(2, *v.shape, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    n, dn = vertex_normals_jvp(v[None].requires_grad_(), faces, tangents)
    assert not n.requires_grad and not dn.requires_grad
    assert_close(n, vertex_normals(v[None], faces))
    n, dn = vertex_normals_jvp(v.new_zeros(0, *v.shape), faces, tangents)
    assert n.shape == (0, *v.shape) and dn.shape == (0, *v.shape, 2)
    n, dn = VertexNormalsJacobian(faces, tangents)(v.new_zeros(0, *v.shape))
    assert dn.shape == (0, *v.shape, 2)
    with pytest.raises(ValueError, match="tangents: expected a torch.Tensor"):
        vertex_normals_jvp(v[None], faces, tangents.tolist())


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
def test_half_precision_gives_zero_normals_at_unused_vertices(dtype):
    """The norms' eps clamp is 0 in half precision: computed in float32, an unused vertex keeps the
    zero normal (and Jacobian) of vertex_normals instead of 0/0."""
    vertices = torch.tensor([[[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [5, 5, 5]]])
    faces = torch.tensor([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    tangents = torch.randn(2, 5, 3, generator=torch.Generator().manual_seed(0))
    n, dn = vertex_normals_jvp(vertices.to(dtype), faces, tangents.to(dtype))
    assert n.dtype == dtype and dn.dtype == dtype
    assert torch.isfinite(n).all() and torch.isfinite(dn).all()
    assert (n[0, 4] == 0).all() and (dn[0, 4] == 0).all()
    n32, dn32 = vertex_normals_jvp(vertices, faces, tangents)
    assert_close(n.float(), n32, atol=1e-2, rtol=1e-2)
    assert_close(dn.float(), dn32, atol=3e-2, rtol=3e-2)


@pytest.mark.parametrize("vertex_dtype, basis_dtype", [(torch.float32, torch.float64), (torch.float64, torch.float32),
                                                       (torch.float32, torch.float16)])
def test_mixed_float_dtypes_are_refused(vertex_dtype, basis_dtype):
    """Regression: float32 vertices with float64 tangents (or a float64 basis) were silently rounded,
    where the rest of the library raises ValueError for mixed dtypes."""
    v, faces = open_mesh(vertex_dtype)
    basis = torch.ones(2, *v.shape, dtype=basis_dtype)
    with pytest.raises(ValueError, match=f"tangents: expected dtype {vertex_dtype} \\(the dtype of vertices\\), got {basis_dtype}"):
        vertex_normals_jvp(v[None], faces, basis)
    with pytest.raises(ValueError, match=f"tangents: expected dtype {vertex_dtype} \\(the dtype of vertices\\), got {basis_dtype}"):
        vertex_normals_jvp(v[None], faces, basis[None])
    jac = VertexNormalsJacobian(faces, basis)
    match = f"vertices: expected dtype {basis_dtype} \\(the dtype of the module's basis\\), got {vertex_dtype}"
    with pytest.raises(ValueError, match=match):
        jac(v[None])
    with pytest.raises(ValueError, match=match):
        jac.subset(torch.tensor([0, 3]))(v[None])
    n, dn = jac.to(vertex_dtype)(v[None])  # a converted module takes them
    assert n.dtype == dn.dtype == vertex_dtype
    assert jac.subset(torch.tensor([0, 3]))(v[None])[1].dtype == vertex_dtype
