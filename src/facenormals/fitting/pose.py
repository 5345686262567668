r"""Landmark pre-alignment: the 6-DoF head pose of a fixed shape from 2D landmarks.

Minimises :math:`E_Z = \tfrac12 \sum_j \lVert a_j(\theta, t) - b_j \rVert^2` over the Euler angles
:math:`\theta` and the translation :math:`t` with the batched Levenberg-Marquardt solver and an
analytic Jacobian, from several yaw starts at once (one batch), and keeps the best start per view.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import torch
from torch import Tensor

from facenormals.core.check import (check_all_finite, check_finite, check_floating, check_same_dtype_device, check_shape,
                                    check_tensor)
from facenormals.fitting.robust import cauchy_weights, check_scale
from facenormals.geometry import euler_to_rotation_matrix
from facenormals.geometry.rotation import _euler, _rotation
from facenormals.optim import LMStatus, levenberg_marquardt

__all__ = ["FACING_AWAY_COSINE", "PoseEstimate", "facing_cosine", "landmark_pose_jacobian", "prealign_pose"]

DEFAULT_YAW_STARTS = (-70.0, -25.0, 25.0, 70.0)
#: The reweighted solves of :func:`prealign_pose` stop once no landmark weight changes by more than this.
IRLS_WEIGHT_TOLERANCE = 0.02
#: Relative cost reduction that ends each reweighted solve: the weights themselves are only settled
#: to ``IRLS_WEIGHT_TOLERANCE``, so solving each weighted problem to the plain solve's 1e-7 buys
#: digits the next reweighting discards (it changes the pose by < 0.05° here, and saves a solve's
#: last iteration).
IRLS_FTOL = 1e-4


@dataclass
class PoseEstimate:
    """Result of :func:`prealign_pose` for ``B`` views.

    Attributes:
        angles: ``(B, 3)`` roll, pitch, yaw in radians.
        translation: ``(B, 3)`` translation ``t`` of :math:`X_c = R (p + t)`, mm.
        rotation: ``(B, 3, 3)``.
        cost: ``(B,)`` final :math:`E_Z` (px²).
        rms_px: ``(B,)`` root-mean-square landmark error in pixels.
        status: ``(B,)`` :class:`~facenormals.optim.LMStatus` of the last solve of each view: the best
            start's, or that of the last Cauchy-reweighted solve with ``robust_scale``.
    """

    angles: Tensor
    translation: Tensor
    rotation: Tensor
    cost: Tensor
    rms_px: Tensor
    status: Tensor


def require_pose_landmarks(model) -> None:
    """Raise ``ValueError`` unless ``model`` names at least 4 landmarks, the fewest a pre-alignment takes."""
    if len(model.landmark_names) < 4:
        raise ValueError(f"model: {model.name!r} has {len(model.landmark_names)} named landmarks; at least 4 are "
                         "needed to pre-align a head: attach them with MorphableModel.with_annotations "
                         "(docs/models.md)")


def landmark_pose_jacobian(points: Tensor, x: Tensor, intrinsics: Tensor, mask: Tensor | None = None) -> Tensor:
    r"""Jacobian of projected points with respect to the pose ``x = (roll, pitch, yaw, tx, ty, tz)``.

    With :math:`X_c = R(\theta)(p + t)` and :math:`P = \partial a / \partial X_c`:
    :math:`\partial a / \partial \theta_j = P\, D_j (p + t)` and :math:`\partial a / \partial t = P R`.
    Rows of masked points are zero, matching :func:`~facenormals.energy.landmark_residuals`.

    Shape:
        - points: :math:`(B, L, 3)`; x: :math:`(B, 6)`; intrinsics: :math:`(B, 3)`; mask: :math:`(B, L)`
        - output: :math:`(B, 2L, 6)` (empty for ``B = 0`` or ``L = 0``)

    Example:
        >>> landmark_pose_jacobian(torch.zeros(1, 4, 3), torch.tensor([[0.0, 0, 0, 0, 0, 500]]),
        ...                        torch.tensor([[500.0, 64, 64]])).shape
        torch.Size([1, 8, 6])
    """
    dims = check_shape(points, ["B", "L", 3], "points")
    check_shape(x, ["B", 6], "x", dims)
    check_shape(intrinsics, ["B", 3], "intrinsics", dims)
    check_floating(points, "points")
    check_same_dtype_device(points, "points", x=x, intrinsics=intrinsics)
    check_all_finite(points=points, x=x, intrinsics=intrinsics)  # NaN or inf would come back as NaN entries
    if mask is not None:
        check_shape(mask, ["B", "L"], "mask", dims)
        if mask.dtype != torch.bool:
            raise ValueError(f"mask: expected a bool tensor, got dtype {mask.dtype}")
    return _pose_jacobian(x, points, intrinsics, mask)


def _pose_camera(x: Tensor, points: Tensor) -> tuple[Tensor, Tensor]:
    """``R`` ``(B, 3, 3)`` and the camera points ``R (p + t)`` ``(B, L, 3)`` of the poses ``x``."""
    R = _rotation(x[:, :3])
    return R, torch.matmul(points + x[:, None, 3:], R.transpose(1, 2))


def _safe_depth(z: Tensor) -> Tensor:
    """Depths clamped away from zero as :func:`~facenormals.geometry.project_points` does (eps 1e-9)."""
    eps = torch.full_like(z, 1e-9)
    return torch.where(z.abs() < eps, torch.where(z < 0, -eps, eps), z)


def _pose_jacobian(x: Tensor, points: Tensor, intrinsics: Tensor, mask: Tensor | None) -> Tensor:
    """:func:`landmark_pose_jacobian` without its input checks."""
    R, camera = _pose_camera(x, points)
    return _jacobian_at(x, R, camera, _safe_depth(camera[..., 2]), intrinsics, mask)


def _jacobian_at(x: Tensor, R: Tensor, camera: Tensor, z: Tensor, intrinsics: Tensor, mask: Tensor | None,
                 arm: Tensor | None = None) -> Tensor:
    r"""The pose Jacobian ``(B, 2L, 6)`` from the camera points ``camera`` of ``x`` and their safe depths ``z``.

    The Euler rotations' derivatives (``euler_rotation_derivatives``) move a camera point by
    :math:`\omega_j \times X_c` about the axes :math:`\omega = (R e_z, R_y e_x, e_y)` (roll, pitch,
    yaw), and :math:`\partial X_c / \partial t = R`. With ``arm`` (``R p``, for the camera-frame
    translation :math:`T` of :math:`X_c = R p + T`), the rotations move :math:`\omega_j \times R p`
    and :math:`\partial X_c / \partial T = I`."""
    lever = camera if arm is None else arm
    cx, cy, cz = lever.unbind(-1)
    zero = torch.zeros_like(cx)
    d_roll = torch.linalg.cross(R[:, None, :, 2].expand_as(lever), lever)
    cos_yaw, sin_yaw = torch.cos(x[:, 2:3]), torch.sin(x[:, 2:3])
    d_pitch = torch.stack([sin_yaw * cy, -sin_yaw * cx - cos_yaw * cz, cos_yaw * cy], dim=-1)
    d_yaw = torch.stack([cz, zero, -cx], dim=-1)
    # (B, L, 3, 6): d X_c[k] / d x[j]
    d_translation = R if arm is None else torch.eye(3, dtype=R.dtype, device=R.device).expand_as(R)
    d_camera = torch.cat([torch.stack([d_roll, d_pitch, d_yaw], dim=-1),
                          d_translation[:, None].expand(-1, cx.shape[1], 3, 3)], dim=-1)
    ratio = (camera[..., :2] / z[..., None])[..., None]  # (B, L, 2, 1)
    J = (intrinsics[:, None, 0] / z)[..., None, None] * (d_camera[..., :2, :] - ratio * d_camera[..., 2:3, :])
    if mask is not None:
        J = torch.where(mask[..., None, None], J, torch.zeros((), dtype=J.dtype, device=J.device))
    return J.flatten(1, 2)  # (B, 2L, 6); a reshape to (B, -1, 6) cannot infer -1 for B = 0 or L = 0


class _LandmarkTerms:
    """Residuals ``(B, 2L)`` and Jacobian ``(B, 2L, 6)`` of the pose LM, optionally weighted per landmark,
    without input checks (:func:`prealign_pose` checked them once). The LM asks for the Jacobian at the
    trial point whose residuals it evaluated last, so the two share that point's camera geometry.

    Poses here hold the camera-frame translation: ``x = (roll, pitch, yaw, T)`` with
    :math:`X_c = R p + T`, i.e. ``T = R t`` for the ``t`` of :math:`X_c = R (p + t)` that
    :func:`prealign_pose` returns. With ``t`` in the model frame a yaw step swings the head sideways
    by ``|t| sin``: at long focal lengths (``|t|`` of metres) the yaw and ``t`` are tied in a narrow
    curved valley where the LM crawls (40 iterations left the yaw 3-18° short at f = 3·10⁴-2·10⁵ px
    on a 128² image, and at 10⁶ px it stayed at its start); ``T`` keeps them apart."""

    def __init__(self, points: Tensor, targets: Tensor, mask: Tensor, intrinsics: Tensor,
                 sqrt_weights: Tensor | None = None) -> None:
        self.points, self.targets, self.mask, self.intrinsics = points, targets, mask, intrinsics
        self.sqrt_weights = sqrt_weights  # (B, L, 1) or None
        self._x: Tensor | None = None
        self._geometry: tuple[Tensor, Tensor, Tensor, Tensor] = ()  # type: ignore[assignment]

    def geometry(self, x: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """``R``, the camera points, their safe depths and the arms ``R p`` of the rotations."""
        if self._x is None or not torch.equal(x, self._x):
            R = _rotation(x[:, :3])
            arm = torch.matmul(self.points, R.transpose(1, 2))
            camera = arm + x[:, None, 3:]
            self._x, self._geometry = x, (R, camera, _safe_depth(camera[..., 2]), arm)
        return self._geometry

    def residuals(self, x: Tensor) -> Tensor:
        _, camera, z, _ = self.geometry(x)
        pixels = self.intrinsics[:, None, 0:1] * camera[..., :2] / z[..., None] + self.intrinsics[:, None, 1:]
        r = torch.where(self.mask[..., None], pixels - self.targets, torch.zeros((), dtype=x.dtype, device=x.device))
        return (r if self.sqrt_weights is None else r * self.sqrt_weights).flatten(1)

    def jacobian(self, x: Tensor) -> Tensor:
        R, camera, z, arm = self.geometry(x)
        J = _jacobian_at(x, R, camera, z, self.intrinsics, self.mask, arm)
        if self.sqrt_weights is not None:
            J = (J.view(J.shape[0], -1, 2, 6) * self.sqrt_weights[..., None]).flatten(1, 2)
        return J


def _solve_pose(terms: _LandmarkTerms, x0: Tensor, max_iterations: int, ftol: float = 1e-7):
    """The pre-alignment's LM on ``terms`` from ``x0`` ``(B, 6)`` (camera-frame translations)."""
    return levenberg_marquardt(terms.residuals, x0, jacobian_fn=terms.jacobian, max_iterations=max_iterations,
                               damping=1e-4, ftol=ftol, xtol=1e-7)


def _initial_translation(points: Tensor, targets: Tensor, mask: Tensor, R: Tensor, intrinsics: Tensor) -> Tensor:
    """Camera-frame ``T`` placing the points' centroid on the ray through the landmarks' centroid, at
    the depth where their spreads match: :math:`z = f \\cdot \\mathrm{rms}_{3D} / \\mathrm{rms}_{2D}`."""
    w = mask.to(points.dtype)[..., None]
    count = w.sum(1).clamp_min(1.0)
    centroid3 = (points * w).sum(1) / count
    centroid2 = (torch.nan_to_num(targets) * w).sum(1) / count
    spread3 = (((points - centroid3[:, None]) ** 2).sum(-1, keepdim=True) * w).sum(1) / count
    spread2 = (((torch.nan_to_num(targets) - centroid2[:, None]) ** 2).sum(-1, keepdim=True) * w).sum(1) / count
    f, center = intrinsics[:, 0:1], intrinsics[:, 1:3]
    depth = f * (spread3 / spread2.clamp_min(1e-6)).sqrt()  # spread2 in px² ~ (f/z)² spread3 (x, y only)
    depth = depth * math.sqrt(2.0 / 3.0)  # the 2D spread sees two of three axes
    camera = torch.cat([(centroid2 - center) * depth / f, depth], dim=-1)
    return camera - (R @ centroid3[..., None])[..., 0]


def _pnp_starts(points: Tensor, targets: Tensor, mask: Tensor, intrinsics: Tensor,
                ransac_px: float | None = None) -> tuple[Tensor, Tensor]:
    """OpenCV SQPnP poses ``(B, 6)`` (camera-frame translations) as LM starts, and ``(B,)`` where
    OpenCV gave one (a failed view gets zeros there). With ``ransac_px``, OpenCV's RANSAC (EPnP on
    minimal sets, deterministic: it seeds its generator per call) with that reprojection threshold
    in pixels, and SQPnP on its inliers; with 4 or 5 landmarks there is no minimal set to leave an
    outlier out, and it is SQPnP on all of them."""
    import cv2
    import numpy as np

    batch = points.shape[0]
    all_obj, all_img = points.detach().cpu().double().numpy(), targets.detach().cpu().double().numpy()
    all_keep = mask.cpu().numpy()
    rotations, translations = np.tile(np.eye(3), (batch, 1, 1)), np.zeros((batch, 3))  # a failed view: zeros
    ok = np.zeros(batch, dtype=bool)
    for b, (f, u0, v0) in enumerate(intrinsics.tolist()):
        obj, img = all_obj[b][all_keep[b]], all_img[b][all_keep[b]]
        camera = np.array([[f, 0.0, u0], [0.0, f, v0], [0.0, 0.0, 1.0]])
        try:
            if ransac_px is None:
                found, rvec, tvec = cv2.solvePnP(obj, img, camera, None, flags=cv2.SOLVEPNP_SQPNP)
            else:
                found, rvec, tvec, _ = cv2.solvePnPRansac(obj, img, camera, None, flags=cv2.SOLVEPNP_SQPNP,
                                                          reprojectionError=ransac_px, iterationsCount=100,
                                                          confidence=0.999)
        except cv2.error:
            continue
        if not found or not (np.isfinite(rvec).all() and np.isfinite(tvec).all()) or tvec[2, 0] <= 0:
            continue
        R = cv2.Rodrigues(rvec)[0]
        rotations[b], translations[b], ok[b] = R, tvec[:, 0], True
    poses = torch.cat([_euler(torch.from_numpy(rotations)), torch.from_numpy(translations)], dim=-1)
    return poses.to(dtype=points.dtype, device=points.device), torch.from_numpy(ok).to(points.device)


def _pose_residuals(x: Tensor, points: Tensor, targets: Tensor, mask: Tensor, intrinsics: Tensor) -> Tensor:
    """``(B, L, 2)`` landmark residuals of the poses ``x`` (camera-frame translations; zero where
    masked), without input checks."""
    return _LandmarkTerms(points, targets, mask, intrinsics).residuals(x).view(x.shape[0], -1, 2)


#: A pose whose landmarks' normals make a mean cosine above this with the rays to them faces away
#: from the camera. Mirrored solutions of the eye corners alone score 0.5 - 0.9; true poses at most
#: about 0.15, with every landmark counted in a profile (the far side's too).
FACING_AWAY_COSINE = 0.3


def facing_cosine(points: Tensor, normals: Tensor, rotation: Tensor, translation: Tensor,
                  mask: Tensor | None = None) -> Tensor:
    r"""Mean cosine of the posed outward ``normals`` at ``points`` with the camera rays to them.

    The points are posed as :math:`R\,(p + t)` (see :func:`~facenormals.geometry.transform_points`).
    Seen surface faces the camera: its cosines are negative (about -0.2 for a profile's landmarks,
    -0.6 for a frontal face's); a mean above :data:`FACING_AWAY_COSINE` (0.3) means landmarks said to
    be seen sit on a head turned away from the camera.

    Args:
        points: model-frame points, e.g. a head's landmark vertices.
        normals: their outward unit normals, model frame.
        rotation: the poses' rotations.
        translation: the poses' translations, model frame.
        mask: which points count (default: all); a row without any gives 0.

    Shape:
        - points, normals: :math:`(B, L, 3)`; rotation: :math:`(B, 3, 3)`; translation: :math:`(B, 3)`
        - mask: :math:`(B, L)` bool; output: :math:`(B,)`

    Example:
        >>> p = torch.tensor([[[0.0, 0.0, 0.0]]]); n = torch.tensor([[[0.0, 0.0, -1.0]]])
        >>> facing_cosine(p, n, torch.eye(3)[None], torch.tensor([[0.0, 0.0, 500.0]]))
        tensor([-1.])
    """
    dims = check_shape(points, ["B", "L", 3], "points")
    check_shape(normals, ["B", "L", 3], "normals", dims)
    check_shape(rotation, ["B", 3, 3], "rotation", dims)
    check_shape(translation, ["B", 3], "translation", dims)
    for name, x in (("points", points), ("normals", normals), ("rotation", rotation), ("translation", translation)):
        check_floating(x, name)
        check_finite(x, name)
    check_same_dtype_device(points, "points", normals=normals, rotation=rotation, translation=translation)
    if mask is None:
        mask = torch.ones(points.shape[:2], dtype=torch.bool, device=points.device)
    check_shape(mask, ["B", "L"], "mask", dims)
    if mask.dtype != torch.bool:
        raise ValueError(f"mask: expected a bool tensor, got dtype {mask.dtype}")
    return _facing_cosine(points, normals, rotation, translation, mask)


def _facing_cosine(points: Tensor, normals: Tensor, R: Tensor, t: Tensor, mask: Tensor) -> Tensor:
    camera = torch.matmul(points + t[:, None], R.transpose(1, 2))  # transform_points, inputs checked
    cosine = (torch.matmul(normals, R.transpose(1, 2)) * camera).sum(-1) / camera.norm(dim=-1).clamp_min(1e-12)
    return torch.where(mask, cosine, torch.zeros_like(cosine)).sum(1) / mask.sum(1).clamp_min(1)


def _facing_camera(x: Tensor, points: Tensor, normals: Tensor | None, mask: Tensor) -> Tensor:
    """``(B,)`` whether the poses ``x`` (camera-frame translations) do not turn the view's landmarks
    away from the camera (:func:`facing_cosine` at most ``FACING_AWAY_COSINE``); all True without normals."""
    if normals is None:
        return torch.ones(x.shape[0], dtype=torch.bool, device=x.device)
    R = _rotation(x[:, :3])
    return _facing_cosine(points, normals, R, _model_translation(R, x), mask) <= FACING_AWAY_COSINE


def _model_translation(R: Tensor, x: Tensor) -> Tensor:
    """``t = Rᵀ T`` of poses ``x`` with camera-frame translations ``T`` and rotations ``R``."""
    return (R.transpose(1, 2) @ x[:, 3:, None])[..., 0]


def _best_candidates(batch: int, owner: Tensor, cost: Tensor, facing: Tensor) -> Tensor:
    """Per view, the index of its candidate (``owner`` names the view of each) of lowest ``cost``,
    preferring those ``facing`` the camera; ties go to the candidate listed first."""
    quarter = torch.full_like(cost, torch.finfo(cost.dtype).max / 4)
    cost = torch.minimum(cost, quarter) + torch.where(facing, torch.zeros_like(cost), quarter)  # facing ones win
    table = torch.full((batch, owner.shape[0]), math.inf, dtype=cost.dtype, device=cost.device)
    table[owner, torch.arange(owner.shape[0], device=owner.device)] = cost
    return table.argmin(1)


def _robust_solve(x: Tensor, status: Tensor, points: Tensor, targets: Tensor, mask: Tensor, intrinsics: Tensor,
                  scale: float, rounds: int, max_iterations: int,
                  normals: Tensor | None) -> tuple[Tensor, Tensor, Tensor]:
    r"""Cauchy-reweighted solves (IRLS) from two candidates per view, the plain solution ``x`` and
    OpenCV's RANSAC-SQPnP pose, keeping per view the one of lower Cauchy cost
    :math:`\sum_j \log(1 + (e_j / \delta)^2)`, and return its pose, status and landmark errors
    ``(B, L)`` (pixels, 0 where masked). A few grossly wrong landmarks (a network's eye corner on the
    other eye) can pull the plain solve into another basin (a 23° yaw pre-aligned to 74°) that
    reweighting from there does not leave; the RANSAC start does not see them."""
    batch = x.shape[0]
    ransac, has_ransac = _pnp_starts(points, targets, mask, intrinsics, ransac_px=2.0 * scale)
    owner = torch.cat([torch.arange(batch, device=x.device), has_ransac.nonzero().squeeze(1)])
    x, status = torch.cat([x, ransac[has_ransac]]), torch.cat([status, status[has_ransac]])
    P, b, m, K = points[owner], targets[owner], mask[owner], intrinsics[owner]
    # the weights each candidate was last solved with: 1 for the plain solution; none yet for RANSAC's
    # (2, outside any weight's range, so that it always gets a solve; its status is then its own)
    previous = torch.ones_like(b[..., 0])
    previous[batch:] = 2.0
    active = torch.ones(owner.shape[0], dtype=torch.bool, device=x.device)
    error = None  # the landmark errors at x, where known
    for _ in range(rounds):
        if error is None:
            error = _pose_residuals(x, P, b, m, K).norm(dim=-1)
        weights = cauchy_weights(error, scale)
        # per candidate, so that a batch gives each view its result alone
        change = torch.where(m, (weights - previous).abs(), torch.zeros_like(weights)).amax(-1)
        active &= change > IRLS_WEIGHT_TOLERANCE
        if not bool(active.any()):
            break  # converged: the weights each last solve used are those of its solution
        i = active.nonzero().squeeze(1)
        previous, sqrt_w = weights, weights[i].sqrt()[..., None]
        weighted = _solve_pose(_LandmarkTerms(P[i], b[i], m[i], K[i], sqrt_w), x[i], max_iterations, IRLS_FTOL)
        x, status = x.index_copy(0, i, weighted.x), status.index_copy(0, i, weighted.status)
        if bool((sqrt_w > 0).all()):  # the plain errors from the solve's weighted residuals at its x
            plain = weighted.residuals.view(i.shape[0], -1, 2) / sqrt_w
            error = error.index_copy(0, i, plain.norm(dim=-1))
        else:  # a weight underflowed to 0 (an error beyond ~1e154 robust scales): evaluate them
            error = None
    if error is None:
        error = _pose_residuals(x, P, b, m, K).norm(dim=-1)
    cost = torch.where(m, torch.log1p((error / scale).square()), torch.zeros_like(error)).sum(-1)
    cost = torch.where(torch.isfinite(cost) & (status != LMStatus.FAILED), cost, torch.finfo(cost.dtype).max)
    pick = _best_candidates(batch, owner, cost, _facing_camera(x, P, None if normals is None else normals[owner], m))
    return x[pick], status[pick], error[pick]  # ties: the plain solution (listed first)


def _per_view(points: Tensor, name: str, dims: dict[str, int]) -> Tensor:
    """``points`` of shape ``(L, 3)`` (shared by the views) or ``(B, L, 3)`` as ``(B, L, 3)``."""
    check_tensor(points, name)
    if points.dim() == 2:
        check_shape(points, [dims["L"], 3], name)
        points = points.expand(dims["B"], -1, -1)
    check_shape(points, ["B", "L", 3], name, dims)
    return points


def prealign_pose(
    landmarks: Tensor,
    model_points: Tensor,
    intrinsics: Tensor,
    mask: Tensor | None = None,
    init: str = "pnp",
    yaw_starts_deg: Sequence[float] = DEFAULT_YAW_STARTS,
    max_iterations: int = 40,
    robust_scale: float | None = None,
    robust_rounds: int = 2,
    model_normals: Tensor | None = None,
) -> PoseEstimate:
    r"""Head pose of a fixed shape from 2D landmarks, robust to any yaw in ±90°.

    The start is OpenCV's SQPnP solution (a globally optimal PnP, ``init="pnp"``; a view where
    OpenCV fails gets the yaw starts) or several yaw starts solved as one batch (``init="multistart"``,
    the best start wins). LM with an analytic Jacobian then minimises the reprojection error. Each
    view's result is what it would get alone, whatever else is in the batch.

    Args:
        landmarks: detected 2D landmarks ``b_j`` in pixels (NaN allowed where ``mask`` is False).
        model_points: the corresponding 3D model points (e.g. the mean head's landmark vertices), mm.
        intrinsics: ``(f, u0, v0)`` per view, e.g. a prior.
        mask: which landmarks are present; default: the finite ones.
        init: ``"pnp"`` or ``"multistart"``.
        yaw_starts_deg: initial yaw angles in degrees for ``"multistart"``.
        max_iterations: LM iterations per start (most views converge in 2-5, near-orthographic
            cameras too: the LM moves the camera-frame translation ``R t``, see ``_LandmarkTerms``).
        robust_scale: if given, up to ``robust_rounds`` more solves, each with Cauchy weights
            :math:`1 / (1 + (e_j / \delta)^2)` of the landmark errors :math:`e_j` (pixels) at its
            start (IRLS), so that a few spurious landmarks do not tilt the pose. They run from two
            starts per view, the plain solution and OpenCV's RANSAC pose (SQPnP on the inliers
            within :math:`2\delta`; from 6 landmarks up), and the one of lower Cauchy cost :math:`\sum_j \log(1 + (e_j/\delta)^2)`
            wins: grossly wrong landmarks (a network's eye corner placed on the other eye) can pull
            the plain solve into a wrong basin that reweighting alone does not leave. ``cost`` and
            ``rms_px`` stay those of the plain errors. (Reweighting the SQPnP start directly,
            without the plain solve, saves a solve but gave 3 % worse fits to the network's
            landmarks, whose outliers bias SQPnP.) With reweighting, every solve, the plain one
            included, stops at a relative cost reduction of ``IRLS_FTOL`` (1e-4) instead of 1e-7:
            the weights are settled only to ``IRLS_WEIGHT_TOLERANCE``, and the poses move by less
            than 0.05° and 0.5 mm.
        robust_rounds: the most reweighted solves; they stop once no weight changes by more than
            ``IRLS_WEIGHT_TOLERANCE`` (0.02), e.g. after one solve for clean landmarks.
        model_normals: optional outward unit normals of ``model_points`` (model frame, e.g. the mean
            head's vertex normals at its landmarks). A pose that turns a view's landmarks away from
            the camera (mean cosine of normals and rays above ``FACING_AWAY_COSINE``, 0.3) is then kept
            only when no start gives another (with
            ``init="pnp"`` such a view is solved again from the yaw starts): 4 or 5 nearly coplanar
            landmarks (the eye corners alone) fit a pose mirrored through their plane, facing away
            from the camera, as well as the true one.

    Returns:
        A :class:`PoseEstimate`.

    Raises:
        ValueError: on bad shapes, or when a view has fewer than 4 usable landmarks (the message names
            the view).

    Shape:
        - landmarks: :math:`(B, L, 2)`; model_points: :math:`(L, 3)` or :math:`(B, L, 3)`
        - intrinsics: :math:`(B, 3)`; mask: :math:`(B, L)`; model_normals: as ``model_points``

    Example:
        >>> from facenormals.geometry import project_points
        >>> pts = torch.randn(1, 10, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64) * 50
        >>> R = euler_to_rotation_matrix(torch.tensor([[0.1, -0.2, 1.2]], dtype=torch.float64))
        >>> K = torch.tensor([[500.0, 64, 64]], dtype=torch.float64)
        >>> uv, _ = project_points(pts, R, torch.tensor([[0.0, 0, 600]], dtype=torch.float64) @ R[0], K)
        >>> est = prealign_pose(uv, pts[0], K)
        >>> print(*(round(v, 3) for v in est.angles[0].tolist()))
        0.1 -0.2 1.2
    """
    dims = check_shape(landmarks, ["B", "L", 2], "landmarks")
    check_floating(landmarks, "landmarks")
    if dims["B"] < 1:
        raise ValueError(f"landmarks: expected at least one view, got shape {tuple(landmarks.shape)}")
    model_points = _per_view(model_points, "model_points", dims)
    check_floating(model_points, "model_points")  # bool or integer points fitted a wrong pose, "converged"
    check_shape(intrinsics, ["B", 3], "intrinsics", dims)
    check_floating(intrinsics, "intrinsics")
    check_finite(intrinsics, "intrinsics")
    if not bool((intrinsics[:, 0] > 0).all()):
        raise ValueError(f"intrinsics: expected focal lengths f > 0, got {intrinsics[:, 0].min().item():g}")
    check_finite(model_points, "model_points")
    if model_normals is not None:
        model_normals = _per_view(model_normals, "model_normals", dims)
        check_floating(model_normals, "model_normals")
        check_finite(model_normals, "model_normals")
    if mask is None:
        mask = torch.isfinite(landmarks).all(-1)
    check_shape(mask, ["B", "L"], "mask", dims)
    if mask.dtype != torch.bool:
        raise ValueError(f"mask: expected a bool tensor, got dtype {mask.dtype}")
    mask = mask & torch.isfinite(landmarks).all(-1)
    counts = mask.sum(1).tolist()
    for view, count in enumerate(counts):
        if count < 4:
            raise ValueError(
                f"landmarks: view {view} has {count} visible landmarks; the pose needs at least 4 "
                "(is there a face in this view?)"
            )
    check_scale("robust_scale", robust_scale)
    if init not in ("pnp", "multistart"):
        raise ValueError(f"init: expected 'pnp' or 'multistart', got {init!r}")
    if len(yaw_starts_deg) == 0:
        raise ValueError("yaw_starts_deg: expected at least one yaw start, got none")
    out_dtype = landmarks.dtype
    dtype = torch.float64  # a 6-parameter problem: float64 costs nothing and converges in fewer steps
    landmarks = landmarks.to(dtype)
    model_points = model_points.to(dtype)
    intrinsics = intrinsics.to(dtype)
    batch = dims["B"]
    # Starts: the SQPnP pose of each view where OpenCV gives one, the yaw starts elsewhere (per view,
    # so that a view's result never depends on the others in the batch).
    if init == "pnp":
        pnp, has_pnp = _pnp_starts(model_points, landmarks, mask, intrinsics)
    else:
        pnp = torch.zeros(batch, 6, dtype=dtype, device=landmarks.device)
        has_pnp = torch.zeros(batch, dtype=torch.bool, device=landmarks.device)
    normals = None if model_normals is None else model_normals.to(dtype)
    yaws = torch.tensor(yaw_starts_deg, dtype=dtype, device=landmarks.device).deg2rad()

    def yaw_starts(views: Tensor) -> tuple[Tensor, Tensor]:
        """Start-major: every view at the first yaw, then the next."""
        multi = views.repeat(len(yaws))
        angles0 = torch.zeros(len(yaws), views.shape[0], 3, dtype=dtype, device=landmarks.device)
        angles0[..., 2] = yaws[:, None]
        angles0 = angles0.reshape(-1, 3)
        t0 = _initial_translation(model_points[multi], landmarks[multi], mask[multi],
                                  euler_to_rotation_matrix(angles0), intrinsics[multi])
        return multi, torch.cat([angles0, t0], dim=-1)

    robust = robust_scale is not None and robust_rounds > 0
    ftol = IRLS_FTOL if robust else 1e-7  # robust: the plain solution is only the reweighting's start

    def solve(owner: Tensor, x0: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """Solutions, statuses, costs and ranking costs of the starts ``x0`` of the views ``owner``."""
        pts, targets, msk, K = model_points[owner], landmarks[owner], mask[owner], intrinsics[owner]
        result = _solve_pose(_LandmarkTerms(pts, targets, msk, K), x0, max_iterations, ftol)
        # a failed start ranks with the largest finite value (a view whose starts all failed keeps its first)
        rank = torch.where(result.status == LMStatus.FAILED, torch.finfo(dtype).max, result.cost)
        return result.x, result.status, result.cost, rank

    if bool(has_pnp.all()):
        owner, x0 = torch.arange(batch, device=landmarks.device), pnp
    else:
        multi, x_multi = yaw_starts((~has_pnp).nonzero().squeeze(1))
        owner, x0 = torch.cat([has_pnp.nonzero().squeeze(1), multi]), torch.cat([pnp[has_pnp], x_multi])
    x_all, status_all, cost_all, rank_all = solve(owner, x0)
    facing = _facing_camera(x_all, model_points[owner], None if normals is None else normals[owner], mask[owner])
    pick = _best_candidates(batch, owner, rank_all, facing)
    away = has_pnp & ~facing[pick]  # a PnP solution facing away: the yaw starts may find one facing the camera
    if bool(away.any()):
        again, x_again = yaw_starts(away.nonzero().squeeze(1))
        x_more, status_more, cost_more, rank_more = solve(again, x_again)
        owner = torch.cat([owner, again])
        x_all, status_all = torch.cat([x_all, x_more]), torch.cat([status_all, status_more])
        cost_all = torch.cat([cost_all, cost_more])
        facing = torch.cat([facing, _facing_camera(x_more, model_points[again], normals[again], mask[again])])
        pick = _best_candidates(batch, owner, torch.cat([rank_all, rank_more]), facing)
    x, status, final_cost = x_all[pick], status_all[pick], cost_all[pick]

    if robust:
        x, status, error = _robust_solve(x, status, model_points, landmarks, mask, intrinsics, robust_scale,
                                         robust_rounds, max_iterations, normals)
        final_cost = 0.5 * error.square().sum(1)  # the plain cost at the robust pose
    # Wrap the angles into (-pi, pi].
    angles = torch.atan2(torch.sin(x[:, :3]), torch.cos(x[:, :3]))
    R = _rotation(angles)
    count = mask.sum(1).to(dtype)
    return PoseEstimate(
        angles=angles.to(out_dtype),
        translation=_model_translation(R, x).to(out_dtype),
        rotation=R.to(out_dtype),
        cost=final_cost.to(out_dtype),
        rms_px=(2.0 * final_cost / count).sqrt().to(out_dtype),
        status=status,
    )
