r"""Landmark maps Z: small Gaussians at the landmarks' sub-pixel positions, and their peaks.

Channel :math:`j` of :math:`Z` is

.. math::

    Z_j(u, v) = \exp\!\Big(-\frac{(u - u_j)^2 + (v - v_j)^2}{2\sigma^2}\Big)
    \quad\text{if } (u - u_j)^2 + (v - v_j)^2 \le (r\sigma)^2, \text{ else } 0,

for a visible landmark at :math:`(u_j, v_j)` (pixel centres at integers, ``docs/conventions.md``),
and all zeros for an invisible one. The value would be 1 exactly at the landmark; the largest
pixel value is at the nearest pixel. The default :math:`\sigma = 1.5` px at 128×128 (about 5 mm
on a head filling 60 % of the image) and cut-off :math:`r = 3`.
"""

from __future__ import annotations

import torch
from torch import Tensor

from facenormals.core.check import (check_finite, check_floating, check_image_size, check_nonnegative, check_positive,
                                    check_shape)

__all__ = ["landmark_maps", "landmarks_from_maps"]

#: Default Gaussian standard deviation of the landmark maps, in pixels.
DEFAULT_SIGMA = 1.5


def landmark_maps(
    points: Tensor,
    visible: Tensor | None,
    image_size: tuple[int, int],
    sigma: float = DEFAULT_SIGMA,
    radius: float = 3.0,
) -> Tensor:
    r"""Rasterise landmark maps :math:`Z` from landmark pixels.

    Args:
        points: landmark pixels ``(u, v)``.
        visible: which landmarks are drawn (``None``: all finite ones); non-finite points are never drawn.
        image_size: ``(H, W)``, two integers >= 1.
        sigma: Gaussian standard deviation in pixels.
        radius: the maps are exactly 0 farther than ``radius · sigma`` from the landmark.

    Returns:
        The maps, with the dtype and device of ``points``.

    Raises:
        ValueError: on bad shapes or dtypes, or a non-positive ``sigma``/``radius``/size.

    Shape:
        - points: :math:`(B, L, 2)`; visible: :math:`(B, L)` bool
        - output: :math:`(B, L, H, W)`

    Example:
        >>> z = landmark_maps(torch.tensor([[[3.0, 2.0]]]), None, (8, 10))
        >>> z.shape, float(z[0, 0, 2, 3]), float(z[0, 0, 7, 9])
        (torch.Size([1, 1, 8, 10]), 1.0, 0.0)
    """
    dims = check_shape(points, ["B", "L", 2], "points")
    check_floating(points, "points")
    if visible is not None:
        check_shape(visible, ["B", "L"], "visible", dims)
        if visible.dtype != torch.bool:
            raise ValueError(f"visible: expected a bool tensor, got dtype {visible.dtype}")
    height, width = check_image_size(image_size)
    sigma, radius = check_nonnegative(sigma, "sigma"), check_nonnegative(radius, "radius")
    if not sigma > 0 or not radius > 0:
        raise ValueError(f"sigma, radius: expected positive values, got {sigma}, {radius}")
    if points.dtype in (torch.float16, torch.bfloat16):  # the pixel grid is inexact above 2048 (bfloat16: 256)
        return landmark_maps(points.float(), visible, image_size, sigma, radius).to(points.dtype)
    finite = torch.isfinite(points).all(-1)
    draw = finite if visible is None else finite & visible.to(points.device)
    safe = torch.where(draw[..., None], points, torch.zeros((), dtype=points.dtype, device=points.device))
    u = torch.arange(width, dtype=points.dtype, device=points.device)
    v = torch.arange(height, dtype=points.dtype, device=points.device)
    du2 = (u - safe[..., 0:1]) ** 2  # (B, L, W)
    dv2 = (v - safe[..., 1:2]) ** 2  # (B, L, H)
    d2 = dv2[..., :, None] + du2[..., None, :]
    maps = torch.exp(-d2 / (2.0 * sigma * sigma))
    keep = (d2 <= (radius * sigma) ** 2) & draw[..., None, None]
    return torch.where(keep, maps, torch.zeros((), dtype=maps.dtype, device=maps.device))


def landmarks_from_maps(maps: Tensor, threshold: float | Tensor = 0.1, eps: float = 1e-6) -> tuple[Tensor, Tensor]:
    r"""Sub-pixel landmark positions from landmark maps: the peak, refined by a parabola through the logs.

    For each channel the largest pixel is found; if it exceeds ``threshold`` its position is refined
    along u and v by the vertex of the parabola through :math:`\log Z` at the pixel and its two
    neighbours, which is exact for a Gaussian (offsets are clamped to ±0.5 px).

    Args:
        maps: landmark maps.
        threshold: a peak counts as a detection where it is greater than this: one for all
            channels, or one per channel :math:`(L,)`. The default suits exact maps (peaks of 1);
            for a network's maps pass its calibrated thresholds,
            :func:`facenormals.training.landmark_threshold` (0.525-0.825 for the shipped weights: with 0.1
            their maps "find" most hidden landmarks too).
        eps: values are clamped to at least ``eps`` before the logarithm.

    Returns:
        ``(points, found)``: ``(u, v)`` pixels (NaN where not found), in the dtype of ``maps`` but
        at least float32 (a half-precision pixel grid is too coarse for sub-pixel positions:
        bfloat16 spaces whole numbers 0.5 apart above 64), and the detection mask.

    Shape:
        - maps: :math:`(B, L, H, W)`
        - points: :math:`(B, L, 2)`; found: :math:`(B, L)` bool

    Example:
        >>> z = landmark_maps(torch.tensor([[[3.3, 1.8]]]), None, (6, 7))
        >>> points, found = landmarks_from_maps(z)
        >>> torch.allclose(points, torch.tensor([[[3.3, 1.8]]]), atol=1e-4), bool(found)
        (True, True)
    """
    dims = check_shape(maps, ["B", "L", "H", "W"], "maps")
    check_floating(maps, "maps")
    check_finite(maps, "maps")  # a NaN peak would read as "not found"
    b, l, h, w = dims["B"], dims["L"], dims["H"], dims["W"]
    if h < 1 or w < 1:
        raise ValueError(f"maps: expected H, W >= 1, got shape {tuple(maps.shape)}")
    check_positive(eps, "eps")  # log(0) made the sub-pixel offset NaN at a landmark counted as found
    if maps.dtype in (torch.float16, torch.bfloat16):  # decoded in float32, the threshold not rounded to half
        return landmarks_from_maps(maps.float(), threshold, eps)
    threshold = torch.as_tensor(threshold, dtype=maps.dtype, device=maps.device)
    if threshold.dim() != 0:
        check_shape(threshold, [l], "threshold")
    if bool(torch.isnan(threshold).any()):  # would find nothing, silently (-inf: everything is allowed)
        raise ValueError("threshold: expected numbers (or -inf to keep every peak), got NaN")
    flat = maps.reshape(b, l, h * w)
    peak, index = flat.max(-1)
    row, col = index // w, index % w
    log = torch.log(maps.clamp_min(eps))

    def offset(along: Tensor, size: int, take) -> Tensor:
        if size < 3:
            return torch.zeros(along.shape, dtype=maps.dtype, device=maps.device)
        # the parabola through the peak and its neighbours, or, at the border, through the three
        # pixels inside the image (exact for a Gaussian either way: the log is a parabola)
        centre = along.clamp(1, size - 2)
        left, mid, right = take(centre - 1), take(centre), take(centre + 1)
        curvature = left - 2.0 * mid + right
        delta = 0.5 * (left - right) / torch.where(curvature < -1e-12, curvature, torch.full_like(curvature, -1.0))
        delta = (centre - along).to(maps.dtype) + delta
        return torch.where(curvature < -1e-12, delta.clamp(-0.5, 0.5), torch.zeros_like(delta))

    def at(r: Tensor, c: Tensor) -> Tensor:
        return torch.gather(log.reshape(b, l, h * w), 2, (r * w + c)[..., None])[..., 0]

    du = offset(col, w, lambda c: at(row, c))
    dv = offset(row, h, lambda r: at(r, col))
    points = torch.stack([col.to(maps.dtype) + du, row.to(maps.dtype) + dv], dim=-1)
    found = peak > threshold
    points = torch.where(found[..., None], points, torch.full_like(points, float("nan")))
    return points, found
