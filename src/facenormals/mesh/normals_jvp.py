r"""Analytic forward-mode derivatives of the paper's vertex normals along fixed directions.

For a morphable model :math:`X = X_0 + W y` the fitting needs :math:`\partial n_i / \partial y_k`
for every vertex and every shape component. With :math:`c_f = (v_1 - v_0) \times (v_2 - v_0)`,
:math:`m_f = c_f / \lVert c_f \rVert`, :math:`s_i = \sum_{f \ni i} m_f` and
:math:`n_i = s_i / \lVert s_i \rVert` (the ``"ring"`` estimator of
:func:`~facenormals.mesh.vertex_normals`), a tangent :math:`\dot v` gives

.. math::

    \dot c_f = \dot e_1 \times e_2 + e_1 \times \dot e_2, \quad
    \dot m_f = \frac{(I - m_f m_f^\top)\,\dot c_f}{\lVert c_f \rVert}, \quad
    \dot n_i = \frac{(I - n_i n_i^\top) \sum_{f \ni i} \dot m_f}{\lVert s_i \rVert}.

A face with :math:`\lVert c_f \rVert < \varepsilon` (degenerate) has :math:`m_f = \dot m_f = 0`
and a vertex with :math:`\lVert s_i \rVert < \varepsilon` has :math:`n_i = \dot n_i = 0`, as in
:func:`~facenormals.mesh.vertex_normals` (whose gradient stops there).

All ``K`` tangents are pushed at once; for a fixed basis the tangent edge differences
:math:`\dot e_1, \dot e_2` are precomputed by :class:`VertexNormalsJacobian`. This is exact (it
equals ``torch.func.jvp`` of ``vertex_normals``) and several times cheaper than vmapped autograd.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from facenormals.core.check import (
    check_faces,
    check_finite,
    check_floating,
    check_positive,
    check_same_dtype_device,
    check_shape,
    check_tensor,
)
from facenormals.mesh.normals import _check_vertices, _cross, _inverse_norm

__all__ = ["VertexNormalsJacobian", "vertex_normals_jvp"]


def _tangent_edges(tangents: Tensor, faces: Tensor) -> tuple[Tensor, Tensor]:
    """Edge differences of ``K`` tangents ``(K, N, 3)`` in the layout ``(F, 3, K)``."""
    rows = tangents.permute(1, 2, 0)  # (N, 3, K)
    t0, t1, t2 = (rows[faces[:, k]] for k in range(3))
    return (t1 - t0).contiguous(), (t2 - t0).contiguous()


def _jvp_one(
    vertices: Tensor, faces: Tensor, d_e1: Tensor, d_e2: Tensor, eps: float,
    corners: Tensor | None = None, num_out: int | None = None, work: Tensor | None = None,
) -> tuple[Tensor, Tensor]:
    """One mesh ``(N, 3)`` with tangent edges ``(F, 3, K)`` → normals ``(N, 3)``, Jacobian ``(N, 3, K)``.

    Rows (faces, vertices) hold ``3 K`` contiguous numbers, so the scatter into vertices is a row-wise
    ``index_add`` and products are fused with ``addcmul``: the K-fold work is a few passes over memory.
    With ``corners`` (the faces' corners renumbered into ``num_out`` output rows, ``num_out - 1`` being
    a discarded row) only a subset of the vertices is produced.
    """
    if vertices.dtype in (torch.float16, torch.bfloat16):  # the eps clamps round to 0: 0/0 at unused vertices
        n, d_n = _jvp_one(vertices.float(), faces, d_e1.float(), d_e2.float(), eps, corners, num_out)
        return n.to(vertices.dtype), d_n.to(vertices.dtype)
    if corners is None:
        corners, num_out = faces, vertices.shape[0]
    num_vertices = num_out
    v0, v1, v2 = (vertices[faces[:, k]] for k in range(3))
    e1, e2 = v1 - v0, v2 - v0  # (F, 3)
    c = _cross(e1, e2)  # exactly 0 for a degenerate face [a, b, b], as in vertex_normals
    c_inverse = _inverse_norm(c, eps)  # (F, 1); 0 below eps: ṁ = 0 there, whatever rounding leaves in ċ
    m = c * c_inverse
    d_c = torch.empty_like(d_e1) if work is None else work  # a reused buffer avoids page faults
    for i, (j, k) in enumerate(((1, 2), (2, 0), (0, 1))):
        # (ė1 × e2 + e1 × ė2)_i = ė1_j e2_k − ė1_k e2_j + e1_j ė2_k − e1_k ė2_j
        out = d_c[:, i]
        torch.mul(d_e1[:, j], e2[:, k : k + 1], out=out)
        out.addcmul_(d_e1[:, k], e2[:, j : j + 1], value=-1.0)
        out.addcmul_(d_e2[:, k], e1[:, j : j + 1])
        out.addcmul_(d_e2[:, j], e1[:, k : k + 1], value=-1.0)
    along = d_c[:, 0] * m[:, 0:1]  # m · ċ, (F, K)
    along.addcmul_(d_c[:, 1], m[:, 1:2]).addcmul_(d_c[:, 2], m[:, 2:3])
    d_m = d_c.addcmul_(m.unsqueeze(-1), along.unsqueeze(1), value=-1.0).mul_(c_inverse.unsqueeze(-1))
    s = vertices.new_zeros(num_vertices, 3)
    d_s = vertices.new_zeros(num_vertices, 3, d_e1.shape[-1])
    for k in range(3):
        s.index_add_(0, corners[:, k], m)
        d_s.index_add_(0, corners[:, k], d_m)
    s_inverse = _inverse_norm(s, eps)  # (N, 1)
    n = s * s_inverse
    along = d_s[:, 0] * n[:, 0:1]
    along.addcmul_(d_s[:, 1], n[:, 1:2]).addcmul_(d_s[:, 2], n[:, 2:3])
    d_n = d_s.addcmul_(n.unsqueeze(-1), along.unsqueeze(1), value=-1.0).mul_(s_inverse.unsqueeze(-1))
    return n, d_n


@torch.no_grad()
def _jvp(vertices: Tensor, faces: Tensor, d_e1: Tensor, d_e2: Tensor, eps: float) -> tuple[Tensor, Tensor]:
    """Batched: tangent edges ``(F, 3, K)`` shared, or ``(B, F, 3, K)`` per element."""
    batch, num = vertices.shape[:2]
    normals, jacobian = vertices.new_zeros(batch, num, 3), vertices.new_zeros(batch, num, 3, d_e1.shape[-1])
    for b in range(batch):
        normals[b], jacobian[b] = _jvp_one(vertices[b], faces, d_e1 if d_e1.dim() == 3 else d_e1[b],
                                           d_e2 if d_e2.dim() == 3 else d_e2[b], eps)
    return normals, jacobian


def _check_device(vertices: Tensor, faces: Tensor, basis_edges: Tensor) -> None:
    """``vertices`` on the module's device and of its basis' dtype (a float64 basis with float32 vertices
    was silently rounded, as torch would silently promote elsewhere; the rest of the library refuses it)."""
    if vertices.device != faces.device:
        raise ValueError(f"vertices: expected device {faces.device} (the module's), got {vertices.device}")
    if vertices.dtype != basis_edges.dtype:
        raise ValueError(f"vertices: expected dtype {basis_edges.dtype} (the dtype of the module's basis), got "
                         f"{vertices.dtype}; convert the vertices, or the module with .to({vertices.dtype})")


def vertex_normals_jvp(vertices: Tensor, faces: Tensor, tangents: Tensor, eps: float = 1e-12) -> tuple[Tensor, Tensor]:
    r"""Ring vertex normals and their directional derivatives along ``K`` vertex tangents.

    Args:
        vertices: mesh vertices.
        faces: triangles, counter-clockwise seen from outside.
        tangents: ``K`` directions of vertex motion, shared by the batch ``(K, N, 3)`` or per
            element ``(B, K, N, 3)`` (e.g. the shape basis :math:`W_k`), with the dtype and device
            of ``vertices``.
        eps: the clamp of the norms, as in :func:`~facenormals.mesh.vertex_normals`.

    Returns:
        ``(normals, jacobian)``: the normals ``(B, N, 3)`` and, in Jacobian layout ``(B, N, 3, K)``,
        ``jacobian[b, i, :, k]`` :math:`= \partial n_i / \partial \text{tangent}_k`. Values only:
        they carry no autograd graph (differentiate :func:`~facenormals.mesh.vertex_normals` instead).

    Example:
        >>> v = torch.tensor([[[0.0, 0, 0], [1, 0, 0], [0, 1, 0]]])
        >>> t = torch.zeros(1, 3, 3); t[0, 0, 2] = 1.0  # lift vertex 0 along +z
        >>> n, dn = vertex_normals_jvp(v, torch.tensor([[0, 1, 2]]), t)
        >>> n[0, 0].tolist(), dn[0, 0, :, 0].tolist()
        ([0.0, 0.0, 1.0], [1.0, 1.0, 0.0])
    """
    _check_vertices(vertices)
    check_faces(faces, vertices.shape[1])
    check_tensor(tangents, "tangents")
    if tangents.dim() == 3:
        check_shape(tangents, ["K", vertices.shape[1], 3], "tangents")
    else:
        check_shape(tangents, ["B", "K", vertices.shape[1], 3], "tangents", {"B": vertices.shape[0]})
    faces = faces.to(device=vertices.device, dtype=torch.long)
    check_floating(tangents, "tangents")
    check_same_dtype_device(vertices, "vertices", tangents=tangents)  # not rounded or promoted silently
    check_finite(tangents, "tangents")
    tangents = tangents.detach()
    if tangents.dim() == 3:
        d_e1, d_e2 = _tangent_edges(tangents, faces)
    else:
        edges = [_tangent_edges(t, faces) for t in tangents]
        d_e1, d_e2 = torch.stack([e[0] for e in edges]), torch.stack([e[1] for e in edges])
    return _jvp(vertices, faces, d_e1, d_e2, check_positive(eps, "eps"))


class _SubsetJacobian:
    """Normals and Jacobian rows of a vertex subset (see :meth:`VertexNormalsJacobian.subset`)."""

    def __init__(self, faces: Tensor, corners: Tensor, d_e1: Tensor, d_e2: Tensor, size: int, eps: float,
                 num_vertices: int, repeat: Tensor | None) -> None:
        self.faces, self.corners, self.d_e1, self.d_e2, self.size, self.eps = faces, corners, d_e1, d_e2, size, eps
        self.num_vertices = num_vertices
        self.repeat = repeat  # rows of the unique vertices giving the requested ones, when some repeat
        self._work: Tensor | None = None  # scratch for the face-normal derivatives, never returned

    @torch.no_grad()
    def __call__(self, vertices: Tensor) -> tuple[Tensor, Tensor]:
        _check_vertices(vertices, self.num_vertices)
        _check_device(vertices, self.faces, self.d_e1)
        d_e1, d_e2 = self.d_e1, self.d_e2
        if self._work is None or self._work.dtype != d_e1.dtype or self._work.device != d_e1.device:
            self._work = torch.empty_like(d_e1)
        normals = vertices.new_zeros(vertices.shape[0], self.size, 3)
        jacobian = vertices.new_zeros(vertices.shape[0], self.size, 3, d_e1.shape[-1])
        for b, v in enumerate(vertices):
            n, dn = _jvp_one(v, self.faces, d_e1, d_e2, self.eps, self.corners, self.size + 1, self._work)
            normals[b], jacobian[b] = n[: self.size], dn[: self.size]
        if self.repeat is not None:
            normals, jacobian = normals[:, self.repeat], jacobian[:, self.repeat]
        return normals, jacobian


class VertexNormalsJacobian(nn.Module):
    r"""Ring vertex normals and :math:`\partial n / \partial y` for a fixed basis ``(K, N, 3)``.

    Precomputes the basis' edge differences once, so each call costs two cross products per face
    and component. See :func:`vertex_normals_jvp`. The vertices must have the basis' dtype (or the
    dtype the module was converted to, e.g. with ``.double()``) and the module's device.

    Shape:
        - forward: vertices :math:`(B, N, 3)` → normals :math:`(B, N, 3)`, Jacobian :math:`(B, N, 3, K)`

    Example:
        >>> from facenormals.models import builtin_head_model
        >>> model = builtin_head_model()
        >>> jac = VertexNormalsJacobian(model.faces, model.shape_basis)
        >>> n, dn = jac(model(torch.zeros(1, model.num_shape)))
        >>> tuple(dn.shape)
        (1, 10242, 3, 24)
    """

    def __init__(self, faces: Tensor, basis: Tensor, eps: float = 1e-12) -> None:
        super().__init__()
        dims = check_shape(basis, ["K", "N", 3], "basis")
        check_floating(basis, "basis")
        check_finite(basis, "basis")
        check_faces(faces, dims["N"])
        faces = faces.to(torch.long)
        d_e1, d_e2 = _tangent_edges(basis, faces)
        self.eps = check_positive(eps, "eps")
        self.num_vertices = dims["N"]
        self.register_buffer("faces", faces, persistent=False)
        self.register_buffer("d_e1", d_e1.contiguous(), persistent=False)
        self.register_buffer("d_e2", d_e2.contiguous(), persistent=False)

    def forward(self, vertices: Tensor) -> tuple[Tensor, Tensor]:
        _check_vertices(vertices, self.num_vertices)
        _check_device(vertices, self.faces, self.d_e1)
        return _jvp(vertices, self.faces, self.d_e1, self.d_e2, self.eps)

    def subset(self, vertex_index: Tensor) -> "_SubsetJacobian":
        """A callable giving normals and Jacobian rows of ``vertex_index`` ``(S,)`` only: ``(B, S, 3)``
        and ``(B, S, 3, K)``. Only the faces around those vertices are processed, which is what a fit
        needs when it scores only the visible vertices. Indices may repeat; a vertex in no face gets
        a zero normal, as in :meth:`forward`.

        Raises:
            ValueError: naming ``vertex_index`` unless it is a 1-D integer tensor in ``[0, N)``.

        Example:
            >>> from facenormals.models import builtin_head_model
            >>> model = builtin_head_model()
            >>> jac = VertexNormalsJacobian(model.faces, model.shape_basis)
            >>> v = model(torch.zeros(1, model.num_shape))
            >>> n, dn = jac.subset(torch.tensor([5, 7]))(v)
            >>> torch.allclose(dn, jac(v)[1].index_select(1, torch.tensor((5, 7))), atol=1e-6)
            True
        """
        check_shape(vertex_index, ["S"], "vertex_index")
        if vertex_index.dtype.is_floating_point or vertex_index.dtype.is_complex or vertex_index.dtype == torch.bool:
            raise ValueError(f"vertex_index: expected an integer tensor, got dtype {vertex_index.dtype}")
        index = vertex_index.to(device=self.faces.device, dtype=torch.long)
        if index.numel() and (int(index.min()) < 0 or int(index.max()) >= self.num_vertices):
            raise ValueError(f"vertex_index: expected vertex indices in [0, {self.num_vertices}), got values in "
                             f"[{int(index.min())}, {int(index.max())}]")
        unique, repeat = torch.unique(index, return_inverse=True)
        if unique.shape[0] == index.shape[0]:
            repeat = None  # all distinct: computed in the caller's order
        else:
            index = unique
        compact = torch.full((self.num_vertices,), index.shape[0], dtype=torch.long, device=self.faces.device)
        compact[index] = torch.arange(index.shape[0], device=self.faces.device)
        selected = (compact[self.faces] < index.shape[0]).any(1)
        return _SubsetJacobian(self.faces[selected], compact[self.faces[selected]], self.d_e1[selected],
                               self.d_e2[selected], index.shape[0], self.eps, self.num_vertices, repeat)

    def extra_repr(self) -> str:
        return f"faces={self.faces.shape[0]}, components={self.d_e1.shape[-1]}"
