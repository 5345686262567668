"""Lambert-shaded previews of posed meshes, for figures and overlays."""

from __future__ import annotations

import torch
from torch import Tensor

from facenormals.core.check import check_finite, check_floating, check_real, check_shape
from facenormals.render.normal_map import render_normal_map

__all__ = ["shade_normal_map", "render_shaded"]


def shade_normal_map(normal_map: Tensor, light: tuple[float, float, float] = (0.3, -0.5, -1.0), ambient: float = 0.15) -> Tensor:
    """Grey-level Lambert shading ``(B, 1, H, W)`` in [0, 1] of a camera-frame normal map ``(B, 3, H, W)``.

    ``light`` points from the surface towards the light, in the camera frame (x right, y down, z
    forward: the default comes from the upper right of the image, in front of the face). Background
    stays 0.

    Raises:
        ValueError: naming ``normal_map`` unless it is a finite floating ``(B, 3, H, W)`` tensor, ``light``
            unless it is a non-zero finite 3-vector, ``ambient`` unless it is in [0, 1].

    Example:
        >>> nmap = torch.zeros(1, 3, 2, 2); nmap[:, 2] = -1.0
        >>> shade_normal_map(nmap, light=(0.0, 0.0, -1.0), ambient=0.0)[0, 0]
        tensor([[1., 1.],
                [1., 1.]])
    """
    check_shape(normal_map, ["B", 3, "H", "W"], "normal_map")
    check_floating(normal_map, "normal_map")
    check_finite(normal_map, "normal_map")  # NaN pixels would shade as background
    try:
        direction = torch.as_tensor(light, dtype=torch.float64).reshape(-1)
    except (TypeError, ValueError, RuntimeError):
        direction = torch.zeros(0, dtype=torch.float64)
    if direction.shape != (3,) or not bool(torch.isfinite(direction).all()) or float(direction.norm()) == 0.0:
        raise ValueError(f"light: expected a non-zero finite direction (x, y, z), got {light!r}")
    if not 0.0 <= check_real(ambient, "ambient") <= 1.0:
        raise ValueError(f"ambient: expected a value in [0, 1], got {ambient}")
    direction = (direction / direction.norm()).to(dtype=normal_map.dtype, device=normal_map.device)
    lambert = (normal_map * direction[None, :, None, None]).sum(1, keepdim=True).clamp(min=0.0)
    foreground = (normal_map.norm(dim=1, keepdim=True) > 0.5).to(normal_map.dtype)
    return (ambient + (1.0 - ambient) * lambert) * foreground


def render_shaded(
    vertices: Tensor,
    faces: Tensor,
    rotation: Tensor,
    translation: Tensor,
    intrinsics: Tensor,
    image_size: tuple[int, int],
    light: tuple[float, float, float] = (0.3, -0.5, -1.0),
) -> Tensor:
    """Shaded grey image ``(B, 1, H, W)`` of a posed mesh (see :func:`render_normal_map` for the pose)."""
    normal_map, _ = render_normal_map(vertices, faces, rotation, translation, intrinsics, image_size)
    return shade_normal_map(normal_map, light)
