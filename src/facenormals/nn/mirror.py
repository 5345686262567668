r"""Test-time mirroring: average a network's prediction with that of the mirrored image.

Mirroring the photo about its vertical centre line (pixel ``x`` goes to ``W - 1 - x``, see
``docs/conventions.md``) mirrors the scene about the camera's ``y-z`` plane. A prediction on the
mirrored photo is mapped back by mirroring the maps again, negating the ``x`` component of the
normals, and swapping the landmark channels of each right/left pair. On the held-out synthetic set
the average of the two is better than either (the shipped network: landmarks ~12 % closer, normals
~6 %; docs/model_card.md), for twice the inference cost.
"""

from __future__ import annotations

import operator
from typing import Sequence

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from facenormals.core.check import check_finite, check_floating, check_shape
from facenormals.models.landmarks import LANDMARK_NAMES, LANDMARK_PAIRS
from facenormals.nn.unet import UNetOutput

__all__ = ["mirror_output", "mirror_averaged", "mirror_permutation"]


def mirror_permutation(names: Sequence[str] = LANDMARK_NAMES,
                       pairs: Sequence[tuple[str, str]] = LANDMARK_PAIRS) -> list[int]:
    """Channel ``i`` of a mirrored landmark map is channel ``perm[i]`` of the original.

    Example:
        >>> mirror_permutation(("a_right", "nose", "a_left"), [("a_right", "a_left")])
        [2, 1, 0]
    """
    perm = list(range(len(names)))
    for right, left in pairs:
        if right not in names or left not in names:
            raise ValueError(f"pairs: ({right!r}, {left!r}) is not a pair of names {tuple(names)}")
        i, j = names.index(right), names.index(left)
        perm[i], perm[j] = j, i
    return perm


def mirror_output(output: UNetOutput, permutation: Sequence[int]) -> UNetOutput:
    """Map a prediction on a mirrored image back to the original image.

    Args:
        output: the network's output on the mirrored image.
        permutation: landmark channel permutation, :func:`mirror_permutation`.

    Shape:
        - normals :math:`(B, 3, H, W)`, landmarks :math:`(B, L, H, W)`, foreground logits
          :math:`(B, 1, H, W)`, the same out.

    Example:
        >>> n = torch.nn.functional.normalize(torch.randn(1, 3, 4, 5), dim=1)
        >>> out = UNetOutput(n, torch.rand(1, 2, 4, 5), torch.randn(1, 1, 4, 5))
        >>> twice = mirror_output(mirror_output(out, [1, 0]), [1, 0])
        >>> all(torch.equal(a, b) for a, b in zip(twice, out))
        True
    """
    if not isinstance(output, UNetOutput):  # a plain tuple has no .normals
        raise ValueError(f"output: expected a UNetOutput, got {type(output).__name__}")
    dims = check_shape(output.normals, ["B", 3, "H", "W"], "output.normals")
    check_shape(output.landmarks, ["B", len(permutation), "H", "W"], "output.landmarks", dims)
    check_shape(output.foreground_logits, ["B", 1, "H", "W"], "output.foreground_logits", dims)
    for field in UNetOutput._fields:  # the averages of mirror_averaged would round integer maps
        check_floating(getattr(output, field), f"output.{field}")
    try:  # integers only: int() would truncate 1.5 to a valid index
        order = [operator.index(i) for i in permutation]
    except TypeError:
        order = None
    if order is None or sorted(order) != list(range(len(order))):
        raise ValueError(f"permutation: expected a permutation of 0..{len(permutation) - 1}, got {list(permutation)}")
    sign = torch.tensor([-1.0, 1.0, 1.0], dtype=output.normals.dtype, device=output.normals.device).view(1, 3, 1, 1)
    index = torch.as_tensor(order, device=output.landmarks.device)
    return UNetOutput(output.normals.flip(-1) * sign, output.landmarks.flip(-1).index_select(1, index),
                      output.foreground_logits.flip(-1))


def mirror_averaged(net: nn.Module, images: Tensor, permutation: Sequence[int] | None = None) -> UNetOutput:
    r"""The average of ``net(images)`` and the mirrored prediction on the mirrored images.

    Normals are averaged and renormalised; landmark maps and foreground logits are averaged.

    Args:
        net: a network returning :class:`~facenormals.nn.UNetOutput`.
        images: :math:`(B, 3, H, W)` in ``[0, 1]``, finite.
        permutation: landmark channel permutation (default: :func:`mirror_permutation` of the 24
            library landmarks).

    Example:
        >>> from facenormals.nn import NormalLandmarkUNet
        >>> net = NormalLandmarkUNet(base_channels=4, depth=2).eval()
        >>> mirror_averaged(net, torch.rand(1, 3, 16, 16)).landmarks.shape
        torch.Size([1, 24, 16, 16])
    """
    check_shape(images, ["B", 3, "H", "W"], "images")
    check_floating(images, "images")
    check_finite(images, "images")  # one NaN pixel would turn every map into NaN
    if permutation is None:
        permutation = mirror_permutation()
    both = net(torch.cat([images, images.flip(-1)]))
    if not isinstance(both, UNetOutput):
        raise ValueError(f"net: expected a network returning a UNetOutput, got one returning {type(both).__name__}")
    if len(permutation) != both.landmarks.shape[1]:
        raise ValueError(f"permutation: expected one entry per landmark channel ({both.landmarks.shape[1]}), "
                         f"got {len(permutation)}")
    B = images.shape[0]
    plain = UNetOutput(*(t[:B] for t in both))
    back = mirror_output(UNetOutput(*(t[B:] for t in both)), permutation)
    return UNetOutput(F.normalize(plain.normals + back.normals, dim=1, eps=1e-12),
                      0.5 * (plain.landmarks + back.landmarks),
                      0.5 * (plain.foreground_logits + back.foreground_logits))
