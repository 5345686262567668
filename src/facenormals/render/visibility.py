"""Vertex visibility: front-facing, inside the image and not hidden behind another surface."""

from __future__ import annotations

import torch
from torch import Tensor

from facenormals.core.check import check_floating, check_shape

__all__ = ["visible_vertices"]


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
    and its depth is at most ``tolerance`` (mm) behind the z-buffer at its nearest pixel.

    Args:
        pixels: projected vertices ``(u, v)``.
        depth: their camera-frame depths.
        camera_normals: vertex normals in the camera frame.
        camera_points: vertices in the camera frame.
        zbuffer: the depth map of the same mesh, e.g. ``rasterize_triangles(...).depth``
            (``inf`` on background).
        tolerance: depth slack in mm, to allow for the z-buffer's sampling at pixel centres.
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
    check_shape(depth, ["B", "N"], "depth", dims)
    check_shape(camera_normals, ["B", "N", 3], "camera_normals", dims)
    check_shape(camera_points, ["B", "N", 3], "camera_points", dims)
    zdims = check_shape(zbuffer, ["B", "H", "W"], "zbuffer", dims)
    for name, x in (("pixels", pixels), ("depth", depth), ("zbuffer", zbuffer)):
        check_floating(x, name)
    height, width = zdims["H"], zdims["W"]
    with torch.no_grad():
        facing = (camera_normals * camera_points).sum(-1) / camera_points.norm(dim=-1).clamp_min(1e-12)
        front = facing < -min_facing
        u = torch.round(pixels[..., 0])
        v = torch.round(pixels[..., 1])
        inside = (u >= 0) & (u <= width - 1) & (v >= 0) & (v <= height - 1) & (depth > 0)
        index = (v.clamp(0, height - 1) * width + u.clamp(0, width - 1)).long()
        surface = torch.gather(zbuffer.reshape(dims["B"], -1), 1, index)
        unoccluded = depth <= surface + tolerance
        return front & inside & unoccluded
