"""Dense-alignment overlays: projected vertices and landmarks drawn over the input image."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from facenormals.core.check import check_finite, check_floating, check_integer, check_shape
from facenormals.core.files import atomic_write

__all__ = ["draw_alignment", "normal_map_to_image"]


def normal_map_to_image(normal_map: Tensor) -> np.ndarray:
    """A ``(3, H, W)`` camera-frame normal map as an RGB ``uint8`` image ``(H, W, 3)``.

    Uses the common colour coding ``rgb = (n + 1) / 2`` with the y and z axes flipped, so that a
    surface facing the camera is light blue and "up" is green; background stays black.

    Example:
        >>> nmap = torch.zeros(3, 2, 2); nmap[2] = -1.0
        >>> normal_map_to_image(nmap)[0, 0].tolist()
        [128, 128, 255]
    """
    check_shape(normal_map, [3, "H", "W"], "normal_map")
    check_floating(normal_map, "normal_map")
    check_finite(normal_map, "normal_map")  # NaN normals would be drawn as background
    n = normal_map.detach().cpu().float()
    foreground = n.norm(dim=0) > 0.5
    rgb = torch.stack([n[0], -n[1], -n[2]]) * 0.5 + 0.5
    rgb = torch.where(foreground[None], rgb, torch.zeros_like(rgb))
    return (rgb.clamp(0, 1) * 255).round().to(torch.uint8).permute(1, 2, 0).numpy()


def draw_alignment(
    image: np.ndarray,
    vertex_pixels: Tensor,
    landmark_pixels: Tensor | None = None,
    visible: Tensor | None = None,
    path: str | Path | None = None,
    scale: int = 4,
    max_points: int = 4000,
) -> np.ndarray:
    """Draw projected vertices (small dots) and landmarks (circles) over an RGB image.

    Args:
        image: ``(H, W, 3)`` or ``(H, W)`` uint8 RGB image.
        vertex_pixels: ``(N, 2)`` projected vertices in the image's pixel coordinates (non-finite
            rows and points far outside the image, e.g. of vertices behind the camera, are skipped).
        landmark_pixels: optional ``(L, 2)`` landmarks (NaN rows are skipped).
        visible: optional ``(N,)`` bool: only visible vertices are drawn.
        path: if given, the overlay is written there as PNG.
        scale: upsampling of the image before drawing, so that dots stay thin on small crops.
        max_points: at most this many vertices are drawn (evenly subsampled).

    Returns:
        The ``(scale·H, scale·W, 3)`` RGB overlay.

    Raises:
        ValueError: naming the argument of a wrong shape or dtype.
        OSError: naming ``path`` when the PNG cannot be written.
    """
    import cv2

    dims = check_shape(vertex_pixels, ["N", 2], "vertex_pixels")
    if visible is not None:
        check_shape(visible, [dims["N"]], "visible")
        if visible.dtype != torch.bool:
            raise ValueError(f"visible: expected a bool mask, got dtype {visible.dtype}")
    if landmark_pixels is not None:
        check_shape(landmark_pixels, ["L", 2], "landmark_pixels")
    scale = check_integer(scale, "scale", minimum=1)
    max_points = check_integer(max_points, "max_points", minimum=1)
    img = np.asarray(image)
    if img.ndim == 2:
        img = np.repeat(img[..., None], 3, axis=2)
    if img.ndim != 3 or img.shape[2] != 3 or img.dtype != np.uint8:
        raise ValueError(f"image: expected a uint8 (H, W, 3) or (H, W) array, got {img.dtype} {img.shape}")
    if img.shape[0] < 1 or img.shape[1] < 1:  # cv2.resize fails on an empty image
        raise ValueError(f"image: expected a non-empty image (H, W >= 1), got shape {img.shape}")
    out = cv2.resize(img, (img.shape[1] * scale, img.shape[0] * scale), interpolation=cv2.INTER_NEAREST)
    points = vertex_pixels.detach().cpu().double()
    if visible is not None:
        points = points[visible.detach().cpu()]
    if points.shape[0] > max_points:
        points = points[torch.linspace(0, points.shape[0] - 1, max_points).long()]
    for u, v in _on_canvas(points, scale, img.shape[:2]):
        cv2.circle(out, (u, v), max(1, scale // 4) << _SHIFT, (255, 220, 0), -1, cv2.LINE_AA, _SHIFT)
    if landmark_pixels is not None:
        for u, v in _on_canvas(landmark_pixels.detach().cpu().double(), scale, img.shape[:2]):
            cv2.circle(out, (u, v), scale << _SHIFT, (255, 60, 60), 2, cv2.LINE_AA, _SHIFT)
    if path is not None:
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        with atomic_write(path) as part:
            try:
                written = cv2.imwrite(str(part), cv2.cvtColor(out, cv2.COLOR_RGB2BGR))
            except cv2.error:  # no writer for the suffix
                written = False
            if not written:
                raise OSError(f"{path}: cannot write the overlay (a .png or other image suffix is needed)")
    return out


#: Fractional bits of the drawn centres (OpenCV's ``shift``): dots sit at sub-pixel positions of the canvas.
_SHIFT = 4


def _on_canvas(points: Tensor, scale: int, size: tuple[int, int]) -> list[list[int]]:
    """Upsampled centres of the finite ``points`` that land on or near the canvas, in fixed point
    with :data:`_SHIFT` fractional bits.

    Pixel (0, 0) covers [-0.5, 0.5]; its upsampled centre is ``scale * (u + 0.5) - 0.5``.
    """
    centres = (points + 0.5) * scale - 0.5
    margin = 2 * scale  # a circle centred just outside still shows its edge
    inside = torch.isfinite(centres).all(1)
    inside &= (centres[:, 0] > -margin) & (centres[:, 0] < size[1] * scale + margin)
    inside &= (centres[:, 1] > -margin) & (centres[:, 1] < size[0] * scale + margin)
    return (centres[inside] * (1 << _SHIFT)).round().long().tolist()
