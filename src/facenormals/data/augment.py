"""The paper's photometric augmentation of training images: random Gaussian blur and Gaussian noise."""

from __future__ import annotations

import torch
from torch import Tensor, nn

from facenormals.core.check import check_floating, check_real, check_shape, check_tensor, check_unit_range

__all__ = ["PhotoAugmentation"]

#: Largest blur standard deviation in pixels (a 61-pixel kernel); blurs wider than that erase a face crop.
MAX_BLUR_SIGMA = 10.0


class PhotoAugmentation(nn.Module):
    """Random blur (:class:`kornia.augmentation.RandomGaussianBlur`) then additive Gaussian noise.

    Only the image changes; normals and landmark maps stay aligned with it. Apply it per sample in
    a :class:`~facenormals.data.SyntheticHeadDataset` (``augment=``) or on whole batches on the
    training device.

    Args:
        blur_probability: probability of blurring an image, in ``[0, 1]``.
        blur_sigma: ``(low, high)`` range of the blur's standard deviation in pixels (uniform),
            ``0 < low <= high <= 10`` (:data:`MAX_BLUR_SIGMA`; the kernel is ``6 high + 1`` wide).
        noise_probability: probability of adding noise to an image, in ``[0, 1]``.
        noise_std: ``(low, high)`` range of the noise's standard deviation (uniform), images in
            ``[0, 1]``: ``0 <= low <= high <= 1``.

    Raises:
        ValueError: if an argument is not a finite real number (a pair of them for the ranges) or
            is out of its range; when called, naming ``images`` unless they are a floating
            :math:`(B, 3, H, W)` or :math:`(3, H, W)` tensor of finite values in ``[0, 1]``.

    Shape:
        - input: :math:`(B, 3, H, W)` or :math:`(3, H, W)`, floating, finite, in ``[0, 1]``
        - output: same shape, clamped to ``[0, 1]``

    Example:
        >>> aug = PhotoAugmentation()
        >>> aug(torch.rand(2, 3, 16, 16)).shape
        torch.Size([2, 3, 16, 16])
    """

    def __init__(
        self,
        blur_probability: float = 0.5,
        blur_sigma: tuple[float, float] = (0.2, 1.5),
        noise_probability: float = 0.5,
        noise_std: tuple[float, float] = (0.005, 0.04),
    ) -> None:
        super().__init__()
        import kornia.augmentation as K

        for name, p in (("blur_probability", blur_probability), ("noise_probability", noise_probability)):
            if not 0.0 <= check_real(p, name) <= 1.0:
                raise ValueError(f"{name}: expected a probability in [0, 1], got {p}")
        blur_sigma, noise_std = _pair(blur_sigma, "blur_sigma"), _pair(noise_std, "noise_std")
        if not 0.0 < blur_sigma[0] <= blur_sigma[1] <= MAX_BLUR_SIGMA:
            raise ValueError(f"blur_sigma: expected 0 < low <= high <= {MAX_BLUR_SIGMA:g} pixels, got {blur_sigma}")
        if not 0.0 <= noise_std[0] <= noise_std[1] <= 1.0:
            raise ValueError(f"noise_std: expected 0 <= low <= high <= 1, got {noise_std}")
        self.blur_probability, self.blur_sigma = float(blur_probability), blur_sigma
        self.noise_probability, self.noise_std = float(noise_probability), noise_std
        kernel = 2 * int(round(3.0 * blur_sigma[1])) + 1
        self.blur = K.RandomGaussianBlur((kernel, kernel), blur_sigma, p=self.blur_probability)

    def forward(self, images: Tensor) -> Tensor:
        check_tensor(images, "images")
        single = images.dim() == 3
        batch = images[None] if single else images
        check_shape(batch, ["B", 3, "H", "W"], "images")
        check_floating(batch, "images")
        check_unit_range(batch, "images")
        if self.blur_probability > 0:
            batch = self.blur(batch)
        if self.noise_probability > 0 and self.noise_std[1] > 0:
            n = batch.shape[0]
            lo, hi = self.noise_std
            std = lo + (hi - lo) * torch.rand(n, 1, 1, 1, dtype=batch.dtype, device=batch.device)
            apply = (torch.rand(n, 1, 1, 1, device=batch.device) < self.noise_probability).to(batch.dtype)
            batch = batch + apply * std * torch.randn_like(batch)
        batch = batch.clamp(0.0, 1.0)
        return batch[0] if single else batch

    def extra_repr(self) -> str:
        return (f"blur_probability={self.blur_probability}, blur_sigma={self.blur_sigma}, "
                f"noise_probability={self.noise_probability}, noise_std={self.noise_std}")


def _pair(value: object, name: str) -> tuple[float, float]:
    """``value`` as a ``(low, high)`` tuple of floats, raising ``ValueError`` unless it is a pair of finite real numbers."""
    if not isinstance(value, (tuple, list)) or len(value) != 2:
        raise ValueError(f"{name}: expected a (low, high) pair of numbers, got {type(value).__name__} {value!r}")
    return check_real(value[0], name), check_real(value[1], name)
