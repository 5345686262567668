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
