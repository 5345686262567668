r"""Euler-angle rotations for head poses.

The angles are ``(roll, pitch, yaw)`` in radians and compose as

.. math::

    R = R_y(\text{yaw})\, R_x(\text{pitch})\, R_z(\text{roll}),

so a vector is rolled about the optical axis first, then pitched about x, then yawed about y.
The singularity of this order is at pitch = ±90°, outside the range of head poses, so profile
views (yaw = ±90°) keep unique angles. See ``docs/conventions.md`` for the signs.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from facenormals.core.check import check_finite, check_floating, check_shape, values_readable

__all__ = ["euler_rotation_derivatives", "euler_to_rotation_matrix", "rotation_matrix_to_euler"]


def euler_to_rotation_matrix(angles: Tensor) -> Tensor:
    r"""Rotation matrices from ``(roll, pitch, yaw)`` angles.

    Computes :math:`R = R_y(\text{yaw}) R_x(\text{pitch}) R_z(\text{roll})` with right-handed
    elementary rotations, e.g. :math:`R_x(\alpha) = [[1,0,0],[0,\cos\alpha,-\sin\alpha],
    [0,\sin\alpha,\cos\alpha]]`.

    Args:
        angles: roll, pitch and yaw in radians.

    Returns:
        The rotation matrices.

    Raises:
        ValueError: if ``angles`` is not a floating tensor of shape ``(B, 3)`` with finite values.

    Shape:
        - angles: :math:`(B, 3)`
        - output: :math:`(B, 3, 3)`

    Example:
        >>> R = euler_to_rotation_matrix(torch.tensor([[0.0, 0.0, 0.5]]))
        >>> R.shape
        torch.Size([1, 3, 3])
        >>> torch.allclose(R @ R.transpose(1, 2), torch.eye(3).expand(1, 3, 3), atol=1e-6)
        True
    """
    check_shape(angles, ["B", 3], "angles")
    check_floating(angles, "angles")
    check_finite(angles, "angles")
    return _rotation(angles)


def _rotation(angles: Tensor) -> Tensor:
    """:func:`euler_to_rotation_matrix` without the input checks."""
    cr, cp, cy = torch.cos(angles).unbind(-1)
    sr, sp, sy = torch.sin(angles).unbind(-1)
    # Product R_y(yaw) @ R_x(pitch) @ R_z(roll), written out (sp·sr and sp·cr shared).
    sp_sr, sp_cr = sp * sr, sp * cr
    r00 = cy * cr + sy * sp_sr
    r01 = sy * sp_cr - cy * sr
    r02 = sy * cp
    r10 = cp * sr
    r11 = cp * cr
    r12 = -sp
    r20 = cy * sp_sr - sy * cr
    r21 = sy * sr + cy * sp_cr
    r22 = cy * cp
    return torch.stack([r00, r01, r02, r10, r11, r12, r20, r21, r22], dim=-1).reshape(-1, 3, 3)


def euler_rotation_derivatives(angles: Tensor) -> Tensor:
    r"""Derivatives of :func:`euler_to_rotation_matrix` with respect to roll, pitch and yaw.

    Used to build analytic Jacobians of poses: :math:`\partial (R p) / \partial \theta_j = D_j p`.

    Args:
        angles: roll, pitch and yaw in radians.

    Returns:
        ``D`` with ``D[:, j] = dR / d angles[:, j]``.

    Shape:
        - angles: :math:`(B, 3)`
        - output: :math:`(B, 3, 3, 3)`

    Example:
        >>> euler_rotation_derivatives(torch.zeros(2, 3)).shape
        torch.Size([2, 3, 3, 3])
    """
    check_shape(angles, ["B", 3], "angles")
    check_floating(angles, "angles")
    check_finite(angles, "angles")
    # With the generators G_a = [e_a]× (R_a' = G_a R_a = R_a G_a): dR/droll = R G_z, dR/dyaw = G_y R and
    # dR/dpitch = R_y G_x R_x R_z = [R_y e_x]× R, each a few column or row moves of R.
    R = _rotation(angles)
    yaw = angles[:, 2]
    zero = torch.zeros_like(R[:, 0])
    d_roll = torch.stack([R[:, :, 1], -R[:, :, 0], zero], dim=-1)
    axis = torch.stack([torch.cos(yaw), torch.zeros_like(yaw), -torch.sin(yaw)], dim=-1)  # R_y e_x
    d_pitch = torch.linalg.cross(axis[:, :, None].expand_as(R), R, dim=1)
    d_yaw = torch.stack([R[:, 2], zero, -R[:, 0]], dim=1)
    return torch.stack([d_roll, d_pitch, d_yaw], dim=1)


def rotation_matrix_to_euler(rotation: Tensor) -> Tensor:
    r"""``(roll, pitch, yaw)`` angles of rotation matrices; inverse of :func:`euler_to_rotation_matrix`.

    Uses ``pitch = atan2(-R[1,2], hypot(R[1,0], R[1,1]))``, ``roll = atan2(R[1,0], R[1,1])`` and
    ``yaw = atan2(R[0,2], R[2,2])``. Exact for ``|pitch| < π/2``; roll and yaw lie in ``(-π, π]``.
    At the singularity ``|pitch| = π/2`` roll and yaw turn about the same axis and only
    ``yaw ∓ roll`` is determined: within ``sqrt(eps)`` of it (``hypot(R[1,0], R[1,1])`` below the
    square root of the dtype's resolution, where the formulas above would divide rounding noise)
    roll is 0 and ``yaw = atan2(sign(-R[1,2]) R[0,1], R[0,0])``, so that the angles still give back
    ``R`` (to about ``sqrt(eps)``). Gradients are finite everywhere: at exactly ``|pitch| = π/2``,
    the kink of the hypot, the pitch's gradient in ``R[1,0]`` and ``R[1,1]`` is 0.

    The matrices must be rotations: orthonormal, :math:`\max |R^T R - I| \le 10^{-3}` (or 8 times
    the dtype's resolution where that is larger: float16, bfloat16), with determinant +1. That
    admits float32 rotations from OpenCV (``cv2.Rodrigues``) or an SVD, about 1e-6 off, and refuses
    reflections and scaled matrices, whose angles would not give them back.

    Args:
        rotation: rotation matrices.

    Returns:
        Angles in radians.

    Raises:
        ValueError: if ``rotation`` is not a floating tensor of shape ``(B, 3, 3)`` with finite values,
            or holds a matrix that is not a rotation (see above).

    Shape:
        - rotation: :math:`(B, 3, 3)`
        - output: :math:`(B, 3)`

    Example:
        >>> angles = torch.tensor([[0.1, -0.2, 1.3]], dtype=torch.float64)
        >>> rotation_matrix_to_euler(euler_to_rotation_matrix(angles))
        tensor([[ 0.1000, -0.2000,  1.3000]], dtype=torch.float64)
    """
    check_shape(rotation, ["B", 3, 3], "rotation")
    check_floating(rotation, "rotation")
    check_finite(rotation, "rotation")
    _check_rotation(rotation)
    return _euler(rotation)


def _check_rotation(rotation: Tensor) -> None:
    """Raise ``ValueError`` unless every matrix of ``rotation`` ``(B, 3, 3)`` (finite) is a rotation, to
    the tolerance of :func:`rotation_matrix_to_euler`. Like ``check_finite`` it reads values, so it is
    skipped while ``torch.compile`` traces and for tensors that ``torch.func`` wraps."""
    if rotation.shape[0] == 0 or not values_readable(rotation):
        return
    work = rotation.detach().to(torch.promote_types(rotation.dtype, torch.float32))
    eye = torch.eye(3, dtype=work.dtype, device=work.device)
    error = (work.transpose(1, 2) @ work - eye).abs().amax((1, 2))
    det = torch.linalg.det(work)
    tolerance = max(1e-3, 8 * torch.finfo(rotation.dtype).eps)
    bad = (error > tolerance) | (det <= 0)
    if bool(bad.any()):
        raise ValueError(f"rotation: expected rotation matrices, orthonormal with det +1 (max |R^T R - I| <= "
                         f"{tolerance:g}), got {int(bad.sum())} of {rotation.shape[0]} that are not (largest "
                         f"|R^T R - I| {float(error.max()):.3g}, smallest det {float(det.min()):.3g})")


def _euler(rotation: Tensor) -> Tensor:
    """:func:`rotation_matrix_to_euler` without the input checks."""
    r10, r11, r12 = rotation[:, 1, 0], rotation[:, 1, 1], rotation[:, 1, 2]
    squared = r10 * r10 + r11 * r11
    positive = squared > 0  # sqrt's derivative is infinite at 0 (times 0: NaN at pitch exactly ±90°)
    cos_pitch = torch.where(positive, torch.sqrt(torch.where(positive, squared, 1.0)), 0.0)
    pitch = torch.atan2(-r12, cos_pitch)
    # Gimbal lock: roll 0, yaw from the top-left block. Each atan2 (and the sqrt above) gets harmless
    # arguments where its result is not used, so that no 0/0 reaches the gradients through torch.where.
    lock = cos_pitch <= torch.finfo(rotation.dtype).eps ** 0.5
    zero, one = torch.zeros_like(r10), torch.ones_like(r10)
    roll = torch.atan2(torch.where(lock, zero, r10), torch.where(lock, one, r11))
    free_yaw = torch.atan2(torch.where(lock, zero, rotation[:, 0, 2]), torch.where(lock, one, rotation[:, 2, 2]))
    locked_yaw = torch.atan2(torch.where(lock, torch.sign(-r12) * rotation[:, 0, 1], zero),
                             torch.where(lock, rotation[:, 0, 0], one))
    yaw = torch.where(lock, locked_yaw, free_yaw)
    angles = torch.stack([roll, pitch, yaw], dim=-1)
    return torch.where(angles <= -math.pi, -angles, angles)  # atan2(-0.0, x < 0) = -π: keep (-π, π]
