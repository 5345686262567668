"""The ring-normal derivative blocks equal the forward-mode derivatives of the whole mesh."""

import pytest
import torch

from facenormals.fitting.rings import Rings, _compact
from facenormals.mesh import VertexNormalsJacobian, vertex_normals
from facenormals.models import builtin_head_model


def test_blocks_times_basis_equal_the_normal_jacobian():
    model = builtin_head_model(dtype=torch.float64)
    y = torch.randn(2, model.num_shape, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    verts = model(y)
    N = verts.shape[1]
    sets = [torch.arange(0, N, 7), torch.arange(3, N, 5)]  # a different subset per batch element
    rings = Rings.cat([Rings.build(model.faces, s, N) for s in sets], N)
    normals, blocks = rings.normals_and_blocks(verts.reshape(-1, 3))
    flat = torch.cat([s + b * N for b, s in enumerate(sets)])
    torch.testing.assert_close(normals, vertex_normals(verts, model.faces).reshape(-1, 3)[flat])
    torch.testing.assert_close(rings.normals(verts.reshape(-1, 3)), normals)
    basis = model.shape_basis.permute(1, 2, 0)  # (N, 3, K)
    dn = torch.zeros(rings.num_slots, 3, model.num_shape, dtype=torch.float64)
    dn.index_add_(0, rings.block_slot, blocks @ basis[rings.block_vertex % N])
    reference = VertexNormalsJacobian(model.faces, model.shape_basis)(verts)[1]
    torch.testing.assert_close(dn, reference.reshape(-1, 3, model.num_shape)[flat], rtol=1e-10, atol=1e-12)


def test_ring_normals_ignore_a_degenerate_face_as_vertex_normals_does():
    """A face ``[a, b, b]`` adds nothing to its corners' ring normals, as in vertex_normals."""
    g = torch.Generator().manual_seed(1)
    verts = torch.randn(1, 5, 3, generator=g) * 50
    faces = torch.tensor([[0, 1, 2], [1, 3, 4], [1, 4, 4]])
    rings = Rings.build(faces, torch.arange(5), 5)
    reference = vertex_normals(verts, faces)[0]
    torch.testing.assert_close(rings.normals(verts.reshape(-1, 3)), reference, rtol=1e-5, atol=1e-6)


def test_shared_face_geometry_gives_the_same_normals_and_derivatives():
    """A fit computes the ring faces once per point for its residuals and its Jacobian."""
    model = builtin_head_model(dtype=torch.float64)
    verts = model(torch.randn(1, model.num_shape, generator=torch.Generator().manual_seed(1), dtype=torch.float64))
    flat = verts.reshape(-1, 3)
    rings = Rings.build(model.faces, torch.arange(2, model.num_vertices, 3), model.num_vertices)
    faces = rings.face_geometry(flat)
    assert faces[0].shape == (rings.faces.shape[0], 3, 3) and faces[1].shape == faces[0].shape[::2]
    assert torch.equal(rings.normals(flat, faces), rings.normals(flat))
    for shared, alone in zip(rings.normal_derivatives(flat, faces), rings.normal_derivatives(flat)):
        assert torch.equal(shared, alone)
    # the geometry is what is used: another mesh's faces give that mesh's normals
    other = (flat * torch.tensor([1.0, 1.3, 0.8], dtype=torch.float64))
    assert torch.equal(rings.normals(flat, rings.face_geometry(other)), rings.normals(other))


@pytest.mark.parametrize("layout", [None, torch.sparse_bsr, torch.sparse_csr])
def test_row_structure_is_the_dense_block_matrix(layout):
    model = builtin_head_model(dtype=torch.float64)
    N = model.num_vertices
    rings = Rings.build(model.faces, torch.tensor([5, 40, 41]), N)
    entries = torch.tensor([2, 3, 0])  # slot 2, an empty row block, slot 0
    rows = rings.row_structure(entries, N)
    generator = torch.Generator().manual_seed(0)
    values = torch.randn(rows.entry.shape[0], 3, 3, generator=generator, dtype=torch.float64)
    dense = torch.zeros(9, 3 * N, dtype=torch.float64)
    for t, (e, b) in enumerate(zip(rows.entry.tolist(), rows.block.tolist())):
        assert rings.block_slot[b] == entries[e]
        g = int(rings.block_vertex[b])
        dense[3 * e : 3 * e + 3, 3 * g : 3 * g + 3] += values[t]
    matrix = rows.matrix(values, 3 * N, layout=layout)
    assert matrix.layout == (layout or torch.sparse_bsr)  # the CPU's default
    torch.testing.assert_close(matrix.to_dense(), dense)
    basis = torch.randn(3 * N, 4, generator=generator, dtype=torch.float64)
    torch.testing.assert_close(matrix @ basis, dense @ basis)
    assert dense[3:6].abs().sum() == 0


def test_sort_keys_shrink_to_int32_only_where_they_fit():
    keys = torch.tensor([0, 5, 2**31 - 2])
    assert _compact(keys, 2**31 - 1).dtype == torch.int32 and _compact(keys, 2**31 - 1).tolist() == keys.tolist()
    big = torch.tensor([0, 2**31, 2**40])
    assert _compact(big, 2**40 + 1).dtype == torch.int64 and torch.equal(_compact(big, 2**40 + 1), big)
