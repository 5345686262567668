r"""Pinhole projection with the paper's parametrisation ``a = (1/z) K R (p + t)``."""

from __future__ import annotations

import torch
from torch import Tensor

from facenormals.core.check import (
    check_all_finite, check_floating, check_positive, check_same_dtype_device, check_shape, values_readable,
)

__all__ = ["project_points", "projection_jacobian", "transform_points"]

_HALF = (torch.float16, torch.bfloat16)


def _check_pose(points: Tensor, rotation: Tensor, translation: Tensor, **intrinsics: Tensor) -> dict[str, int]:
    dims = check_shape(points, ["B", "N", 3], "points")
    check_shape(rotation, ["B", 3, 3], "rotation", dims)
    check_shape(translation, ["B", 3], "translation", dims)
    for name, x in intrinsics.items():
        check_shape(x, ["B", 3], name, dims)
    check_floating(points, "points")
    check_same_dtype_device(points, "points", rotation=rotation, translation=translation, **intrinsics)
    check_all_finite(points=points, rotation=rotation, translation=translation, **intrinsics)
    return dims


def _check_focal(intrinsics: Tensor) -> None:
    if values_readable(intrinsics) and not bool((intrinsics[:, 0] > 0).all()):  # not under compile or vmap
        raise ValueError(f"intrinsics: expected focal lengths f > 0, got {intrinsics[:, 0].min().item():g}")


def transform_points(points: Tensor, rotation: Tensor, translation: Tensor) -> Tensor:
    r"""Model points to the camera frame, :math:`X_c = R (p + t)`.

    The translation is added in the model frame, **before** the rotation (the paper's convention;
    OpenCV's ``tvec`` equals ``R t``).

    Args:
        points: model points ``p`` in mm.
        rotation: rotation matrices ``R``.
        translation: translations ``t`` in the model frame, in mm.

    Returns:
        Points in the camera frame.

    Shape:
        - points: :math:`(B, N, 3)`
        - rotation: :math:`(B, 3, 3)`
        - translation: :math:`(B, 3)`
        - output: :math:`(B, N, 3)`

    Example:
        >>> transform_points(torch.zeros(1, 2, 3), torch.eye(3)[None], torch.tensor([[0.0, 0.0, 500.0]])).shape
        torch.Size([1, 2, 3])
    """
    _check_pose(points, rotation, translation)
    return torch.matmul(points + translation[:, None, :], rotation.transpose(1, 2))


def project_points(
    points: Tensor,
    rotation: Tensor,
    translation: Tensor,
    intrinsics: Tensor,
    eps: float = 1e-9,
) -> tuple[Tensor, Tensor]:
    r"""Project model points to pixels with :math:`a = \frac{1}{z} K R (p + t)`.

    With :math:`X_c = R (p + t) = (x, y, z)` and :math:`K = [[f, 0, u_0], [0, f, v_0]]` the pixel is
    :math:`(f x / z + u_0,\; f y / z + v_0)`. The camera is OpenCV's (x right, y down, z forward) and
    pixel ``(0, 0)`` is the centre of the top-left pixel. Depths with ``|z| < eps`` are clamped to
    ``eps`` (keeping their sign) before the division; callers should mask ``depth <= 0``.

    Args:
        points: model points ``p`` in mm.
        rotation: rotation matrices ``R``.
        translation: translations ``t`` in the model frame, in mm.
        intrinsics: ``(f, u0, v0)`` in pixels.
        eps: smallest depth magnitude used in the division.

    Returns:
        ``(pixels, depth)``: the pixel coordinates ``(u, v)`` and the camera-frame depth ``z``.

    Raises:
        ValueError: on wrong shapes, mismatched batch sizes, non-floating or non-finite inputs, a
            focal length ``f <= 0`` or an ``eps`` that is not a finite number > 0.

    Shape:
        - points: :math:`(B, N, 3)`
        - rotation: :math:`(B, 3, 3)`
        - translation: :math:`(B, 3)`
        - intrinsics: :math:`(B, 3)`
        - pixels: :math:`(B, N, 2)`
        - depth: :math:`(B, N)`

    Example:
        >>> pts = torch.tensor([[[10.0, -20.0, 0.0]]])
        >>> uv, z = project_points(pts, torch.eye(3)[None], torch.tensor([[0.0, 0.0, 500.0]]),
        ...                        torch.tensor([[1000.0, 64.0, 64.0]]))
        >>> uv, z
        (tensor([[[84., 24.]]]), tensor([[500.]]))
    """
    _check_pose(points, rotation, translation, intrinsics=intrinsics)
    _check_focal(intrinsics)
    eps = check_positive(eps, "eps")
    if points.dtype in _HALF:  # f·x overflows float16 at ~65k (f = 1000 px, x = 66 mm); exact in float32
        pixels, z = project_points(points.float(), rotation.float(), translation.float(), intrinsics.float(), eps)
        return pixels.to(points.dtype), z.to(points.dtype)
    camera = torch.matmul(points + translation[:, None, :], rotation.transpose(1, 2))
    z = camera[..., 2]
    z_safe = torch.where(z.abs() < eps, torch.full_like(z, eps) * torch.where(z < 0, -1.0, 1.0), z)
    f = intrinsics[:, None, 0:1]
    center = intrinsics[:, None, 1:3]
    pixels = f * camera[..., :2] / z_safe[..., None] + center
    return pixels, z


def projection_jacobian(camera_points: Tensor, intrinsics: Tensor, eps: float = 1e-9) -> Tensor:
    r"""Jacobian of the pixel ``(u, v)`` with respect to the camera-frame point :math:`X_c = (x, y, z)`.

    .. math::

        \frac{\partial (u, v)}{\partial X_c} = \frac{f}{z}
        \begin{pmatrix} 1 & 0 & -x/z \\ 0 & 1 & -y/z \end{pmatrix}

    Chain it with :math:`\partial X_c / \partial p = R` (shape), :math:`R` (translation) or the
    rotation derivatives of :func:`~facenormals.geometry.euler_rotation_derivatives` (pose).

    Args:
        camera_points: points in the camera frame.
        intrinsics: ``(f, u0, v0)``.
        eps: smallest depth magnitude, as in :func:`project_points`.

    Raises:
        ValueError: on wrong shapes, mismatched batch sizes, non-floating or non-finite inputs, a
            focal length ``f <= 0`` or an ``eps`` that is not a finite number > 0.

    Shape:
        - camera_points: :math:`(B, N, 3)`; intrinsics: :math:`(B, 3)`
        - output: :math:`(B, N, 2, 3)`

    Example:
        >>> projection_jacobian(torch.tensor([[[0.0, 0.0, 2.0]]]), torch.tensor([[4.0, 0.0, 0.0]]))
        tensor([[[[2., 0., -0.],
                  [0., 2., -0.]]]])
    """
    dims = check_shape(camera_points, ["B", "N", 3], "camera_points")
    check_shape(intrinsics, ["B", 3], "intrinsics", dims)
    check_floating(camera_points, "camera_points")
    check_same_dtype_device(camera_points, "camera_points", intrinsics=intrinsics)
    check_all_finite(camera_points=camera_points, intrinsics=intrinsics)
    _check_focal(intrinsics)
    eps = check_positive(eps, "eps")
    if camera_points.dtype in _HALF:
        return projection_jacobian(camera_points.float(), intrinsics.float(), eps).to(camera_points.dtype)
    x, y, z = camera_points.unbind(-1)
    z = torch.where(z.abs() < eps, torch.full_like(z, eps) * torch.where(z < 0, -1.0, 1.0), z)
    scale = intrinsics[:, None, 0] / z
    zero = torch.zeros_like(x)
    row_u = torch.stack([scale, zero, -scale * x / z], dim=-1)
    row_v = torch.stack([zero, scale, -scale * y / z], dim=-1)
    return torch.stack([row_u, row_v], dim=-2)
