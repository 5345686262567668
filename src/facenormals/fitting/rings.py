r"""Ring normals of a vertex subset and their exact derivative as sparse 3×3 blocks.

For the paper's one-ring normals :math:`n_i = s_i / \lVert s_i \rVert`, :math:`s_i = \sum_{f \ni i} m_f`,
:math:`m_f = c_f / \lVert c_f \rVert` and :math:`c_f = (p_1 - p_0) \times (p_2 - p_0)`, the derivative
of :math:`n_i` is linear in the motions of the vertices of its ring:

.. math::

    \dot n_i = \sum_{g \in \mathrm{ring}(i)} M_{ig}\, \dot p_g, \qquad
    M_{ig} = \frac{I - n_i n_i^\top}{\lVert s_i \rVert} \sum_{f \ni i,\ g = f_k}
    \frac{(I - m_f m_f^\top)\,[p_{k+2} - p_{k+1}]_\times}{\lVert c_f \rVert},

with corner indices modulo 3 and :math:`[d]_\times v = d \times v`. The 3×3 blocks :math:`M_{ig}`
cost no work per shape component: a fit multiplies them with the basis rows in one sparse matrix
product (:class:`~facenormals.fitting.HeadFitProblem`), instead of pushing every component through
the faces. Vertex positions are given flat, ``(B·N, 3)``, so one :class:`Rings` serves a batch of
meshes that share the faces but not the subsets.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import torch
from torch import Tensor

from facenormals.mesh.normals import _cross

__all__ = ["RingRows", "Rings"]


@dataclass
class Rings:
    """The faces around ``U`` selected vertices of a batch of meshes, and the ``(slot, vertex)`` blocks.

    Build with :meth:`build` (one mesh) and :meth:`cat` (a batch). Vertex ids are *flat*: vertex
    ``v`` of batch element ``b`` is ``b · N + v``.

    Attributes:
        slot_vertex: ``(U,)`` flat id of each selected vertex ("slot").
        faces: ``(F, 3)`` flat corner ids of the faces touching a selected vertex.
        corner_slot: ``(F, 3)`` slot of each corner, ``U`` where the corner is not selected.
        face_block: ``(F, 3, 3)`` block receiving (row corner, column corner), ``nb`` where the row
            corner is not selected.
        block_slot: ``(nb,)`` row slot of each block; blocks are sorted by slot, then vertex.
        block_vertex: ``(nb,)`` flat column vertex of each block.
        block_start: ``(U + 1,)`` the blocks of slot ``u`` are ``block_start[u] : block_start[u + 1]``.
    """

    slot_vertex: Tensor
    faces: Tensor
    corner_slot: Tensor
    face_block: Tensor
    block_slot: Tensor
    block_vertex: Tensor
    block_start: Tensor

    @staticmethod
    def build(faces: Tensor, vertex_index: Tensor, num_vertices: int) -> "Rings":
        """The rings of ``vertex_index`` ``(U,)`` (sorted, unique) on a mesh with ``num_vertices``.

        Example:
            >>> faces = torch.tensor([[0, 1, 2], [0, 2, 3]])
            >>> rings = Rings.build(faces, torch.tensor([3]), 4)
            >>> rings.faces.tolist(), rings.block_vertex.tolist()
            ([[0, 2, 3]], [0, 2, 3])
        """
        faces = faces.to(torch.long)
        device = faces.device
        U = vertex_index.shape[0]
        compact = torch.full((num_vertices,), U, dtype=torch.long, device=device)
        compact[vertex_index] = torch.arange(U, device=device)
        slots = compact[faces]
        keep = (slots < U).any(1)
        faces, slots = faces[keep], slots[keep]
        rows = slots[:, :, None].expand(-1, 3, 3)  # (F, row corner, column corner)
        cols = faces[:, None, :].expand(-1, 3, 3)
        used = rows < U
        key = _compact(rows[used] * num_vertices + cols[used], U * num_vertices)
        unique, inverse = torch.unique(key, return_inverse=True)  # sorted: by slot, then vertex
        unique, inverse = unique.long(), inverse.long()
        face_block = torch.full(rows.shape, unique.shape[0], dtype=torch.long, device=device)
        face_block[used] = inverse
        block_slot = unique // num_vertices
        block_start = torch.zeros(U + 1, dtype=torch.long, device=device)
        block_start[1:] = torch.bincount(block_slot, minlength=U).cumsum(0)
        return Rings(vertex_index.to(torch.long), faces, slots, face_block, block_slot, unique % num_vertices,
                     block_start)

    @staticmethod
    def cat(parts: list["Rings"], num_vertices: int) -> "Rings":
        """Rings of a batch: part ``b`` belongs to batch element ``b`` of meshes with ``num_vertices``."""
        out: dict[str, list[Tensor]] = {name: [] for name in Rings.__dataclass_fields__}
        slots = blocks = 0
        total_slots = sum(p.slot_vertex.shape[0] for p in parts)
        total_blocks = sum(p.block_slot.shape[0] for p in parts)
        for b, p in enumerate(parts):
            U, nb, shift = p.slot_vertex.shape[0], p.block_slot.shape[0], b * num_vertices
            out["slot_vertex"].append(p.slot_vertex + shift)
            out["faces"].append(p.faces + shift)
            out["corner_slot"].append(torch.where(p.corner_slot < U, p.corner_slot + slots, total_slots))
            out["face_block"].append(torch.where(p.face_block < nb, p.face_block + blocks, total_blocks))
            out["block_slot"].append(p.block_slot + slots)
            out["block_vertex"].append(p.block_vertex + shift)
            out["block_start"].append(p.block_start[:-1] + blocks)
            slots, blocks = slots + U, blocks + nb
        out["block_start"].append(torch.tensor([blocks], dtype=torch.long, device=parts[0].faces.device))
        return Rings(**{name: torch.cat(values) for name, values in out.items()})

    @property
    def num_slots(self) -> int:
        return self.slot_vertex.shape[0]

    def _sum_matrices(self, dtype: torch.dtype) -> tuple[Tensor, Tensor]:
        """0/1 CSR matrices summing face rows into slots ``(U, F)`` and corner coefficients into
        blocks ``(nb, 3F)``: sparse products are several times faster than ``index_add_`` here."""
        cache = self.__dict__.setdefault("_sums_cache", {})
        if dtype not in cache:
            F, U, nb = self.faces.shape[0], self.num_slots, self.block_slot.shape[0]
            face = torch.arange(F, device=self.faces.device)
            slot_rows, slot_cols = self.corner_slot.reshape(-1), face.repeat_interleave(3)
            block_rows = self.face_block.reshape(-1)
            block_cols = (3 * face[:, None, None] + torch.arange(3, device=face.device)).expand(-1, 3, -1).reshape(-1)
            cache[dtype] = (_summing(slot_rows, slot_cols, U, F, dtype), _summing(block_rows, block_cols, nb, 3 * F, dtype))
        return cache[dtype]

    def face_geometry(self, vertices: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """Corners ``(F, 3, 3)``, unit normals ``(F, 3)`` and ``|c|`` ``(F, 1)`` of the ring faces from
        flat vertices ``(B·N, 3)``: what :meth:`normals` and :meth:`normal_derivatives` start from, for
        a caller that needs both at the same vertices (a fit's residuals, then its Jacobian)."""
        p = vertices[self.faces]
        c = _cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])  # exactly 0 for a degenerate face [a, b, b]
        norm = c.norm(dim=1, keepdim=True).clamp_min(1e-12)
        return p, c / norm, norm

    def normals(self, vertices: Tensor, face_geometry: tuple[Tensor, Tensor, Tensor] | None = None) -> Tensor:
        """Unit ring normals ``(U, 3)`` of the slots from flat vertices ``(B·N, 3)`` (or their
        :meth:`face_geometry`); differentiable, also under ``torch.func`` transforms."""
        m = (face_geometry or self.face_geometry(vertices))[1]
        s = m.new_zeros(self.num_slots + 1, 3)
        for k in range(3):  # out of place: works under vmap / jvp
            s = s.index_add(0, self.corner_slot[:, k], m)
        s = s[:-1]
        return s / s.norm(dim=1, keepdim=True).clamp_min(1e-12)

    def normal_derivatives(self, vertices: Tensor, face_geometry: tuple[Tensor, Tensor, Tensor] | None = None
                           ) -> tuple[Tensor, Tensor, Tensor]:
        r"""Normals ``(U, 3)``, projectors ``(U, 3, 3)`` and raw blocks ``(nb, 3, 3)`` from flat vertices
        (or their :meth:`face_geometry`).

        Block ``b`` of :math:`\partial n / \partial p` is ``projector[block_slot[b]] @ raw[b]``, with
        the projector :math:`(I - n n^\top) / \lVert s \rVert` of the row's slot (kept apart so that
        a caller can fold its own left factor into it).
        """
        slot_sum, block_sum = self._sum_matrices(vertices.dtype)
        p, m, c_norm = face_geometry or self.face_geometry(vertices)
        s = slot_sum @ m
        s_norm = s.norm(dim=1, keepdim=True).clamp_min(1e-12)
        n = s / s_norm
        # The corner coefficient is P [d]× / |c| with P = I - m mᵀ and d = p_{k+2} - p_{k+1}, the edge
        # opposite corner k; it is -([d]× P / |c|)ᵀ (P symmetric, [d]× antisymmetric), and
        # [d]× P = [d]× - (d × m) mᵀ is written out per entry (a stacked skew matrix and two batched
        # 3×3 products made this function 1.8× slower). Rows (face, corner) stay contiguous for the
        # summing product.
        d = p.roll(1, 1) - p.roll(-1, 1)  # (F, corner, 3)
        m_corner = m[:, None].expand_as(d)
        coef_t = -torch.linalg.cross(d, m_corner)[..., :, None] * m[:, None, None, :]  # (F, corner, 3, 3)
        x, y, z = d.unbind(-1)
        coef_t[..., 0, 1] -= z
        coef_t[..., 0, 2] += y
        coef_t[..., 1, 0] += z
        coef_t[..., 1, 2] -= x
        coef_t[..., 2, 0] -= y
        coef_t[..., 2, 1] += x
        coef_t = coef_t.div_(c_norm[:, :, None, None]).view(-1, 9)
        raw = -(block_sum @ coef_t).view(-1, 3, 3).transpose(1, 2)
        eye = torch.eye(3, dtype=p.dtype, device=p.device)
        projector = (eye - n[:, :, None] * n[:, None, :]) / s_norm[:, :, None]
        return n, projector, raw

    def normals_and_blocks(self, vertices: Tensor) -> tuple[Tensor, Tensor]:
        r"""Normals ``(U, 3)`` and blocks ``(nb, 3, 3)``: :math:`\partial n_{slot} / \partial p_{vertex}`."""
        n, projector, raw = self.normal_derivatives(vertices)
        return n, torch.bmm(projector[self.block_slot], raw)

    def row_structure(self, entry_slot: Tensor, num_vertices: int) -> "RingRows":
        r"""The sparse layout of ``3 E`` rows, 3 per entry, each a 3×3 block row ``Σ_g A_g p_g`` over
        the ring of the entry's slot: ``entry_slot`` ``(E,)``, a slot or ``U`` for an empty row block.
        Columns ``3 (g mod num_vertices) + j``: the meshes of the batch share the column space, e.g.
        the rows of a morphable model's basis.

        Example:
            >>> faces = torch.tensor([[0, 1, 2], [0, 2, 3]])
            >>> rings = Rings.build(faces, torch.tensor([0, 3]), 4)
            >>> rows = rings.row_structure(torch.tensor([1, 2, 0]), 4)  # slot 1, none, slot 0
            >>> rows.crow.tolist(), rows.block.tolist(), rows.col.tolist()
            ([0, 3, 3, 7], [4, 5, 6, 0, 1, 2, 3], [0, 2, 3, 0, 1, 2, 3])
        """
        device = entry_slot.device
        U = self.num_slots
        slot = entry_slot.clamp(max=U)
        start = torch.cat([self.block_start, self.block_start[-1:]])  # slot U: no blocks
        counts = start[slot + 1] - start[slot]  # (E,)
        total = int(counts.sum())
        entry = torch.repeat_interleave(torch.arange(slot.shape[0], device=device), counts, output_size=total)
        crow = torch.zeros(slot.shape[0] + 1, dtype=torch.long, device=device)
        crow[1:] = torch.cumsum(counts, 0)
        block = start[slot][entry] + torch.arange(total, device=device) - crow[entry]  # an entry's blocks in order
        return RingRows(entry, block, crow, self.block_vertex[block] % num_vertices)


@dataclass
class RingRows:
    """Sparse layout from :meth:`Rings.row_structure`: ``E`` entries (block rows of 3 rows) and ``T``
    (entry, block) pairs, each a 3×3 block.

    Attributes:
        entry: ``(T,)`` the entry of each pair, ascending; block: ``(T,)`` its ring block.
        crow: ``(E + 1,)`` the pairs of entry ``e`` are ``crow[e] : crow[e + 1]``.
        col: ``(T,)`` the block column of each pair (its vertex modulo the column space's vertices).
    """

    entry: Tensor
    block: Tensor
    crow: Tensor
    col: Tensor

    @property
    def num_rows(self) -> int:
        return 3 * (self.crow.shape[0] - 1)

    def matrix(self, values: Tensor, num_columns: int, layout: torch.layout | None = None) -> Tensor:
        """The sparse matrix ``(3E, num_columns)`` with per-pair blocks ``values`` ``(T, 3, 3)``.

        ``layout`` defaults to BSR on the CPU, where MKL's block product with a dense matrix is faster
        than the CSR one (~0.8 ms of a 15 ms fit iteration on the ICT head, ``docs/performance.md``)
        and takes the blocks as they are, and to CSR on other devices (the layout measured on CUDA).
        """
        if layout is None:
            layout = torch.sparse_bsr if values.device.type == "cpu" else torch.sparse_csr
        with warnings.catch_warnings():  # "sparse CSR/BSR support is in beta"
            warnings.simplefilter("ignore", UserWarning)
            if layout == torch.sparse_bsr:
                return torch.sparse_bsr_tensor(self.crow, self.col, values, (self.num_rows, num_columns),
                                               check_invariants=False)
            crow, col, perm = self._csr()
            return torch.sparse_csr_tensor(crow, col, values.reshape(-1)[perm], (self.num_rows, num_columns),
                                           check_invariants=False)

    def _csr(self) -> tuple[Tensor, Tensor, Tensor]:
        """CSR row pointers ``(3E + 1,)``, column indices ``(9T,)`` and the order ``(9T,)`` of the
        flat per-pair values: row ``3e + a`` holds, for each pair of entry ``e`` in turn, the
        columns ``3 col + j``."""
        cache = self.__dict__.setdefault("_csr_cache", {})
        if not cache:
            device = self.crow.device
            counts, first = self.crow.diff(), self.crow[:-1]
            crow = torch.zeros(3 * counts.shape[0] + 1, dtype=torch.long, device=device)
            crow[1:] = torch.cumsum((3 * counts).repeat_interleave(3), 0)
            a = torch.arange(3, device=device)
            position = torch.arange(self.entry.shape[0], device=device) - first[self.entry]
            # value (pair t, row a, column j) sits at 9 first + 3 a counts + 3 position + j
            dest = ((9 * first[self.entry] + 3 * position)[:, None, None] + 3 * a[None, :, None]
                    * counts[self.entry][:, None, None] + a[None, None, :]).reshape(-1)
            perm = torch.empty_like(dest)
            perm[dest] = torch.arange(dest.shape[0], device=device)
            col = torch.empty_like(dest)
            col[dest] = (3 * self.col[:, None, None] + a[None, None, :]).expand(-1, 3, -1).reshape(-1)
            cache["csr"] = (crow, col, perm)
        return cache["csr"]


def _summing(rows: Tensor, cols: Tensor, num_rows: int, num_cols: int, dtype: torch.dtype) -> Tensor:
    """CSR ``(num_rows, num_cols)`` with ones at ``(rows, cols)``; entries with ``rows >= num_rows`` are dropped."""
    keep = rows < num_rows
    rows, cols = rows[keep], cols[keep]
    order = torch.argsort(_compact(rows, num_rows), stable=True)
    crow = torch.zeros(num_rows + 1, dtype=torch.long, device=rows.device)
    crow[1:] = torch.bincount(rows, minlength=num_rows).cumsum(0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        return torch.sparse_csr_tensor(crow, cols[order], torch.ones(rows.shape[0], dtype=dtype, device=rows.device),
                                       (num_rows, num_cols), check_invariants=False)


def _compact(keys: Tensor, bound: int) -> Tensor:
    """Non-negative int64 ``keys`` below ``bound`` as int32 where they fit: sorting them (``unique``,
    ``argsort``) is then 1.7-1.8x faster on CPU."""
    return keys.to(torch.int32) if bound <= torch.iinfo(torch.int32).max else keys
