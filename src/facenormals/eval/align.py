r"""Rough alignment by corresponding points: closed-form rigid and similarity transforms.

:func:`fit_similarity` is Umeyama's (1991) least-squares solution of

.. math:: \min_{s, R, t} \sum_i w_i \lVert s R x_i + t - y_i \rVert^2,
          \qquad R \in SO(3),\ s > 0,

batched over ``B`` problems: with weighted centroids :math:`\bar x, \bar y` and
:math:`\Sigma = \sum_i w_i (y_i - \bar y)(x_i - \bar x)^T / \sum_i w_i = U S V^T`,
:math:`R = U D V^T` with :math:`D = \operatorname{diag}(1, 1, \operatorname{sign}\det(U V^T))` (so
:math:`\det R = +1` even when the best orthogonal matrix would be a reflection),
:math:`s = \operatorname{tr}(S D) / \sigma_x^2` (or 1 for a rigid fit) and
:math:`t = \bar y - s R \bar x`. It is differentiable through :func:`torch.linalg.svd` wherever the
singular values are distinct.

The evaluation protocol starts from six pre-selected corresponding points,
:data:`DEFAULT_ALIGNMENT_LANDMARKS`: the four eye corners, the nose tip and the chin.
"""

from __future__ import annotations

from typing import Mapping, Sequence

import torch
from torch import Tensor

from facenormals.core.check import (
    check_all_finite,
    check_finite,
    check_floating,
    check_integer,
    check_same_dtype_device,
    check_shape,
    values_readable,
)
from facenormals.geometry.rotation import _check_rotation  # the tolerance of rotation_matrix_to_euler
from facenormals.models.landmarks import IBUG68_OF_LANDMARK

__all__ = ["DEFAULT_ALIGNMENT_LANDMARKS", "apply_similarity", "fit_similarity", "landmark_correspondences"]

#: The six landmarks of the rough alignment: eye corners ×4, nose tip, chin (names of
#: :data:`facenormals.models.LANDMARK_NAMES`). They are rigid-ish and spread over the face.
DEFAULT_ALIGNMENT_LANDMARKS: tuple[str, ...] = (
    "right_eye_outer", "right_eye_inner", "left_eye_inner", "left_eye_outer", "nose_tip", "chin",
)  # fmt: skip


def fit_similarity(
    source: Tensor,
    target: Tensor,
    weights: Tensor | None = None,
    scale: bool = True,
) -> tuple[Tensor, Tensor, Tensor]:
    r"""Least-squares similarity (or rigid) transform with ``target ≈ s · R · source + t``.

    Args:
        source: points :math:`x_i` to be mapped.
        target: corresponding points :math:`y_i`.
        weights: optional non-negative weights :math:`w_i` (each problem needs a positive sum).
        scale: fit the scale :math:`s`; with ``False`` the fit is rigid and ``s`` is 1.

    Returns:
        ``(s, R, t)``: scales, proper rotations (:math:`\det R = +1`) and translations, with the
        dtype and device of ``source``.

    Raises:
        ValueError: on badly shaped, non-floating or non-finite inputs, fewer than 3 points,
            negative / all-zero weights, or points (with positive weight) that do not span a plane.

    Shape:
        - source, target: :math:`(B, N, 3)`, :math:`N \ge 3`
        - weights: :math:`(B, N)`
        - output: :math:`(B,)`, :math:`(B, 3, 3)`, :math:`(B, 3)`

    Example:
        >>> source = torch.tensor([[[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]]])
        >>> R = torch.tensor([[[0.0, -1, 0], [1, 0, 0], [0, 0, 1]]])  # 90° about z
        >>> target = 2.0 * source @ R.transpose(1, 2) + torch.tensor([1.0, 2, 3])
        >>> s, R_fit, t = fit_similarity(source, target)
        >>> s.shape, R_fit.shape, t.shape
        (torch.Size([1]), torch.Size([1, 3, 3]), torch.Size([1, 3]))
        >>> round(s.item(), 4), torch.allclose(R_fit, R, atol=1e-5), t.round(decimals=4)
        (2.0, True, tensor([[1., 2., 3.]]))
    """
    dims = check_shape(source, ["B", "N", 3], "source")
    check_shape(target, ["B", "N", 3], "target", dims)
    for name, x in (("source", source), ("target", target)):
        check_floating(x, name)
        check_finite(x, name)
    if dims["N"] < 3:
        raise ValueError(f"source: expected at least 3 points, got shape {tuple(source.shape)}")
    target = target.to(source)
    if weights is None:
        w = source.new_full(source.shape[:2], 1.0 / dims["N"])
    else:
        check_shape(weights, ["B", "N"], "weights", dims)
        check_floating(weights, "weights")
        check_finite(weights, "weights")
        weights = weights.to(source)
        if bool((weights < 0).any()):
            raise ValueError("weights: expected non-negative values")
        total = weights.sum(dim=1, keepdim=True)
        if bool((total <= 0).any()):
            raise ValueError("weights: expected a positive sum for every problem")
        w = weights / total
    if source.dtype in (torch.float16, torch.bfloat16):  # torch has no half-precision SVD
        s_, rotation, t = fit_similarity(source.float(), target.float(), w.float(), scale)
        return s_.to(source.dtype), rotation.to(source.dtype), t.to(source.dtype)
    mu_s = (w[..., None] * source).sum(dim=1)
    mu_t = (w[..., None] * target).sum(dim=1)
    xs = source - mu_s[:, None]
    yt = target - mu_t[:, None]
    cov = torch.einsum("bn,bni,bnj->bij", w, yt, xs)
    u, sing, vh = torch.linalg.svd(cov)
    flat = sing[:, 1] <= 10 * torch.finfo(sing.dtype).eps * sing[:, 0]
    if bool(flat.any()):
        raise ValueError(
            "source, target: expected corresponding points that span a plane (on one line or at one point the "
            f"rotation is undetermined), got degenerate points in problem(s) {torch.nonzero(flat).flatten().tolist()}"
        )
    sign = torch.sign(torch.det(u) * torch.det(vh))
    sign = torch.where(sign == 0, torch.ones_like(sign), sign)
    d = torch.stack([torch.ones_like(sign), torch.ones_like(sign), sign], dim=-1)
    rotation = u @ (d[..., None] * vh)
    if scale:
        var_s = (w * xs.square().sum(dim=-1)).sum(dim=1)
        tiny = torch.finfo(source.dtype).tiny
        s = (sing * d).sum(dim=-1) / var_s.clamp_min(tiny)
    else:
        s = torch.ones_like(sign)
    t = mu_t - s[:, None] * (rotation @ mu_s[..., None])[..., 0]
    return s, rotation, t


def apply_similarity(points: Tensor, s: Tensor, rotation: Tensor, translation: Tensor) -> Tensor:
    """Map ``points`` by ``s · R · p + t`` (the transform returned by :func:`fit_similarity`).

    Shape:
        - points: :math:`(B, N, 3)`; s: :math:`(B,)`; rotation: :math:`(B, 3, 3)`;
          translation: :math:`(B, 3)`; output: :math:`(B, N, 3)`

    Raises:
        ValueError: on badly shaped inputs, mixed dtypes or devices, non-finite ``s``, ``rotation`` or
            ``translation``, a scale ``<= 0`` or a matrix that is not a rotation (orthonormal with
            det +1, to the tolerance of :func:`~facenormals.geometry.rotation_matrix_to_euler`).

    Example:
        >>> p = torch.ones(1, 2, 3)
        >>> apply_similarity(p, torch.tensor([2.0]), torch.eye(3)[None], torch.tensor([[0.0, 0, 1]]))
        tensor([[[2., 2., 3.],
                 [2., 2., 3.]]])
    """
    dims = check_shape(points, ["B", "N", 3], "points")
    check_shape(s, ["B"], "s", dims)
    check_shape(rotation, ["B", 3, 3], "rotation", dims)
    check_shape(translation, ["B", 3], "translation", dims)
    check_floating(points, "points")
    check_same_dtype_device(points, "points", s=s, rotation=rotation, translation=translation)
    # a NaN, zero or negative scale, or a matrix that is no rotation, would map every point silently wrong
    check_all_finite(s=s, rotation=rotation, translation=translation)
    if values_readable(s) and bool((s <= 0).any()):
        raise ValueError(f"s: expected scales > 0, got {int((s <= 0).sum())} of {s.shape[0]} <= 0 "
                         f"(smallest {float(s.min()):.3g})")
    _check_rotation(rotation)
    return s[:, None, None] * (points @ rotation.transpose(1, 2)) + translation[:, None, :]


def _lookup(landmarks: Mapping[str, int], name: str, argument: str) -> int:
    ibug = IBUG68_OF_LANDMARK.get(name)
    for key in (name, None if ibug is None else f"ibug_{ibug:02d}"):
        if key in landmarks:  # int() would truncate 10.9 and take True for 1
            return check_integer(landmarks[key], f"{argument}[{key!r}]", minimum=0)
    raise ValueError(
        f"{argument}: expected landmark {name!r} (or its iBUG-68 equivalent), got names {sorted(landmarks)}"
    )


def landmark_correspondences(
    source_landmarks: Mapping[str, int],
    target_landmarks: Mapping[str, int],
    names: Sequence[str] = DEFAULT_ALIGNMENT_LANDMARKS,
    *,
    source_name: str = "source_landmarks",
    target_name: str = "target_landmarks",
) -> Tensor:
    """Index pairs ``(K, 2)`` = ``(source vertex, target vertex)`` of the named landmarks.

    A name missing from a mapping is also looked up under its iBUG-68 name (``ibug_36`` for
    ``right_eye_outer``, ...), which is how the ICT-FaceKit loader names its landmarks.

    Args:
        source_landmarks: landmark name → vertex index of the source mesh.
        target_landmarks: the same for the target mesh.
        names: the landmarks to pair.
        source_name: what errors call ``source_landmarks`` (e.g. the file it came from).
        target_name: what errors call ``target_landmarks``.

    Raises:
        ValueError: naming the mapping that lacks a landmark.

    Example:
        >>> ict = {f"ibug_{i:02d}": 100 + i for i in range(68)}
        >>> landmark_correspondences(ict, ict, ["right_eye_outer", "nose_tip", "chin"])
        tensor([[136, 136],
                [130, 130],
                [108, 108]])
    """
    rows = [
        (_lookup(source_landmarks, n, source_name), _lookup(target_landmarks, n, target_name))
        for n in names
    ]
    return torch.tensor(rows, dtype=torch.long).reshape(-1, 2)
