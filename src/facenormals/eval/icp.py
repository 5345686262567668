r"""Point-to-plane ICP, rigid or with scale, for evaluation (CPU, numpy, float64).

Each iteration pairs points by nearest neighbours (:class:`scipy.spatial.cKDTree`), rejects pairs
farther apart than ``max_distance``, and solves the point-to-plane problem linearised about the
current transform,

.. math:: \min_{\omega, \tau, \sigma} \sum_i \big( r_i + \sigma\, (x_i - c) \cdot n_i
          + \omega \cdot ((x_i - c) \times n_i) + \tau \cdot n_i \big)^2,
          \qquad r_i = (x_i - y_i) \cdot n_i,

where :math:`x_i = s R p_i + t` is the transformed source point, :math:`y_i, n_i` its target point
and target normal and :math:`c` the centroid of the paired :math:`x_i` (for conditioning). The
increment :math:`x \mapsto c + e^{\sigma} \exp([\omega]_\times) (x - c) + \tau` (small-angle
rotation, applied exactly through Rodrigues' formula; :math:`\sigma = 0` for a rigid fit) is
composed onto the transform. The least-squares problem is solved with :func:`numpy.linalg.lstsq`,
so directions the surface does not constrain (rotation about a sphere's centre) get no update.
"""

from __future__ import annotations

import reprlib
from dataclasses import dataclass
from numbers import Real

import numpy as np
import torch
from torch import Tensor

from facenormals.core.check import check_finite, check_floating, check_integer, check_nonnegative, check_shape

__all__ = ["ICPResult", "icp_point_to_plane"]

_DIRECTIONS = ("source_to_target", "target_to_source")
_INTEGER_DTYPES = (torch.uint8, torch.int8, torch.int16, torch.int32, torch.int64)


@dataclass(frozen=True)
class ICPResult:
    """The transform ``target ≈ s · R · source + t`` found by :func:`icp_point_to_plane`.

    Attributes:
        s: the scale (1 for a rigid fit).
        R: ``(3, 3)`` rotation, det +1.
        t: ``(3,)`` translation (mm).
        rmse: point-to-plane RMSE (mm) over the pairs kept at the final transform.
        iterations: number of updates applied.
        converged: whether a stopping criterion (not ``max_iterations``) ended the loop.
        num_pairs: pairs kept at the final transform.
    """

    s: float
    R: Tensor
    t: Tensor
    rmse: float
    iterations: int
    converged: bool
    num_pairs: int


def _rodrigues(omega: np.ndarray) -> np.ndarray:
    angle = float(np.linalg.norm(omega))
    k = np.array([[0.0, -omega[2], omega[1]], [omega[2], 0.0, -omega[0]], [-omega[1], omega[0], 0.0]])
    if angle < 1e-12:
        return np.eye(3) + k
    return np.eye(3) + np.sin(angle) / angle * k + (1.0 - np.cos(angle)) / angle**2 * (k @ k)


def _kind(x: object) -> str:
    if isinstance(x, (Tensor, np.ndarray)):
        return f"{type(x).__name__} of dtype {x.dtype}"
    return f"{type(x).__name__} {reprlib.repr(x)}"


def _real_array(x: object, what: str) -> Tensor:
    """``x`` (a number, sequence, array or tensor of real numbers, no bools) as a float64 CPU tensor."""
    error = ValueError(f"init: expected real numbers for {what}, got {_kind(x)}")
    try:
        out = torch.as_tensor(x if isinstance(x, Tensor) else np.asarray(x))
    except (TypeError, ValueError, RuntimeError):  # strings, ragged or object sequences
        raise error from None
    if not (out.dtype.is_floating_point or out.dtype in _INTEGER_DTYPES):  # bool, complex
        raise error
    return out.detach().cpu().double()


def _parse_init(init, dtype=np.float64) -> tuple[float, np.ndarray, np.ndarray]:
    if init is None:
        return 1.0, np.eye(3), np.zeros(3)
    if not isinstance(init, (tuple, list)) or len(init) != 3:
        raise ValueError(f"init: expected a tuple (s, R, t), got {type(init).__name__}")
    s, rotation, translation = (_real_array(x, what) for x, what in zip(init, ("the scale s", "R", "t")))
    if s.numel() != 1:
        raise ValueError(f"init: expected a single scale s, got shape {tuple(s.shape)}")
    if rotation.numel() != 9:
        raise ValueError(f"init: expected R of shape (3, 3) or (1, 3, 3), got {tuple(rotation.shape)}")
    if translation.numel() != 3:
        raise ValueError(f"init: expected t of shape (3,) or (1, 3), got {tuple(translation.shape)}")
    out = float(s), rotation.reshape(3, 3).numpy().astype(dtype), translation.reshape(3).numpy().astype(dtype)
    if not (np.isfinite(out[0]) and out[0] > 0 and np.isfinite(out[1]).all() and np.isfinite(out[2]).all()):
        raise ValueError(f"init: expected finite values and a positive scale, got s = {out[0]:g}")
    error, det = float(np.abs(out[1].T @ out[1] - np.eye(3)).max()), float(np.linalg.det(out[1]))
    if error > 1e-5 or det < 0:  # float32 rotations are orthonormal to ~1e-7
        raise ValueError(f"init: expected R to be a rotation (orthonormal, det +1), got max |RᵀR − I| = {error:.2g} "
                         f"and det {det:.3g}")
    return out


def icp_point_to_plane(
    source_points: Tensor,
    target_points: Tensor,
    target_normals: Tensor,
    init: tuple[Tensor | float, Tensor, Tensor] | None = None,
    scale: bool = False,
    max_iterations: int = 50,
    tolerance: float = 1e-6,
    max_distance: float | None = None,
    direction: str = "source_to_target",
) -> ICPResult:
    r"""Align ``source_points`` to the surface ``(target_points, target_normals)`` by point-to-plane ICP.

    Args:
        source_points: points :math:`p_i` to move (mm).
        target_points: the fixed points :math:`y_j` (mm).
        target_normals: normals :math:`n_j` at the target points (normalised here; a zero normal
            removes its point).
        init: starting transform ``(s, R, t)`` of real numbers: ``s`` a positive number or
            ``(1,)`` tensor (not a bool), ``R`` ``(3, 3)``/``(1, 3, 3)``, ``t`` ``(3,)``/``(1, 3)``
            (the output of :func:`fit_similarity` fits). Default: identity.
        scale: also fit a scale (similarity ICP); otherwise the scale of ``init`` is kept.
        max_iterations: the most updates.
        tolerance: stop when the update is small, :math:`\max(\lVert\omega\rVert, |\sigma|,
            \lVert\tau\rVert / \rho) <` ``tolerance`` with :math:`\rho` the RMS radius of the target
            about its centroid, or when the point-to-plane RMSE of the pairs changes by less than
            ``tolerance`` relative to the previous iteration, or returns to within ``tolerance`` of
            the one before it: a 2-cycle, where the closest pairs and the updates alternate between two
            sets (the better of its two states is returned). All three count as converged.
        max_distance: reject pairs whose points are farther apart than this (mm) after the current
            transform. ``None`` (default) keeps every pair. If fewer than ``3 × unknowns`` pairs
            (18 rigid, 21 with scale) would remain, that iteration keeps all pairs instead.
        direction: ``"source_to_target"`` (default, classic ICP): each source point is paired
            with its nearest target point. ``"target_to_source"``: each target point is paired
            with the nearest transformed source point (use it when the source covers more than the
            target, e.g. a whole predicted head against a reference face region).

    Returns:
        :class:`ICPResult` with ``R``, ``t`` in the dtype of ``source_points`` (on the CPU).

    Raises:
        ValueError: on badly shaped, non-floating or non-finite inputs, a bad ``init``,
            ``direction`` or iteration settings.

    Shape:
        - source_points: :math:`(N, 3)`; target_points, target_normals: :math:`(M, 3)`

    Example:
        >>> g = torch.Generator().manual_seed(0)
        >>> n = torch.nn.functional.normalize(torch.randn(2000, 3, generator=g), dim=1)
        >>> target = n * torch.tensor([60.0, 80.0, 100.0])  # points on an ellipsoid
        >>> normals = torch.nn.functional.normalize(target / torch.tensor([60.0, 80.0, 100.0]) ** 2, dim=1)
        >>> result = icp_point_to_plane(target + torch.tensor([2.0, -1.0, 3.0]), target, normals)
        >>> result.t.round(decimals=3), result.rmse < 1e-6, result.converged
        (tensor([-2.,  1., -3.]), True, True)
    """
    dims = check_shape(source_points, ["N", 3], "source_points")
    tdims = check_shape(target_points, ["M", 3], "target_points")
    check_shape(target_normals, ["M", 3], "target_normals", tdims)
    arguments = {"source_points": source_points, "target_points": target_points, "target_normals": target_normals}
    for name, x in arguments.items():
        check_floating(x, name)
        check_finite(x, name)
    if direction not in _DIRECTIONS:
        raise ValueError(f"direction: expected one of {_DIRECTIONS}, got {direction!r}")
    max_iterations = check_integer(max_iterations, "max_iterations", minimum=0)
    tolerance = check_nonnegative(tolerance, "tolerance")
    if max_distance is not None and (isinstance(max_distance, bool) or not isinstance(max_distance, Real)
                                     or not max_distance > 0):
        raise ValueError(f"max_distance: expected a positive number or None, got {max_distance!r}")
    if dims["N"] == 0 or tdims["M"] == 0:
        raise ValueError("source_points, target_points: expected at least one point each")
    from scipy.spatial import cKDTree

    s, rotation, translation = _parse_init(init)
    src = source_points.detach().cpu().double().numpy()
    tgt = target_points.detach().cpu().double().numpy()
    nrm = target_normals.detach().cpu().double().numpy()
    length = np.linalg.norm(nrm, axis=1)
    valid = length > 1e-12
    nrm = nrm / np.maximum(length, 1e-12)[:, None]
    radius = float(np.sqrt(((tgt - tgt.mean(0)) ** 2).sum(1).mean())) or 1.0
    unknowns = 7 if scale else 6
    if int(valid.sum()) < unknowns:
        raise ValueError(f"target_normals: expected at least {unknowns} non-zero normals to fit "
                         f"{'a similarity' if scale else 'a rigid'} transform, got {int(valid.sum())}")
    to_target = direction == "source_to_target"
    tree = cKDTree(tgt if to_target else src)

    def pairs(s, rotation, translation):
        if to_target:
            x = s * src @ rotation.T + translation
            dist, j = tree.query(x)
            y, n, ok = tgt[j], nrm[j], valid[j]
        else:
            # nearest transformed source point = nearest source point to the inverse-mapped target
            _, i = tree.query(((tgt - translation) @ rotation) / s)
            x = s * src[i] @ rotation.T + translation
            y, n, ok = tgt, nrm, valid
            dist = np.linalg.norm(x - y, axis=1)
        keep = ok if max_distance is None else ok & (dist <= max_distance)
        if keep.sum() < 3 * unknowns:
            keep = ok
        return x[keep], y[keep], n[keep]

    def same(a: float, b: float) -> bool:
        return abs(a - b) <= tolerance * max(a, 1e-300)

    iterations, converged, history = 0, False, []  # history: (rmse, state) of the states before this one
    for _ in range(max_iterations):
        x, y, n = pairs(s, rotation, translation)
        residual = ((x - y) * n).sum(1)
        rmse = float(np.sqrt(np.mean(residual**2))) if len(residual) else 0.0
        if history and same(history[-1][0], rmse):
            converged = True
            break
        if len(history) >= 2 and same(history[-2][0], rmse):
            # a 2-cycle: the closest pairs alternate between two sets, and so do the updates; keep the
            # better of the two states (its RMSE differs from the other's by ~1e-4 relative)
            if history[-1][0] < rmse:
                s, rotation, translation = history[-1][1]
            converged = True
            break
        history.append((rmse, (s, rotation, translation)))
        centre = x.mean(0)
        xc = x - centre
        columns = [np.cross(xc, n), n] + ([(xc * n).sum(1, keepdims=True)] if scale else [])
        step = np.linalg.lstsq(np.concatenate(columns, axis=1), -residual, rcond=None)[0]
        omega, tau = step[:3], step[3:6]
        sigma = float(step[6]) if scale else 0.0
        r_inc, s_inc = _rodrigues(omega), float(np.exp(sigma))
        s = s_inc * s
        rotation = r_inc @ rotation
        u, _, vh = np.linalg.svd(rotation)  # keep R orthonormal over many compositions
        rotation = u @ vh
        translation = s_inc * r_inc @ (translation - centre) + centre + tau
        iterations += 1
        if max(np.linalg.norm(omega), abs(sigma), np.linalg.norm(tau) / radius) < tolerance:
            converged = True
            break
    x, y, n = pairs(s, rotation, translation)
    residual = ((x - y) * n).sum(1)
    rmse = float(np.sqrt(np.mean(residual**2))) if len(residual) else 0.0
    dtype = source_points.dtype
    return ICPResult(
        s=float(s),
        R=torch.from_numpy(rotation).to(dtype),
        t=torch.from_numpy(translation).to(dtype),
        rmse=rmse,
        iterations=iterations,
        converged=converged,
        num_pairs=len(residual),
    )
