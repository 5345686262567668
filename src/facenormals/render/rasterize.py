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


def _bucket_sizes(extent: Tensor) -> list[int]:
    sizes = []
    size = 2
    top = int(extent.max()) if extent.numel() else 0
    while True:
        sizes.append(size)
        if size > top:
            return sizes
        size *= 2


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
    in buckets of triangles by bounding-box size; ``pixel`` is the flat index ``(b H + v) W + u``."""
    device = pixels.device
    work = torch.float64
    faces = faces.to(device=device, dtype=torch.long)
    tri_uv = pixels.to(work)[:, faces]  # (B, F, 3, 2)
    tri_z = depth.to(work)[:, faces]  # (B, F, 3)
    p0, p1, p2 = tri_uv.unbind(2)
    area = (p1[..., 0] - p0[..., 0]) * (p2[..., 1] - p0[..., 1]) - (p1[..., 1] - p0[..., 1]) * (p2[..., 0] - p0[..., 0])
    valid = (tri_z > near).all(-1) & torch.isfinite(tri_uv).all(-1).all(-1) & (area.abs() > 1e-12)
    if cull_backfaces:  # facing the camera: counter-clockwise on screen, i.e. area < 0 with v pointing down
        valid &= area < 0
    lo = torch.ceil(tri_uv.amin(2) - 1e-9).clamp(min=0)
    hi = torch.floor(tri_uv.amax(2) + 1e-9)
    hi = torch.minimum(hi, torch.tensor([width - 1, height - 1], dtype=work, device=device))
    valid &= (hi >= lo).all(-1)
    extent = torch.where(valid[..., None], hi - lo + 1, torch.zeros_like(hi)).amax(-1)  # (B, F)
    previous = 0
    for size in _bucket_sizes(extent):
        in_bucket = valid & (extent > previous) & (extent <= size)
        previous = size
        b_idx, f_idx = torch.nonzero(in_bucket, as_tuple=True)
        if b_idx.numel() == 0:
            continue
        offsets = torch.arange(size, device=device, dtype=work)
        du, dv = torch.meshgrid(offsets, offsets, indexing="xy")
        pu = lo[b_idx, f_idx, 0, None] + du.reshape(1, -1)  # (T, size*size)
        pv = lo[b_idx, f_idx, 1, None] + dv.reshape(1, -1)
        q0, q1, q2 = p0[b_idx, f_idx], p1[b_idx, f_idx], p2[b_idx, f_idx]
        a = area[b_idx, f_idx, None]
        w0 = ((q1[:, None, 0] - pu) * (q2[:, None, 1] - pv) - (q1[:, None, 1] - pv) * (q2[:, None, 0] - pu)) / a
        w1 = ((q2[:, None, 0] - pu) * (q0[:, None, 1] - pv) - (q2[:, None, 1] - pv) * (q0[:, None, 0] - pu)) / a
        w2 = 1.0 - w0 - w1
        screen = torch.stack([w0, w1, w2], -1)
        inside = (screen >= -1e-9).all(-1) & (pu <= hi[b_idx, f_idx, 0, None]) & (pv <= hi[b_idx, f_idx, 1, None])
        t_idx, k_idx = torch.nonzero(inside, as_tuple=True)
        screen = screen[t_idx, k_idx]
        inv_z = screen / tri_z[b_idx[t_idx], f_idx[t_idx]]
        z = 1.0 / inv_z.sum(-1)
        pix = (b_idx[t_idx] * height + pv[t_idx, k_idx].long()) * width + pu[t_idx, k_idx].long()
        yield pix, f_idx[t_idx], z, (inv_z * z[:, None] if barycentric else None)


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
    screen-space barycentrics are all ≥ 0 (up to 1e-9). Among covering triangles the nearest wins.
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
    face_index = torch.full((num_pixels,), -1, dtype=torch.long, device=device)
    barycentric = torch.zeros(num_pixels, 3, dtype=work, device=device)
    for pix, face, z, bary in candidates:
        win = z == zbuf[pix]
        face_index[pix[win]] = face[win]
        barycentric[pix[win]] = bary[win]
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
    pixel's winning face and its barycentrics saves ~10 % (the coverage tests dominate). Same
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
    dims = check_shape(attributes, ["B", "N", "C"], "attributes")
    check_floating(attributes, "attributes")  # barycentric weights would round to 0 or 1
    check_shape(fragments.face_index, ["B", "H", "W"], "fragments.face_index", dims)
    count = check_faces(faces, dims["N"])["F"]
    if fragments.face_index.numel() and int(fragments.face_index.max()) >= count:
        raise ValueError(f"faces: expected the {int(fragments.face_index.max()) + 1} or more triangles the fragments "
                         f"were rasterised from, got {count}")
    faces = faces.to(device=attributes.device, dtype=torch.long)
    batch = dims["B"]
    face = fragments.face_index.clamp(min=0)  # (B, H, W)
    corner = faces[face]  # (B, H, W, 3)
    b = torch.arange(batch, device=attributes.device).view(batch, 1, 1, 1)
    values = attributes[b, corner]  # (B, H, W, 3, C)
    out = (values * fragments.barycentric.to(attributes.dtype)[..., None]).sum(-2)
    out = torch.where(fragments.mask[..., None], out, torch.zeros_like(out))
    return out.permute(0, 3, 1, 2).contiguous()
