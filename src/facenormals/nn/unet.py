r"""A lean U-Net that predicts a normal map, landmark maps and a foreground mask from a photo.

The architecture follows the generator of Su et al., *Interactive sketch-based normal map
generation with deep neural networks* (a pix2pix-style U-Net; its discriminator is dropped):
an encoder of stride-2 convolutions, a mirrored decoder and skip connections that concatenate
each encoder level to the decoder level of the same resolution. Channels double at every level
and, as in pix2pix, stop growing at eight times the base width.

Choices made here (and why):

* **GroupNorm** (at most 8 groups) rather than BatchNorm: it has no running statistics, so
  training and ``eval()`` compute the same function, batch size 1 works in training and
  inference, and the 1-pixel bottleneck of small inputs cannot break it.
* **Bilinear upsampling followed by a 3x3 convolution** rather than transposed convolutions,
  which avoids checkerboard artefacts. Before upsampling, a 1x1 convolution halves the channels
  at the low resolution, which is cheaper than convolving the full concatenation afterwards.
* **LeakyReLU(0.2)** everywhere (pix2pix uses it in the encoder).
* The input, an RGB image in ``[0, 1]``, is mapped to ``[-1, 1]`` inside the network.
* **Normals** are the raw 3-channel output divided by a safe norm
  :math:`\sqrt{\max(\lVert n \rVert^2, \epsilon^2)}`: unit wherever the raw norm is at least
  :math:`\epsilon`, and with finite gradients everywhere (no NaN at a zero output). The bias of the normal head starts at ``(0, 0, -1)``, a normal that
  faces the camera (see ``docs/conventions.md``).
* **Landmark maps** are a linear (identity) regression of the Gaussian heatmaps, trained with a
  squared error as in the paper. They can be slightly negative; clamp them at zero if needed. A
  softplus was not used because it can never output the exact zeros of an empty map.
* **Foreground logits**: a unit normal cannot be zero, so the convention "normal map is zero on
  background" needs a separate mask; :meth:`UNetOutput.normal_map` applies it.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from facenormals.core.check import check_floating, check_positive, check_shape

__all__ = ["NormalLandmarkUNet", "UNetOutput"]


class UNetOutput(NamedTuple):
    """Output of :class:`NormalLandmarkUNet`.

    Attributes:
        normals: unit normals in the camera frame, :math:`(B, 3, H, W)`, defined on every pixel
            (use :meth:`normal_map` for the library's zero-on-background convention).
        landmarks: landmark heatmaps, :math:`(B, L, H, W)` (linear output, may dip below 0).
        foreground_logits: foreground logits, :math:`(B, 1, H, W)`.
    """

    normals: Tensor
    landmarks: Tensor
    foreground_logits: Tensor

    def foreground(self, threshold: float = 0.5) -> Tensor:
        """Boolean foreground mask ``sigmoid(foreground_logits) > threshold``, :math:`(B, 1, H, W)`."""
        if not 0.0 < float(threshold) < 1.0:
            raise ValueError(f"threshold: expected a value in (0, 1), got {threshold}")
        return torch.sigmoid(self.foreground_logits) > threshold

    def normal_map(self, threshold: float = 0.5) -> Tensor:
        """The normal map of ``docs/conventions.md``: unit normals on foreground, exactly zero elsewhere.

        Args:
            threshold: a pixel is foreground when ``sigmoid(foreground_logits) > threshold``.

        Returns:
            :math:`(B, 3, H, W)` normals, zero where the pixel is background.

        Example:
            >>> out = UNetOutput(torch.tensor([0.0, 0.0, -1.0]).view(1, 3, 1, 1).expand(1, 3, 1, 2),
            ...                  torch.zeros(1, 0, 1, 2), torch.tensor([[[[2.0, -2.0]]]]))
            >>> out.normal_map()[0, :, 0]
            tensor([[ 0.,  0.],
                    [ 0.,  0.],
                    [-1.,  0.]])
        """
        # mismatched fields would broadcast or fail deep inside torch.where
        dims = check_shape(self.normals, ["B", 3, "H", "W"], "normals")
        check_shape(self.foreground_logits, ["B", 1, "H", "W"], "foreground_logits", dims)
        mask = self.foreground(threshold)
        return torch.where(mask, self.normals, torch.zeros_like(self.normals))


def _num_groups(channels: int, max_groups: int = 8) -> int:
    return math.gcd(channels, max_groups)


class _ConvNormAct(nn.Sequential):
    """Conv2d (no bias) -> GroupNorm -> LeakyReLU(0.2)."""

    def __init__(self, in_channels: int, out_channels: int, kernel_size: int = 3, stride: int = 1):
        super().__init__(
            nn.Conv2d(in_channels, out_channels, kernel_size, stride, kernel_size // 2, bias=False),
            nn.GroupNorm(_num_groups(out_channels), out_channels),
            nn.LeakyReLU(0.2),
        )


class _Down(nn.Sequential):
    """One encoder level: a stride-2 3x3 convolution, then a 3x3 convolution."""

    def __init__(self, in_channels: int, out_channels: int):
        super().__init__(
            _ConvNormAct(in_channels, out_channels, stride=2),
            _ConvNormAct(out_channels, out_channels),
        )


class _Up(nn.Module):
    """One decoder level: 1x1 channel reduction, bilinear x2, skip concatenation, two 3x3 convs."""

    def __init__(self, in_channels: int, skip_channels: int):
        super().__init__()
        self.reduce = _ConvNormAct(in_channels, skip_channels, kernel_size=1)
        self.fuse = nn.Sequential(
            _ConvNormAct(2 * skip_channels, skip_channels),
            _ConvNormAct(skip_channels, skip_channels),
        )

    def forward(self, x: Tensor, skip: Tensor) -> Tensor:
        x = F.interpolate(self.reduce(x), size=skip.shape[-2:], mode="bilinear", align_corners=False)
        return self.fuse(torch.cat([x, skip], dim=1))


class NormalLandmarkUNet(nn.Module):
    r"""U-Net from an RGB photo to a normal map, landmark maps and a foreground logit.

    Encoder: a full-resolution 3x3 stem, then ``depth`` levels of (stride-2 conv, conv) with
    ``base_channels * 2**i`` channels capped at ``max_channels``. Decoder: ``depth`` mirrored
    levels of (1x1 reduction, bilinear upsampling, concatenation with the encoder level of the
    same resolution, two 3x3 convs). A 1x1 head produces ``3 + num_landmarks + 1`` channels. All
    hidden convolutions use GroupNorm and LeakyReLU(0.2); see the module docstring for the
    reasons. At the defaults (16 base channels, depth 5, channels 16-32-64-128-128-128) the
    network has about 1.96M parameters.

    Args:
        in_channels: channels of the input image (3 for RGB in ``[0, 1]``).
        num_landmarks: number of landmark maps ``L``.
        base_channels: channels at full resolution.
        depth: number of stride-2 levels; ``H`` and ``W`` must be divisible by ``2**depth``.
        max_channels: channel cap, ``8 * base_channels`` (as in pix2pix) when ``None``.
        eps: the :math:`\epsilon` of the safe norm that normalises the normals.

    Shape:
        - images: :math:`(B, C_{in}, H, W)`, floating, with the dtype of the parameters.
        - output: :class:`UNetOutput` of :math:`(B, 3, H, W)` normals, :math:`(B, L, H, W)`
          landmarks and :math:`(B, 1, H, W)` foreground logits, in the dtype of the input.

    Example:
        >>> net = NormalLandmarkUNet(num_landmarks=5, base_channels=4, depth=2)
        >>> out = net(torch.rand(1, 3, 8, 12))
        >>> tuple(tuple(t.shape) for t in out)
        ((1, 3, 8, 12), (1, 5, 8, 12), (1, 1, 8, 12))
        >>> out.normal_map().shape
        torch.Size([1, 3, 8, 12])
    """

    def __init__(
        self,
        in_channels: int = 3,
        num_landmarks: int = 24,
        base_channels: int = 16,
        depth: int = 5,
        max_channels: int | None = None,
        eps: float = 1e-6,
    ):
        super().__init__()
        for name, value, low in (
            ("in_channels", in_channels, 1),
            ("num_landmarks", num_landmarks, 0),
            ("base_channels", base_channels, 1),
            ("depth", depth, 1),
        ):
            if not isinstance(value, int) or isinstance(value, bool) or value < low:
                raise ValueError(f"{name}: expected an integer >= {low}, got {value!r}")
        if max_channels is None:
            max_channels = 8 * base_channels
        if not isinstance(max_channels, int) or max_channels < base_channels:
            raise ValueError(
                f"max_channels: expected an integer >= base_channels={base_channels}, got {max_channels!r}"
            )
        check_positive(eps, "eps")  # finite too: an infinite eps made every normal 0
        self.in_channels = in_channels
        self.num_landmarks = num_landmarks
        self.depth = depth
        self.eps = float(eps)

        channels = [min(base_channels * 2**i, max_channels) for i in range(depth + 1)]
        self.channels = tuple(channels)
        self.stem = _ConvNormAct(in_channels, channels[0])
        self.down = nn.ModuleList(_Down(channels[i], channels[i + 1]) for i in range(depth))
        # up[i] maps level i + 1 to level i; it is applied from i = depth - 1 down to 0.
        self.up = nn.ModuleList(_Up(channels[i + 1], channels[i]) for i in range(depth))
        self.head = nn.Conv2d(channels[0], 3 + num_landmarks + 1, kernel_size=1)
        with torch.no_grad():
            self.head.bias.zero_()
            self.head.bias[2] = -1.0  # start from normals facing the camera (-z)

    def forward(self, images: Tensor) -> UNetOutput:
        """Predict normals, landmark maps and foreground logits for a batch of images."""
        dims = check_shape(images, ["B", self.in_channels, "H", "W"], "images")
        check_floating(images, "images")
        factor = 2**self.depth
        if dims["H"] % factor or dims["W"] % factor or min(dims["H"], dims["W"]) < factor:
            raise ValueError(
                f"images: expected H and W positive multiples of 2**depth={factor}, "
                f"got shape {tuple(images.shape)}"
            )
        weight = self.head.weight
        if images.dtype != weight.dtype:
            raise ValueError(
                f"images: expected dtype {weight.dtype} (the model's), got {images.dtype}"
            )

        x = self.stem(images * 2.0 - 1.0)
        skips = [x]
        for level in self.down:
            x = level(x)
            skips.append(x)
        for i in range(self.depth - 1, -1, -1):
            x = self.up[i](x, skips[i])
        raw = self.head(x).to(images.dtype)  # float32 normalisation under bf16 autocast

        raw_normals = raw[:, :3]
        if raw_normals.dtype in (torch.float16, torch.bfloat16):  # a half model: eps² underflows, |n|² overflows
            raw_normals = raw_normals.float()
        # clamp before the sqrt: exactly unit where |n| >= eps, finite gradients everywhere.
        norm = torch.sqrt((raw_normals * raw_normals).sum(dim=1, keepdim=True).clamp(min=self.eps**2))
        return UNetOutput(
            normals=(raw_normals / norm).to(raw.dtype),
            landmarks=raw[:, 3 : 3 + self.num_landmarks],
            foreground_logits=raw[:, 3 + self.num_landmarks :],
        )

    @staticmethod
    def normal_map(output: UNetOutput, threshold: float = 0.5) -> Tensor:
        """Same as :meth:`UNetOutput.normal_map`: normals, exactly zero on predicted background."""
        return output.normal_map(threshold)
