"""Weights of iteratively reweighted least squares, shared by the pre-alignment and the fit."""

from __future__ import annotations

import torch
from torch import Tensor

from facenormals.core.check import check_positive


def check_scale(name: str, value: float | None) -> None:
    """Raise ``ValueError`` naming ``name`` unless ``value`` is ``None`` (no reweighting) or a finite
    number > 0."""
    if value is not None:
        check_positive(value, name)


def huber_weights(rho: Tensor, scale: float) -> Tensor:
    """Huber's loss for residual norms ``rho``: weight 1 up to ``scale``, then ``scale / rho``."""
    return torch.where(rho > scale, scale / rho.clamp_min(1e-12), torch.ones_like(rho))


def cauchy_weights(error: Tensor, scale: float) -> Tensor:
    """Cauchy's (redescending) loss for residual norms ``error``: weight ``1 / (1 + (error / scale)²)``."""
    return 1.0 / (1.0 + (error / scale).square())
