"""Vertex subsets about as dense as the pixels, for the normal term of the fit."""

from __future__ import annotations

import torch
from torch import Tensor

from facenormals.core.check import check_finite, check_floating, check_real, check_shape

__all__ = ["grid_subset"]


def grid_subset(vertices: Tensor, cell: float) -> Tensor:
    """Keep one vertex per cube of side ``cell``: the one nearest the cube's centre.

    Regions whose vertices are sparser than ``cell`` keep all of them; denser regions (the face of
    ICT-FaceKit has ~1.5 mm edges) are thinned to about one vertex per ``cell``. Deterministic.

    Args:
        vertices: ``(N, 3)`` positions, e.g. a model's mean head, in the unit of ``cell``.
        cell: cube side; ``<= 0`` keeps every vertex.

    Returns:
        ``(N,)`` bool mask of the kept vertices.

    Example:
        >>> v = torch.tensor([[0.0, 0, 0], [0.4, 0, 0], [1.6, 0, 0]])
        >>> grid_subset(v, 1.0).tolist()
        [False, True, True]
    """
    check_shape(vertices, ["N", 3], "vertices")
    check_floating(vertices, "vertices")
    check_finite(vertices, "vertices")
    cell = check_real(cell, "cell")  # NaN or inf kept a single vertex
    if vertices.shape[0] == 0:
        return torch.zeros(0, dtype=torch.bool, device=vertices.device)
    if cell <= 0:
        return torch.ones(vertices.shape[0], dtype=torch.bool, device=vertices.device)
    key = torch.floor(vertices / cell)
    distance = (vertices - (key + 0.5) * cell).norm(dim=1)
    key = (key - key.amin(0)).to(torch.long)
    size = key.amax(0) + 1
    cube = (key[:, 0] * size[1] + key[:, 1]) * size[2] + key[:, 2]
    _, cube = torch.unique(cube, return_inverse=True)
    # nearest to the centre wins; ties go to the lower index (the order is stable)
    order = torch.argsort(distance, stable=True)
    rank = torch.arange(vertices.shape[0], device=vertices.device)
    best = torch.full((int(cube.max()) + 1,), vertices.shape[0], dtype=torch.long, device=vertices.device)
    best.scatter_reduce_(0, cube[order], rank, reduce="amin")
    keep = torch.zeros(vertices.shape[0], dtype=torch.bool, device=vertices.device)
    keep[order[best]] = True
    return keep
