r"""Training loss of :class:`~facenormals.nn.unet.NormalLandmarkUNet`."""

from __future__ import annotations


import torch
import torch.nn.functional as F
from torch import Tensor

from facenormals.core.check import check_floating, check_nonnegative, check_shape
from facenormals.nn.unet import UNetOutput

__all__ = ["normal_landmark_loss"]


def _foreground_pixel_mask(foreground: Tensor) -> Tensor:
    r"""The pixels :math:`\Omega` that :math:`L_N` averages over: a bool mask as it is, a soft one above 0.5."""
    return foreground if foreground.dtype == torch.bool else foreground.detach() > 0.5


def normal_landmark_loss(
    output: UNetOutput,
    normals_gt: Tensor,
    landmarks_gt: Tensor,
    foreground_gt: Tensor | None = None,
    landmark_weight: float = 1.0,
    foreground_weight: float = 1.0,
    landmark_peak_weight: float = 0.0,
    foreground_pixels: float | Tensor | None = None,
) -> tuple[Tensor, dict[str, Tensor]]:
    r"""The paper's squared-L2 loss :math:`L_N + L_Z`, plus a foreground term.

    .. math::

        L = L_N + w_Z L_Z + w_F L_F, \qquad
        L_N = \frac{1}{|\Omega|} \sum_{p \in \Omega} \lVert \hat n_p - n_p \rVert^2, \qquad
        L_Z = \operatorname{mean}\, (1 + \alpha Z) (\hat Z - Z)^2,

    where :math:`\Omega` is the ground-truth foreground over the whole batch (``foreground_gt >
    0.5`` or, when ``foreground_gt`` is ``None``, the pixels with :math:`\lVert n_p \rVert > 0.5`,
    see ``docs/conventions.md``) and :math:`L_Z` averages over all ``B * L * H * W`` entries. With
    :math:`\alpha` = ``landmark_peak_weight`` = 0 it is the paper's plain squared error; a positive
    :math:`\alpha` weights the few pixels under the landmark Gaussians up, against the mass of
    zero pixels that otherwise teach the network to predict empty maps for a long time.
    :math:`L_N` is 0 when the batch has no foreground pixel, :math:`L_Z` when ``L = 0``.

    :math:`L_F` is the mean binary cross-entropy between ``output.foreground_logits`` and the
    binary foreground. It is **our addition**, not the paper's: the network's normals are unit on
    every pixel and cannot represent the zero background, so it predicts a foreground mask that
    :meth:`UNetOutput.normal_map` uses to zero the background.

    Args:
        output: the network's prediction.
        normals_gt: ground-truth normal map, zero on background.
        landmarks_gt: ground-truth landmark maps.
        foreground_gt: ground-truth foreground (bool, or floating thresholded at 0.5); derived
            from ``normals_gt`` when ``None``. It is treated as a constant (no gradient).
        landmark_weight: :math:`w_Z`.
        foreground_weight: :math:`w_F`.
        landmark_peak_weight: :math:`\alpha`, the extra weight of pixels under the landmark Gaussians.
        foreground_pixels: :math:`|\Omega|` to divide by (default: this batch's count). Data-parallel
            training passes the global batch's count divided by the number of processes, so that
            the average of the processes' gradients is that of the loss of the global batch.

    Returns:
        ``(total, terms)``: the scalar loss and the unweighted terms ``{"normals": L_N,
        "landmarks": L_Z, "foreground": L_F}``, all 0-dimensional tensors.

    Raises:
        ValueError: on wrong shapes or dtypes, or negative weights.

    Shape:
        - output: :class:`UNetOutput` of :math:`(B, 3, H, W)`, :math:`(B, L, H, W)`,
          :math:`(B, 1, H, W)`
        - normals_gt: :math:`(B, 3, H, W)`
        - landmarks_gt: :math:`(B, L, H, W)`
        - foreground_gt: :math:`(B, 1, H, W)`

    Example:
        >>> n = torch.zeros(1, 3, 2, 2); n[:, 2, 0] = -1.0  # top row foreground
        >>> out = UNetOutput(n, torch.zeros(1, 4, 2, 2), torch.tensor([[[[9.0, 9.0], [-9.0, -9.0]]]]))
        >>> total, terms = normal_landmark_loss(out, n, torch.zeros(1, 4, 2, 2))
        >>> float(terms["normals"]), float(terms["landmarks"])
        (0.0, 0.0)
    """
    if not isinstance(output, UNetOutput):
        raise ValueError(f"output: expected a UNetOutput, got {type(output).__name__}")
    dims = check_shape(output.normals, ["B", 3, "H", "W"], "output.normals")
    check_shape(output.landmarks, ["B", "L", "H", "W"], "output.landmarks", dims)
    check_shape(output.foreground_logits, ["B", 1, "H", "W"], "output.foreground_logits", dims)
    check_shape(normals_gt, ["B", 3, "H", "W"], "normals_gt", dims)
    check_shape(landmarks_gt, ["B", "L", "H", "W"], "landmarks_gt", dims)
    if dims["B"] * dims["H"] * dims["W"] == 0:  # the mean of an empty batch is NaN
        raise ValueError(f"output.normals: expected at least one image and pixel, got shape {tuple(output.normals.shape)}")
    for name, x in (
        ("output.normals", output.normals),
        ("output.landmarks", output.landmarks),
        ("output.foreground_logits", output.foreground_logits),
        ("normals_gt", normals_gt),
        ("landmarks_gt", landmarks_gt),
    ):
        check_floating(x, name)
    landmark_weight = check_nonnegative(landmark_weight, "landmark_weight")
    foreground_weight = check_nonnegative(foreground_weight, "foreground_weight")
    landmark_peak_weight = check_nonnegative(landmark_peak_weight, "landmark_peak_weight")

    normals = output.normals
    if foreground_gt is None:
        mask = (normals_gt * normals_gt).sum(dim=1, keepdim=True) > 0.25
    else:
        check_shape(foreground_gt, ["B", 1, "H", "W"], "foreground_gt", dims)
        if foreground_gt.dtype != torch.bool:
            check_floating(foreground_gt, "foreground_gt")
        mask = _foreground_pixel_mask(foreground_gt)
    mask_f = mask.to(normals.dtype)

    sq_err = ((normals - normals_gt) ** 2).sum(dim=1, keepdim=True)
    if foreground_pixels is None:
        count = mask_f.sum()
    else:
        count = torch.as_tensor(foreground_pixels, dtype=normals.dtype, device=normals.device).detach()
        if count.numel() != 1 or not bool(torch.isfinite(count)) or float(count) < 0:
            raise ValueError(f"foreground_pixels: expected a finite number >= 0, got {foreground_pixels!r}")
        count = count.reshape(())
    # only 0 is replaced (no foreground: the sum is 0 too); a data-parallel share may be below 1
    loss_normals = (sq_err * mask_f).sum() / torch.where(count > 0, count, torch.ones_like(count))
    if landmarks_gt.numel() > 0:
        sq = (output.landmarks - landmarks_gt) ** 2
        if landmark_peak_weight > 0:
            sq = sq * (1.0 + landmark_peak_weight * landmarks_gt.detach())
        loss_landmarks = sq.mean()
    else:  # L = 0: mse_loss of empty tensors would be NaN
        loss_landmarks = (output.landmarks.sum() - landmarks_gt.sum()) * 0.0
    loss_foreground = F.binary_cross_entropy_with_logits(output.foreground_logits, mask_f)

    total = loss_normals + landmark_weight * loss_landmarks + foreground_weight * loss_foreground
    terms = {"normals": loss_normals, "landmarks": loss_landmarks, "foreground": loss_foreground}
    return total, terms
