r"""Residual functions of the fitting energy.

Every term's energy is :math:`E = \tfrac12 \sum r^2` and enters the total energy with a weight
:math:`\lambda`. Each function takes ``weight`` (:math:`\lambda`) and returns residuals already
multiplied by :math:`\sqrt{\lambda}`, so that

.. math::

    \tfrac12 \lVert r \rVert^2 = \lambda\, E_\text{term},

and stacking the residuals of all terms gives the least-squares problem that Gauss-Newton /
Levenberg-Marquardt minimise. Masked entries (invisible vertices, vertices off the foreground,
missing landmarks) are **exactly zero** and have a zero gradient; they are selected with
``torch.where`` so that NaN or infinite values under a mask never leak into values or gradients.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from facenormals.core.check import (
    check_all_finite, check_floating, check_nonnegative, check_same_dtype_device, check_shape, values_readable,
)
from facenormals.sampling.bicubic import sample_bicubic

__all__ = ["landmark_residuals", "normal_residuals", "prior_residuals"]


def _check_mask(mask: Tensor | None, name: str, dims: dict[str, int], count: str, device: torch.device) -> None:
    if mask is None:
        return
    check_shape(mask, ["B", count], name, dims)
    if mask.dtype != torch.bool:
        raise ValueError(f"{name}: expected a bool tensor, got dtype {mask.dtype}")
    if mask.device != device:
        raise ValueError(f"{name}: expected device {device}, got {mask.device}")


def _counted(x: Tensor, mask: Tensor | None) -> Tensor:
    """``x`` (detached) with the rows of points that do not count (``mask`` False) zeroed, for the
    finiteness checks: such points may carry anything."""
    x = x.detach()
    return x if mask is None else x.masked_fill(~mask[..., None], 0.0)


def _support_foreground(normal_map: Tensor) -> Tensor:
    """``(B, H W)``: whether the bilinear support of a point whose floor is pixel ``(v0, u0)`` (entry
    ``v0 W + u0``), i.e. pixels ``v0 .. v0 + 1`` x ``u0 .. u0 + 1`` clamped to the image, is all
    foreground. A pixel is foreground when its map normal has norm > 0.5."""
    B, _, H, W = normal_map.shape
    fg = normal_map.detach().square().sum(dim=1) > 0.25  # (B, H, W), |n| > 0.5
    fg = fg & torch.cat([fg[:, :, 1:], fg[:, :, -1:]], dim=2)  # and the next column (clamped)
    fg = fg & torch.cat([fg[:, 1:], fg[:, -1:]], dim=1)  # and the next row
    return fg.reshape(B, H * W)


def _foreground(normal_map: Tensor, pixels: Tensor) -> Tensor:
    """True where all 4 nearest pixels (the bilinear support) of ``pixels`` are foreground.

    Taps are clamped to the image, so the result is meaningful for points inside the image.
    ``(B, 3, H, W), (B, N, 2) -> (B, N)``.
    """
    return _foreground_at(_support_foreground(normal_map), pixels, normal_map.shape[-2:])


def _foreground_at(support: Tensor, pixels: Tensor, size: tuple[int, int]) -> Tensor:
    """:func:`_foreground` from the maps' :func:`_support_foreground` ``(B, H W)`` (kept by a caller
    whose maps are fixed over many calls) and their ``size`` ``(H, W)``."""
    H, W = size
    finite = torch.isfinite(pixels).all(dim=-1)
    safe = torch.where(finite[..., None], pixels.detach(), torch.zeros((), dtype=pixels.dtype, device=pixels.device))
    u0 = torch.floor(safe[..., 0]).clamp(0.0, float(W - 1)).to(torch.int64)
    v0 = torch.floor(safe[..., 1]).clamp(0.0, float(H - 1)).to(torch.int64)
    return torch.gather(support, 1, v0 * W + u0) & finite


def normal_residuals(
    normal_map: Tensor,
    pixels: Tensor,
    normals: Tensor,
    visible: Tensor | None = None,
    weight: float = 1.0,
) -> tuple[Tensor, Tensor]:
    r"""Normal-map residuals :math:`r_i = \sqrt{\lambda}\,(N(a_i) - n_i)`.

    :math:`N(a_i)` is the predicted normal map sampled bicubically (:func:`sample_bicubic`, OpenCV
    ``INTER_CUBIC``) at the projected vertex :math:`a_i`, and :math:`n_i` the model's vertex normal
    in the camera frame. A vertex is *valid* when it is visible, its projection lies inside the
    image and all 4 nearest pixels of :math:`a_i` (its bilinear support) are foreground, i.e. have a
    map normal of norm > 0.5 (normal maps are zero on background). Residuals of invalid vertices
    are exactly zero, with zero gradient, so that

    .. math::

        \tfrac12 \lVert r \rVert^2 = \lambda \cdot \tfrac12 \sum_{i\ \text{valid}}
        \lVert N(a_i) - n_i \rVert^2 .

    The sampled normals are not renormalised. Differentiable w.r.t. ``normal_map``, ``pixels`` and
    ``normals``.

    Args:
        normal_map: predicted unit normals in the camera frame, zero on background.
        pixels: projected vertices :math:`a_i` as ``(u, v)`` in pixels.
        normals: model vertex normals :math:`n_i` in the camera frame.
        visible: optional visibility mask (e.g. from a z-buffer); ``None`` means all visible.
        weight: the term weight :math:`\lambda \ge 0`.

    Returns:
        ``(residuals, valid)``.

    Raises:
        ValueError: on wrong shapes, mismatched batch or vertex counts, non-floating inputs,
            mismatched dtypes, a non-bool ``visible``, a negative ``weight``, a non-finite
            ``normal_map``, or non-finite ``pixels`` or ``normals`` of vertices marked visible.

    Shape:
        - normal_map: :math:`(B, 3, H, W)`
        - pixels: :math:`(B, N, 2)`
        - normals: :math:`(B, N, 3)`
        - visible: :math:`(B, N)`, bool
        - residuals: :math:`(B, N, 3)`
        - valid: :math:`(B, N)`, bool

    Example:
        >>> normal_map = torch.zeros(1, 3, 4, 4)
        >>> normal_map[:, 2] = -1.0  # every pixel faces the camera
        >>> normal_map[:, :, :, 3] = 0.0  # ... except the last column (background)
        >>> pixels = torch.tensor([[[1.0, 1.0], [2.5, 1.0], [1.0, 1.0]]])
        >>> normals = torch.tensor([[[0.0, 0.6, -0.8], [0.0, 0.0, -1.0], [0.0, 0.0, -1.0]]])
        >>> r, valid = normal_residuals(normal_map, pixels, normals, torch.tensor([[True, True, False]]))
        >>> r, valid
        (tensor([[[ 0.0000, -0.6000, -0.2000],
                 [ 0.0000,  0.0000,  0.0000],
                 [ 0.0000,  0.0000,  0.0000]]]), tensor([[ True, False, False]]))
    """
    dims = check_shape(normal_map, ["B", 3, "H", "W"], "normal_map")
    check_shape(pixels, ["B", "N", 2], "pixels", dims)
    check_shape(normals, ["B", "N", 3], "normals", dims)
    for name, x in (("normal_map", normal_map), ("pixels", pixels), ("normals", normals)):
        check_floating(x, name)
    check_same_dtype_device(normal_map, "normal_map", pixels=pixels, normals=normals)
    _check_mask(visible, "visible", dims, "N", normal_map.device)
    # a NaN would read as background, or a NaN pixel as outside, and the vertices drop out silently;
    # vertices marked invisible may carry anything
    check_all_finite(normal_map=normal_map, pixels=_counted(pixels, visible), normals=_counted(normals, visible))
    scale = math.sqrt(check_nonnegative(weight, "weight"))

    sampled, inside = sample_bicubic(normal_map, pixels)
    valid = inside & _foreground(normal_map, pixels)
    if visible is not None:
        valid = valid & visible
    zero = torch.zeros((), dtype=normals.dtype, device=normals.device)
    safe_normals = torch.where(valid[..., None], normals, zero)
    residuals = torch.where(valid[..., None], sampled - safe_normals, zero)
    if scale != 1.0:
        residuals = residuals * scale
    return residuals, valid


def landmark_residuals(
    pixels: Tensor,
    targets: Tensor,
    mask: Tensor | None = None,
    weight: float = 1.0,
) -> Tensor:
    r"""Landmark residuals :math:`r_j = \sqrt{\lambda}\,(z_j - b_j)`.

    :math:`z_j` is the projected model landmark and :math:`b_j` the detected one. Entries with a
    ``False`` mask (missing landmarks) are exactly zero with zero gradient; their targets may be
    NaN. Differentiable w.r.t. ``pixels`` and ``targets``.

    Args:
        pixels: projected model landmarks :math:`z_j` as ``(u, v)`` in pixels.
        targets: detected landmarks :math:`b_j` in pixels.
        mask: optional, ``True`` where the landmark is present; ``None`` uses every landmark.
        weight: the term weight :math:`\lambda \ge 0`.

    Returns:
        The residuals.

    Raises:
        ValueError: on wrong shapes, mismatched batch or landmark counts, non-floating inputs,
            mismatched dtypes, a non-bool ``mask``, a negative ``weight``, or non-finite ``pixels``
            or ``targets`` of landmarks in use.

    Shape:
        - pixels: :math:`(B, L, 2)`
        - targets: :math:`(B, L, 2)`
        - mask: :math:`(B, L)`, bool
        - output: :math:`(B, L, 2)`

    Example:
        >>> z = torch.tensor([[[10.0, 20.0], [30.0, 40.0]]])
        >>> b = torch.tensor([[[11.0, 18.0], [float("nan"), float("nan")]]])
        >>> landmark_residuals(z, b, torch.tensor([[True, False]]), weight=4.0)
        tensor([[[-2.,  4.],
                 [ 0.,  0.]]])
    """
    dims = check_shape(pixels, ["B", "L", 2], "pixels")
    check_shape(targets, ["B", "L", 2], "targets", dims)
    check_floating(pixels, "pixels")
    check_floating(targets, "targets")
    check_same_dtype_device(pixels, "pixels", targets=targets)
    _check_mask(mask, "mask", dims, "L", pixels.device)
    # a NaN residual would poison the whole solve; masked-out landmarks may carry anything
    check_all_finite(pixels=_counted(pixels, mask), targets=_counted(targets, mask))
    return _landmark_differences(pixels, targets, mask, math.sqrt(check_nonnegative(weight, "weight")))


def _landmark_differences(pixels: Tensor, targets: Tensor, mask: Tensor | None, scale: float = 1.0) -> Tensor:
    """:func:`landmark_residuals` without its input checks, for solver loops whose inputs were
    checked once (a pre-alignment's or a fit's LM iterations), with ``scale`` = √λ."""
    if mask is None:
        residuals = pixels - targets
    else:
        zero = torch.zeros((), dtype=pixels.dtype, device=pixels.device)
        safe_targets = torch.where(mask[..., None], targets, zero)
        residuals = torch.where(mask[..., None], pixels - safe_targets, zero)
    if scale != 1.0:
        residuals = residuals * scale
    return residuals


def prior_residuals(coeffs: Tensor, std: Tensor, weight: float = 1.0) -> Tensor:
    r"""Gaussian prior residuals :math:`r = \sqrt{\lambda}\, y / \sigma`.

    For a diagonal covariance :math:`C = \operatorname{diag}(\sigma^2)`,
    :math:`\tfrac12 \lVert r \rVert^2 = \lambda \cdot \tfrac12\, y^\top C^{-1} y`.
    Differentiable w.r.t. ``coeffs`` (and ``std``).

    Args:
        coeffs: model coefficients :math:`y`.
        std: standard deviations :math:`\sigma > 0`, shared by the batch ``(K,)`` or per sample
            ``(B, K)``.
        weight: the term weight :math:`\lambda \ge 0`.

    Returns:
        The residuals.

    Raises:
        ValueError: on wrong shapes, non-floating inputs, mismatched dtypes, non-finite ``coeffs``,
            ``std`` not finite and > 0 (both checked outside ``torch.compile`` and ``torch.func``
            transforms only) or a negative ``weight``.

    Shape:
        - coeffs: :math:`(B, K)`
        - std: :math:`(K,)` or :math:`(B, K)`
        - output: :math:`(B, K)`

    Example:
        >>> prior_residuals(torch.tensor([[1.0, -3.0]]), torch.tensor([2.0, 3.0]))
        tensor([[ 0.5000, -1.0000]])
    """
    dims = check_shape(coeffs, ["B", "K"], "coeffs")
    if isinstance(std, Tensor) and std.dim() == 1:
        check_shape(std, ["K"], "std", dims)
    else:
        check_shape(std, ["B", "K"], "std", dims)
    check_floating(coeffs, "coeffs")
    check_floating(std, "std")
    check_same_dtype_device(coeffs, "coeffs", std=std)
    scale = math.sqrt(check_nonnegative(weight, "weight"))
    check_all_finite(coeffs=coeffs.detach(), std=std.detach())
    if values_readable(std) and not bool((std > 0).all()):
        raise ValueError(f"std: expected values > 0, got {int((~(std > 0)).sum())} entries <= 0")

    residuals = coeffs / std
    if scale != 1.0:
        residuals = residuals * scale
    return residuals
