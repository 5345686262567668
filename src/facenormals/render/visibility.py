"""Vertex visibility: front-facing, inside the image and not hidden behind another surface."""

from __future__ import annotations

import torch
from torch import Tensor

from facenormals.core.check import (
    check_finite,
    check_floating,
    check_image_size,
    check_integer,
    check_nonnegative,
    check_real,
    check_same_dtype_device,
    check_shape,
)

__all__ = ["splat_zbuffer", "unoccluded_points", "visible_vertices"]


def visible_vertices(
    pixels: Tensor,
    depth: Tensor,
    camera_normals: Tensor,
    camera_points: Tensor,
    zbuffer: Tensor,
    tolerance: float = 3.0,
    min_facing: float = 0.0,
) -> Tensor:
    r"""Which vertices the camera sees.

    A vertex is visible when it is front-facing (its normal points towards the camera,
    :math:`n \cdot X_c / \lVert X_c \rVert < -\text{min\_facing}`), it projects inside the image,
    and its depth is at most ``tolerance`` (mm) behind the z-buffer at its position (read as in
    :func:`unoccluded_points`).

    Args:
        pixels: projected vertices ``(u, v)``.
        depth: their camera-frame depths.
        camera_normals: vertex normals in the camera frame.
        camera_points: vertices in the camera frame.
        zbuffer: the depth map of the same mesh, e.g. :func:`~facenormals.render.rasterize_depth`
            (``inf`` on background).
        tolerance: depth slack in mm, for the surface's curvature between pixel centres.
        min_facing: cosine margin of the front-facing test; e.g. 0.2 drops grazing vertices near
            the silhouette, whose normals a pixel grid samples poorly.

    Returns:
        ``(B, N)`` bool visibility.

    Shape:
        - pixels: :math:`(B, N, 2)`; depth: :math:`(B, N)`; camera_normals, camera_points: :math:`(B, N, 3)`
        - zbuffer: :math:`(B, H, W)`

    Example:
        >>> uv = torch.tensor([[[1.0, 1.0]]]); z = torch.tensor([[5.0]])
        >>> visible_vertices(uv, z, torch.tensor([[[0.0, 0.0, -1.0]]]), torch.tensor([[[0.0, 0.0, 5.0]]]),
        ...                  torch.full((1, 3, 3), 5.0))
        tensor([[True]])
    """
    dims = check_shape(pixels, ["B", "N", 2], "pixels")
    check_shape(camera_normals, ["B", "N", 3], "camera_normals", dims)
    check_shape(camera_points, ["B", "N", 3], "camera_points", dims)
    check_floating(camera_normals, "camera_normals")
    check_floating(camera_points, "camera_points")
    check_finite(camera_normals, "camera_normals")  # NaN would silently read as "not facing"
    check_finite(camera_points, "camera_points")
    min_facing = check_real(min_facing, "min_facing")
    with torch.no_grad():
        facing = (camera_normals * camera_points).sum(-1) / camera_points.norm(dim=-1).clamp_min(1e-12)
        front = facing < -min_facing
    return front & unoccluded_points(pixels, depth, zbuffer, tolerance)


def _nearest_pixel(pixels: Tensor) -> tuple[Tensor, Tensor]:
    """The pixel ``(u, v)`` whose square ``[u - 0.5, u + 0.5) x [v - 0.5, v + 0.5)`` holds each point,
    the same rule on every edge of the image (``torch.round`` rounds half to even: ``W - 0.5`` fell
    inside for odd ``W`` only); a point that projects nowhere (NaN) goes to ``-1``, outside. In at
    least float32: ``x + 0.5`` in float16 (bfloat16) rounds whole numbers above 1024 (128) up."""
    work = pixels.to(torch.promote_types(pixels.dtype, torch.float32))
    rounded = torch.floor(work + 0.5).nan_to_num(nan=-1.0)
    return rounded[..., 0], rounded[..., 1]


def _flat_index(u: Tensor, v: Tensor, height: int, width: int) -> Tensor:
    """``v * W + u`` of the clamped pixel, in integers: float16 holds whole numbers exactly only up
    to 2048 (bfloat16 256), so the product in the pixels' dtype would name a neighbouring pixel."""
    return v.clamp(0, height - 1).long() * width + u.clamp(0, width - 1).long()


def _surface_depth(pixels: Tensor, nearest_u: Tensor, nearest_v: Tensor, zbuffer: Tensor) -> Tensor:
    """The z-buffer's depth ``(B, N)`` at sub-pixel positions: ``1/z`` interpolated bilinearly between
    the four pixel centres around each point (exact on a plane, whose ``1/z`` is affine in the
    pixels). Where one of the four is background or outside the image, the plane through the other
    three stands in for it (``c_k = c_i + c_j - c_opposite``), as exact on a plane; where more are
    missing, or that plane gives no positive ``1/z`` at the point, the depth at the nearest pixel
    ``(nearest_u, nearest_v)`` (:func:`_nearest_pixel`). Points that project nowhere (NaN) read the
    pixel ``(-1, -1)``, clamped (they are outside anyway)."""
    batch, height, width = zbuffer.shape
    work = torch.promote_types(zbuffer.dtype, torch.float32)
    flat = zbuffer.to(work).reshape(batch, height * width)
    uv = pixels.to(work).nan_to_num(nan=-1.0)
    u0, v0 = torch.floor(uv[..., 0]), torch.floor(uv[..., 1])
    fu, fv = uv[..., 0] - u0, uv[..., 1] - v0
    inverses, valid = [], []
    for du, dv in ((0, 0), (1, 0), (0, 1), (1, 1)):
        corner = torch.gather(flat, 1, _flat_index(u0 + du, v0 + dv, height, width))
        ok = (u0 + du >= 0) & (u0 + du <= width - 1) & (v0 + dv >= 0) & (v0 + dv <= height - 1) & torch.isfinite(corner)
        valid.append(ok)
        inverses.append(torch.where(ok, 1.0 / corner, torch.zeros((), dtype=work, device=corner.device)))
    inverse, valid = torch.stack(inverses, -1), torch.stack(valid, -1)  # (B, N, 4), corners 00, 10, 01, 11
    count = valid.sum(-1)
    # a missing corner k from the others: the sum of its two neighbours minus its opposite (3 - k)
    completed = inverse.sum(-1, keepdim=True) - 2.0 * inverse.flip(-1)
    inverse = torch.where(valid, inverse, completed)
    weights = torch.stack([(1 - fu) * (1 - fv), fu * (1 - fv), (1 - fu) * fv, fu * fv], -1)
    at_point = (weights * inverse).sum(-1)
    use = (count == 4) | ((count == 3) & (at_point > 0))
    nearest = torch.gather(flat, 1, _flat_index(nearest_u, nearest_v, height, width))
    return torch.where(use, 1.0 / at_point, nearest)


@torch.no_grad()
def unoccluded_points(pixels: Tensor, depth: Tensor, zbuffer: Tensor, tolerance: float = 3.0) -> Tensor:
    r"""Which points project inside the image, in front of the camera, and at most ``tolerance`` (mm)
    behind the z-buffer at their position: the occlusion half of :func:`visible_vertices`, without
    its front-facing test (e.g. for landmarks, whose surface may face away at the outline).

    A point is inside the image when the square of a pixel holds it: pixel ``(u, v)`` (centre at
    integer coordinates) covers ``[u - 0.5, u + 0.5) x [v - 0.5, v + 0.5)``, so the image spans
    ``[-0.5, W - 0.5) x [-0.5, H - 0.5)``.

    The z-buffer is read at each point's sub-pixel position: its inverse depth is interpolated
    bilinearly between the four pixel centres around the point, which is exact on a plane (whose
    :math:`1/z` is affine in the pixel coordinates), so a sloped surface does not hide its own
    vertices however coarse the pixels. Where one of the four centres is background or outside the
    image, the plane through the other three stands in for it, as exact on a plane; where two or
    more are, the nearest pixel's depth is used (within a pixel of a silhouette, the ``tolerance``
    must then cover the surface's slope over up to half a pixel).

    Args:
        pixels: projected points ``(u, v)``.
        depth: their camera-frame depths, finite where the pixels are.
        zbuffer: a depth map, depths > 0 and ``inf`` on background, e.g.
            :func:`~facenormals.render.rasterize_depth`; 0 or negative values (OpenGL's and
            pyrender's background is 0) are an error, they would hide every point behind them.
        tolerance: depth slack in mm, for the surface's curvature between pixel centres.

    Returns:
        ``(B, N)`` bool; False for points that project nowhere (NaN pixels).

    Raises:
        ValueError: for mismatched shapes, non-floating inputs, a NaN or non-positive z-buffer value,
            a non-finite depth at a finite pixel, or a negative or NaN ``tolerance``.

    Shape:
        - pixels: :math:`(B, N, 2)`; depth: :math:`(B, N)`; zbuffer: :math:`(B, H, W)`

    Example:
        >>> zbuffer = torch.full((1, 3, 3), 5.0)
        >>> unoccluded_points(torch.tensor([[[1.0, 1.0], [1.0, 1.0], [4.0, 1.0]]]), torch.tensor([[7.0, 9.0, 5.0]]),
        ...                   zbuffer)
        tensor([[ True, False, False]])
    """
    dims = check_shape(pixels, ["B", "N", 2], "pixels")
    check_shape(depth, ["B", "N"], "depth", dims)
    zdims = check_shape(zbuffer, ["B", "H", "W"], "zbuffer", dims)
    for name, x in (("pixels", pixels), ("depth", depth), ("zbuffer", zbuffer)):
        check_floating(x, name)
    check_finite(zbuffer, "zbuffer", allow_inf=True)  # inf is background, NaN would hide every point
    # 0 (OpenGL's and pyrender's background) or a negative depth would hide every point behind it
    if zbuffer.numel() and not torch.compiler.is_compiling() and not bool(zbuffer.amin() > 0):
        bad = int((zbuffer <= 0).sum())
        raise ValueError(f"zbuffer: expected depths > 0 with inf on background, got {bad} values <= 0 "
                         f"(minimum {float(zbuffer.amin()):g})")
    # a NaN depth would read as hidden, silently; a point that projects nowhere may carry anything
    check_finite(depth.masked_fill(~torch.isfinite(pixels).all(-1), 0.0), "depth")
    tolerance = check_nonnegative(tolerance, "tolerance")  # NaN would hide every point
    height, width = zdims["H"], zdims["W"]
    if height < 1 or width < 1:
        raise ValueError(f"zbuffer: expected H, W >= 1, got shape {tuple(zbuffer.shape)}")
    u, v = _nearest_pixel(pixels)
    inside = (u >= 0) & (u <= width - 1) & (v >= 0) & (v <= height - 1) & (depth > 0)
    return inside & (depth <= _surface_depth(pixels, u, v, zbuffer) + tolerance)


@torch.no_grad()
def splat_zbuffer(pixels: Tensor, depth: Tensor, image_size: tuple[int, int], radius: int = 1) -> Tensor:
    """A fast approximate z-buffer: the nearest vertex depth per pixel, spread over a ``(2r+1)²`` window.

    Each vertex writes its depth to its nearest pixel (``scatter_reduce`` with ``amin``), then the
    empty pixels between vertices take the minimum of their ``(2r+1)²`` neighbourhood. On a mesh whose vertices are
    about as dense as the pixels (ICT-FaceKit at 128²) this agrees with the exact
    :func:`~facenormals.render.rasterize_triangles` depth for the visibility test of
    :func:`visible_vertices` except within a pixel or two of depth discontinuities, at a fraction of
    the cost. Background is ``inf``.

    A vertex goes to the pixel whose square holds it, as in :func:`unoccluded_points`: pixel
    ``(u, v)`` covers ``[u - 0.5, u + 0.5) x [v - 0.5, v + 0.5)``. Vertices outside the image, at
    depth ``<= 0`` (behind the camera) or that project nowhere (NaN or infinite pixels) are left out;
    a vertex at a finite pixel needs a finite depth, as in :func:`unoccluded_points`.

    Raises:
        ValueError: for mismatched shapes or dtypes, a bad ``image_size`` or ``radius``, or a NaN or
            infinite depth at a finite pixel.

    Shape:
        - pixels: :math:`(B, N, 2)`; depth: :math:`(B, N)` → :math:`(B, H, W)`

    Example:
        >>> z = splat_zbuffer(torch.tensor([[[1.0, 1.0], [1.2, 0.9]]]), torch.tensor([[5.0, 4.0]]), (3, 3), 0)
        >>> z[0, 1, 1].item(), bool(torch.isinf(z[0, 0, 0]))
        (4.0, True)
    """
    dims = check_shape(pixels, ["B", "N", 2], "pixels")
    check_shape(depth, ["B", "N"], "depth", dims)
    check_floating(pixels, "pixels")
    check_floating(depth, "depth")
    check_same_dtype_device(pixels, "pixels", depth=depth)
    height, width = check_image_size(image_size)
    radius = check_integer(radius, "radius", minimum=0)
    # a NaN pixel projects nowhere; a NaN or infinite depth at a finite pixel is a bug (unoccluded_points
    # refuses it too)
    lost = ~torch.isfinite(depth) & torch.isfinite(pixels).all(-1)
    if bool(lost.any()):
        raise ValueError(f"depth: expected a finite depth for every finite pixel, got {int(lost.sum())} NaN or "
                         f"infinite")
    batch = dims["B"]
    u, v = _nearest_pixel(pixels)
    ok = (u >= 0) & (u <= width - 1) & (v >= 0) & (v <= height - 1) & (depth > 0)  # finite where u, v are
    index = _flat_index(u, v, height, width)
    values = torch.where(ok, depth, torch.full_like(depth, float("inf")))
    zbuf = torch.full((batch, height * width), float("inf"), dtype=depth.dtype, device=depth.device)
    zbuf.scatter_reduce_(1, index, values, reduce="amin")
    zbuf = zbuf.view(batch, 1, height, width)
    if radius > 0:  # fill only the empty pixels: a min-filter everywhere would hide sloped surfaces
        size = 2 * radius + 1
        filled = -torch.nn.functional.max_pool2d(-zbuf, size, stride=1, padding=radius)
        zbuf = torch.where(torch.isinf(zbuf), filled, zbuf)
    return zbuf.view(batch, height, width)
