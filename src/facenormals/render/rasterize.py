r"""A small pure-PyTorch z-buffer rasteriser for oracle maps, visibility and tests.

It is exact (perspective-correct barycentrics, pixel centres at integer coordinates) but not
differentiable; the fitting differentiates through :func:`~facenormals.sampling.sample_bicubic`
instead. For photorealistic training images see the pyrender-based generator.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from facenormals.core.check import (
    check_all_finite,
    check_faces,
    check_floating,
    check_image_size,
    check_nonnegative,
    check_same_dtype_device,
    check_shape,
)

__all__ = ["Fragments", "interpolate_vertex_attributes", "rasterize_depth", "rasterize_triangles"]


@dataclass
class Fragments:
    """Per-pixel result of :func:`rasterize_triangles`.

    Attributes:
        face_index: ``(B, H, W)`` long, the visible triangle at each pixel, −1 on background.
        barycentric: ``(B, H, W, 3)`` perspective-correct barycentric coordinates (0 on background).
        depth: ``(B, H, W)`` camera-frame depth z of the visible surface, ``inf`` on background.
    """

    face_index: Tensor
    barycentric: Tensor
    depth: Tensor

    @property
    def mask(self) -> Tensor:
        """``(B, H, W)`` bool foreground mask."""
        return self.face_index >= 0


# Depths within this relative difference of a pixel's nearest count as ties (then the triangle listed
# first wins): the depth at a pixel centre is computed from the triangle's corners in their listed
# order, so the same surface seen through two triangles (a triangle listed twice with its corners in
# another order, a shared edge) comes out a few hundred float64 ulps apart, and 2^-40 (4096 ulps,
# ~1e-12) still covers slivers of aspect ratio 1000; it is a picometre at a metre.
_TIE = 2.0**-40

# Triangles are tested against a grid of pixel centres the size of their bounding box, rounded up
# to powers of two per axis and processed in chunks of at most this many (triangle, pixel) cells:
# the temporaries then stay at a few hundred MB however long and thin the triangles are.
_CELLS_PER_CHUNK = 1 << 21


def _buckets(extent: Tensor) -> list[tuple[Tensor, int, int]]:
    """Group the triangles with bounding boxes ``extent`` ``(..., 2)`` (columns, rows; 0 for the
    skipped ones) by grid size: ``(mask (...), width, height)`` per occupied pair of powers of two."""
    valid = (extent > 0).all(-1)
    log2 = torch.ceil(torch.log2(extent.clamp(min=1.0))).long().clamp(min=1)  # grids of 2 or more
    square = log2.amax(-1, keepdim=True)  # boxes up to 8 px: square grids, fewer buckets (less overhead)
    log2 = torch.where(square <= 3, square, log2)
    key = torch.where(valid, log2[..., 0] * 64 + log2[..., 1], -1)
    present = torch.bincount(key[valid]).nonzero().flatten().tolist()  # no sort, unlike torch.unique
    return [(key == k, 1 << (k // 64), 1 << (k % 64)) for k in present]


def _check_raster_inputs(pixels: Tensor, depth: Tensor, faces: Tensor, image_size: tuple[int, int],
                         near: float) -> tuple[int, int, int, float]:
    dims = check_shape(pixels, ["B", "N", 2], "pixels")
    check_shape(depth, ["B", "N"], "depth", dims)
    check_faces(faces, dims["N"])
    check_floating(pixels, "pixels")
    check_same_dtype_device(pixels, "pixels", depth=depth)  # the z-buffer comes back in this dtype
    check_all_finite(pixels=pixels, depth=depth)  # a NaN triangle would silently leave a hole
    height, width = check_image_size(image_size)
    return dims["B"], height, width, check_nonnegative(near, "near")


def _covered_pixels(pixels: Tensor, depth: Tensor, faces: Tensor, batch: int, height: int, width: int,
                    cull_backfaces: bool, near: float, barycentric: bool):
    """Yield ``(pixel, face, z, barycentric or None)`` for every (triangle, covered pixel centre) pair,
    in buckets of triangles by bounding-box size (see ``_buckets``); ``pixel`` is the flat index
    ``(b H + v) W + u``. Each pair comes once."""
    device = pixels.device
    work = torch.float64
    num_vertices, count = depth.shape[1], faces.shape[0]
    # corners (u, v, z) of every (subject, face), gathered in one pass: (3 coordinates, B, 3 corners, F)
    corners = torch.cat([pixels.to(work), depth.to(work)[..., None]], -1).reshape(-1, 3)
    index = faces.to(device=device, dtype=torch.long).T.reshape(1, -1)
    index = (index + num_vertices * torch.arange(batch, device=device)[:, None]).reshape(-1)
    u, v, z = corners.index_select(0, index).T.reshape(3, batch, 3, count)
    area = (u[:, 1] - u[:, 0]) * (v[:, 2] - v[:, 0]) - (v[:, 1] - v[:, 0]) * (u[:, 2] - u[:, 0])  # (B, F)
    valid = (z > near).all(1) & (area.abs() > 1e-12)  # the inputs are finite (checked)
    if cull_backfaces:  # facing the camera: counter-clockwise on screen, i.e. area < 0 with v pointing down
        valid &= area < 0
    lo_u, lo_v = torch.ceil(u.amin(1) - 1e-9).clamp(min=0), torch.ceil(v.amin(1) - 1e-9).clamp(min=0)
    hi_u, hi_v = torch.floor(u.amax(1) + 1e-9).clamp(max=width - 1), torch.floor(v.amax(1) + 1e-9).clamp(max=height - 1)
    valid &= (hi_u >= lo_u) & (hi_v >= lo_v)
    tri = torch.nonzero(valid.reshape(-1)).squeeze(1)  # flat (subject, face) indices of the boxes to test

    # The screen barycentrics w0, w1 are affine in the pixel centre: for the edge (a, b) opposite a
    # corner, (a - p) x (b - p) = a x b + p_u (a_v - b_v) + p_v (b_u - a_u). Relative to the box's
    # first pixel centre (lo_u, lo_v) (an exact shift) they are c + a du + b dv on the box's cells
    # (du, dv).
    u, v = u - lo_u[:, None], v - lo_v[:, None]

    def edge(i: int, j: int) -> tuple[Tensor, Tensor, Tensor]:
        return (u[:, i] * v[:, j] - v[:, i] * u[:, j]) / area, (v[:, i] - v[:, j]) / area, (u[:, j] - u[:, i]) / area

    (c0, a0, b0), (c1, a1, b1) = edge(1, 2), edge(2, 0)
    # one column per triangle: its box's first cell and size - 1, (c, a, b) of w0 and w1 interleaved,
    # the corners' depths; columns are gathered through the flat storage (index_select along
    # dimension 0 is several times faster than along dimension 1)
    columns = torch.stack([lo_u, lo_v, hi_u - lo_u, hi_v - lo_v, c0, c1, a0, a1, b0, b1, *z.unbind(1)])
    table = _columns(columns.view(13, -1), tri)  # (13, T)

    def cover(pos: Tensor, grid: Tensor):
        """The triangles ``tri[pos]`` on the cells ``grid`` ``(cells, 2)`` (columns ``du, dv``)."""
        n = pos.shape[0]
        rows = _columns(table, pos)
        # (cells, 2 n): w0 of each triangle, then w1; elementwise (a matrix product rounded
        # differently with the chunk's size)
        coef = rows[4:10].view(3, 2 * n)
        du, dv = grid[:, 0:1], grid[:, 1:2]
        w = (coef[1] * du).add_(coef[0]).add_(coef[2] * dv)
        w0, w1 = w[:, :n], w[:, n:]
        inside = (w0 >= -1e-9) & (w1 >= -1e-9) & (1.0 - w0 - w1 >= -1e-9)
        inside &= (du <= rows[2]) & (dv <= rows[3])  # in the box, so in the image
        cell = torch.nonzero(inside.view(-1)).squeeze(1)
        k_idx = cell // n
        t_idx = cell - k_idx * n
        at = cell + k_idx * n  # w0 in w's storage, w1 n further
        w0, w1 = w.view(-1).index_select(0, at), w.view(-1).index_select(0, at + n)
        rows = _columns(rows, t_idx)
        inv_z = torch.stack([w0, w1, 1.0 - w0 - w1], -1) / rows[10:13].T
        depth_ = 1.0 / inv_z.sum(-1)
        pu, pv = (rows[:2].T + grid.index_select(0, k_idx)).long().unbind(1)
        flat = tri.index_select(0, pos.index_select(0, t_idx))
        pix = ((flat // count) * height + pv) * width + pu
        return pix, flat % count, depth_, (inv_z * depth_[:, None] if barycentric else None)

    for in_bucket, grid_w, grid_h in _buckets((table[2:4] + 1).T):
        pos = torch.nonzero(in_bucket).squeeze(1)
        dv, du = torch.meshgrid(torch.arange(grid_h, device=device, dtype=work),
                                torch.arange(grid_w, device=device, dtype=work), indexing="ij")
        grid = torch.stack([du, dv], -1).reshape(-1, 2)
        chunk = max(1, _CELLS_PER_CHUNK // (grid_w * grid_h))
        for first in range(0, pos.numel(), chunk):
            yield cover(pos[first : first + chunk], grid)


def _columns(table: Tensor, index: Tensor) -> Tensor:
    """``table[:, index]`` of a contiguous ``(R, C)`` table, gathered from its flat storage."""
    rows = torch.arange(table.shape[0], device=index.device)[:, None] * table.shape[1]
    return table.view(-1).index_select(0, (rows + index).view(-1)).view(table.shape[0], -1)


@torch.no_grad()
def rasterize_triangles(
    pixels: Tensor,
    depth: Tensor,
    faces: Tensor,
    image_size: tuple[int, int],
    cull_backfaces: bool = False,
    near: float = 1e-6,
) -> Fragments:
    r"""Rasterise projected triangles with a z-buffer.

    A pixel centre ``(u, v)`` (integers, OpenCV convention) is covered by a triangle when its
    screen-space barycentrics are all ≥ 0 (up to 1e-9). Among covering triangles the nearest wins,
    and of those at the same depth the one listed first in ``faces``: depths within a relative
    :math:`2^{-40}` (about 1e-12) of the nearest count as the same, since the rounding of a
    triangle's depth depends on the order of its corners, so that e.g. a triangle listed twice,
    whatever the order of its corners, is drawn by its first copy on every pixel.
    Barycentrics are made perspective-correct by weighting with :math:`1/z`.

    Args:
        pixels: projected vertices ``(u, v)``, e.g. from :func:`~facenormals.geometry.project_points`.
        depth: camera-frame depth of each vertex; triangles with a vertex at ``z <= near`` are skipped.
        faces: triangles as vertex indices.
        image_size: ``(H, W)``.
        cull_backfaces: skip triangles that face away from the camera: with faces wound
            counter-clockwise seen from outside (docs/conventions.md), those that appear clockwise
            in the image as displayed (u right, v down).
        near: near-plane depth.

    Returns:
        The :class:`Fragments`.

    Shape:
        - pixels: :math:`(B, N, 2)`; depth: :math:`(B, N)`; faces: :math:`(F, 3)`

    Example:
        >>> uv = torch.tensor([[[0.0, 0.0], [9.0, 0.0], [0.0, 9.0]]])
        >>> frags = rasterize_triangles(uv, torch.ones(1, 3), torch.tensor([[0, 1, 2]]), (10, 10))
        >>> int(frags.mask.sum())  # pixel centres with u + v <= 9
        55
    """
    batch, height, width, near = _check_raster_inputs(pixels, depth, faces, image_size, near)
    num_pixels = batch * height * width
    work, device = torch.float64, pixels.device
    zbuf = torch.full((num_pixels,), float("inf"), dtype=work, device=device)
    candidates = []
    for pix, face, z, bary in _covered_pixels(pixels, depth, faces, batch, height, width, cull_backfaces, near, True):
        zbuf.scatter_reduce_(0, pix, z, reduce="amin")
        candidates.append((pix, face, z, bary))
    # Of the triangles at the nearest depth, up to the relative _TIE (the same surface: shared edges,
    # duplicated or coplanar triangles, whose depths differ by rounding), the one with the lowest
    # index wins: one winner per pixel, so the writes below never collide.
    none = faces.shape[0]
    face_index = torch.full((num_pixels,), none, dtype=torch.long, device=device)
    for i, (pix, face, z, bary) in enumerate(candidates):
        nearest = z <= zbuf[pix] * (1.0 + _TIE)  # the z-buffer is finite and > 0 at covered pixels
        candidates[i] = (pix[nearest], face[nearest], bary[nearest])
        face_index.scatter_reduce_(0, candidates[i][0], candidates[i][1], reduce="amin")
    barycentric = torch.zeros(num_pixels, 3, dtype=work, device=device)
    for pix, face, bary in candidates:
        wins = face == face_index[pix]
        barycentric[pix[wins]] = bary[wins]
    face_index[face_index == none] = -1
    return Fragments(
        face_index=face_index.reshape(batch, height, width),
        barycentric=barycentric.reshape(batch, height, width, 3).to(pixels.dtype),
        depth=zbuf.reshape(batch, height, width).to(pixels.dtype),
    )


@torch.no_grad()
def rasterize_depth(
    pixels: Tensor,
    depth: Tensor,
    faces: Tensor,
    image_size: tuple[int, int],
    cull_backfaces: bool = False,
    near: float = 1e-6,
) -> Tensor:
    r"""The z-buffer alone: ``rasterize_triangles(...).depth`` without the face indices and barycentrics.

    Visibility tests need only the nearest depth per pixel; skipping the pass that finds each
    pixel's winning face and its barycentrics saves ~15 % (the coverage tests dominate). Same
    arguments and coverage rule as :func:`rasterize_triangles`.

    Returns:
        ``(B, H, W)`` camera-frame depth of the nearest surface, ``inf`` on background.

    Example:
        >>> uv = torch.tensor([[[0.0, 0.0], [9.0, 0.0], [0.0, 9.0]]])
        >>> z = rasterize_depth(uv, torch.tensor([[1.0, 2.0, 2.0]]), torch.tensor([[0, 1, 2]]), (10, 10))
        >>> z[0, 0, 0].item(), z[0, 0, 9].item(), z[0, 9, 9].item()
        (1.0, 2.0, inf)
    """
    batch, height, width, near = _check_raster_inputs(pixels, depth, faces, image_size, near)
    zbuf = torch.full((batch * height * width,), float("inf"), dtype=torch.float64, device=pixels.device)
    for pix, _, z, _ in _covered_pixels(pixels, depth, faces, batch, height, width, cull_backfaces, near, False):
        zbuf.scatter_reduce_(0, pix, z, reduce="amin")
    return zbuf.reshape(batch, height, width).to(pixels.dtype)


def interpolate_vertex_attributes(fragments: Fragments, faces: Tensor, attributes: Tensor) -> Tensor:
    """Interpolate per-vertex attributes ``(B, N, C)`` at each pixel → ``(B, C, H, W)``, 0 on background.

    Example:
        >>> uv = torch.tensor([[[0.0, 0.0], [9.0, 0.0], [0.0, 9.0]]])
        >>> faces = torch.tensor([[0, 1, 2]])
        >>> frags = rasterize_triangles(uv, torch.ones(1, 3), faces, (10, 10))
        >>> interpolate_vertex_attributes(frags, faces, torch.ones(1, 3, 2)).shape
        torch.Size([1, 2, 10, 10])
    """
    if not isinstance(fragments, Fragments):
        raise ValueError(f"fragments: expected the Fragments of rasterize_triangles, got {type(fragments).__name__}")
    dims = check_shape(attributes, ["B", "N", "C"], "attributes")
    check_floating(attributes, "attributes")  # barycentric weights would round to 0 or 1
    check_shape(fragments.face_index, ["B", "H", "W"], "fragments.face_index", dims)
    index_dtype = fragments.face_index.dtype
    if index_dtype.is_floating_point or index_dtype.is_complex or index_dtype == torch.bool:
        raise ValueError(f"fragments.face_index: expected an integer tensor, got dtype {index_dtype}")
    if fragments.face_index.device != attributes.device:
        raise ValueError(f"fragments.face_index: expected device {attributes.device} (the device of attributes), got "
                         f"{fragments.face_index.device}")
    # a (H, W, 3) or (B, H, W, 2) barycentric would broadcast or fail deep inside, an integer one round
    check_shape(fragments.barycentric, ["B", "H", "W", 3], "fragments.barycentric", dims)
    check_floating(fragments.barycentric, "fragments.barycentric")
    check_same_dtype_device(attributes, "attributes", **{"fragments.barycentric": fragments.barycentric})
    check_all_finite(attributes=attributes, **{"fragments.barycentric": fragments.barycentric})
    count = check_faces(faces, dims["N"])["F"]
    if fragments.face_index.numel() and int(fragments.face_index.max()) >= count:
        raise ValueError(f"faces: expected the {int(fragments.face_index.max()) + 1} or more triangles the fragments "
                         f"were rasterised from, got {count}")
    batch = dims["B"]
    if count == 0:  # no triangle, no foreground
        height, width = fragments.face_index.shape[1:]
        return attributes.new_zeros(batch, dims["C"], height, width)
    faces = faces.to(device=attributes.device, dtype=torch.long)
    face = fragments.face_index.clamp(min=0)  # (B, H, W)
    corner = faces[face]  # (B, H, W, 3)
    b = torch.arange(batch, device=attributes.device).view(batch, 1, 1, 1)
    values = attributes[b, corner]  # (B, H, W, 3, C)
    out = (values * fragments.barycentric[..., None]).sum(-2)
    out = torch.where(fragments.mask[..., None], out, torch.zeros_like(out))
    return out.permute(0, 3, 1, 2).contiguous()
