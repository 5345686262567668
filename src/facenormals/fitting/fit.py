r"""The recipe: pre-align on landmarks, then fit shape, pose and intrinsics to normals + landmarks.

:func:`fit_head` composes public ops only: :func:`prealign_pose` (mean shape, per view), then
rounds of [visibility by z-buffer → :func:`~facenormals.optim.levenberg_marquardt` on
:class:`HeadFitProblem`'s residuals with its analytic Jacobian]. Any number of views share one
shape; each view has its own pose and intrinsics.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field
from numbers import Real
from pathlib import Path
from typing import Callable, Sequence

import numpy as np
import torch
from torch import Tensor

from facenormals.core.check import (check_finite, check_flag, check_floating, check_integer, check_real, check_shape,
                                    check_tensor)
from facenormals.fitting.pose import FACING_AWAY_COSINE, facing_cosine, prealign_pose, require_pose_landmarks
from facenormals.fitting.problem import FitWeights, HeadFitProblem
from facenormals.fitting.robust import check_scale
from facenormals.fitting.subsample import grid_subset
from facenormals.geometry import euler_to_rotation_matrix, transform_points
from facenormals.mesh import vertex_normals
from facenormals.models import MorphableModel
from facenormals.optim import LMStatus, levenberg_marquardt

__all__ = ["FitResult", "fit_head"]


@dataclass
class FitResult:
    """Result of :func:`fit_head` for ``B`` subjects and ``V`` views.

    Attributes:
        vertices: ``(B, N, 3)`` fitted heads in the model frame, mm.
        faces: ``(F, 3)`` triangles.
        shape_coeffs: ``(B, K)``; expression_coeffs: ``(B, E)`` or ``None``.
        angles, rotation, translation, intrinsics: per view, ``(B, V, 3)``, ``(B, V, 3, 3)``,
            ``(B, V, 3)`` and ``(B, V, 3)`` (``X_c = R (p + t)``, intrinsics ``(f, u0, v0)``); the
            angles ``(roll, pitch, yaw)`` in radians, each wrapped to (−π, π].
        energies: term name → ``(B,)`` weighted energy (``normals``, ``landmarks``, ``prior``, ...).
        iterations: ``(B,)`` LM iterations over all rounds.
        status: ``(B,)`` :class:`~facenormals.optim.LMStatus` of the last round; reasons: its reasons.
        visible: ``(B, V, N)`` visibility at the last round.
        landmark_rms_px: ``(B, V)`` landmark reprojection RMS over every given landmark, outliers
            included (NaN for a view without landmarks).
        landmark_median_px: ``(B, V)`` median reprojection error: not moved by the few spurious
            landmarks that the Cauchy weights ignore.
        prealignment_rms_px: ``(B, V)`` landmark RMS of the pre-alignment (NaN when ``initial_pose``
            was given).
        landmark_facing: ``(B, V)`` :func:`~facenormals.fitting.facing_cosine` of the fitted head's
            given landmarks in each view: negative where they face the camera, as seen landmarks do;
            above :data:`~facenormals.fitting.FACING_AWAY_COSINE` the head faces away and
            :func:`fit_head` warns (:class:`FacingAwayWarning`); NaN for a view without landmarks.
        timings: seconds of the pre-alignment (``prealign_s``) and of the whole fit (``total_s``).

    ``energies`` are the terms as minimised in the last round: ``energies["normals"]`` is λN·EN
    over that round's vertices (its grid subset, visible and facing the camera by ``min_facing``)
    with its Huber weights, ``energies["landmarks"]`` is λZ·EZ with its Cauchy weights, and
    ``energies["prior"]`` is λP·EP. With ``robust_scale=None``, ``landmark_robust_scale=None`` and
    ``vertex_spacing=None`` they are the paper's weighted terms over the visible vertices.
    """

    vertices: Tensor
    faces: Tensor
    shape_coeffs: Tensor
    expression_coeffs: Tensor | None
    angles: Tensor
    rotation: Tensor
    translation: Tensor
    intrinsics: Tensor
    energies: dict[str, Tensor]
    iterations: Tensor
    status: Tensor
    reasons: list[str]
    visible: Tensor
    landmark_rms_px: Tensor
    landmark_median_px: Tensor
    prealignment_rms_px: Tensor
    landmark_facing: Tensor
    timings: dict[str, float] = field(default_factory=dict)

    def _index(self, value: object, name: str, count: int) -> int:
        index = check_integer(value, name, minimum=0)  # -1 would pick the last one silently
        if index >= count:
            raise ValueError(f"{name}: expected an index in [0, {count}), got {index}")
        return index

    def camera_vertices(self, view: int = 0) -> Tensor:
        """Vertices in the camera frame of ``view``: ``(B, N, 3)``."""
        view = self._index(view, "view", self.rotation.shape[1])
        return transform_points(self.vertices, self.rotation[:, view], self.translation[:, view])

    def export(self, path: str | Path, subject: int = 0) -> Path:
        """Write subject ``subject``'s mesh (model frame, mm) as ``.ply``/``.obj``."""
        from facenormals.mesh import save_mesh

        return save_mesh(path, self.vertices[self._index(subject, "subject", self.vertices.shape[0])], self.faces)

    def summary(self, subject: int = 0) -> str:
        """One line: status, iterations, energies and each view's yaw, focal length and landmark RMS."""
        subject = self._index(subject, "subject", self.vertices.shape[0])
        e = {k: float(v[subject]) for k, v in self.energies.items()}
        terms = ", ".join(f"{k} {v:.4g}" for k, v in e.items())
        views = ", ".join(
            f"view {v}: yaw {math.degrees(float(self.angles[subject, v, 2])):+.1f} deg, "
            f"f {float(self.intrinsics[subject, v, 0]):.1f} px, landmarks {float(self.landmark_rms_px[subject, v]):.2f} px"
            for v in range(self.angles.shape[1])
        )
        return (f"{LMStatus(int(self.status[subject])).name} after {int(self.iterations[subject])} iterations "
                f"({self.reasons[subject]}); energies: {terms}; {views}")


def _check_finite_views(x: Tensor, name: str) -> None:
    """:func:`check_finite` of ``(B, V, ...)`` whose error names the views holding NaN or inf."""
    try:
        check_finite(x, name)
    except ValueError as error:
        bad = (~torch.isfinite(x)).flatten(2).any(-1).nonzero().tolist()
        where = ", ".join(f"view {v}{f' of subject {b}' if x.shape[0] > 1 else ''}" for b, v in bad[:5])
        more = f" and {len(bad) - 5} more" if len(bad) > 5 else ""
        raise ValueError(f"{error}, in {where}{more}") from None


def _as_views(x: Tensor, name: str, tail: list, views: dict[str, int] | None = None) -> Tensor:
    """Accept ``(V, ...)`` for one subject or ``(B, V, ...)``; return ``(B, V, ...)``. ``views``
    (``{"B": B, "V": V}``) binds the leading sizes to those of the normal maps."""
    check_tensor(x, name)
    got = tuple(x.shape)
    if x.dim() == len(tail) + 1:
        x = x[None]
    try:
        check_shape(x, ["B", "V", *tail], name, dict(views) if views else None)
    except ValueError:
        rest = ", ".join(str(t) for t in tail)
        if views and views["B"] > 1:  # (V, ...) is one subject's: here each subject needs its own rows
            raise ValueError(f"{name}: expected shape (B, V, {rest}) with B={views['B']}, V={views['V']} (one entry "
                             f"per subject of normal_maps), got {got}") from None
        sizes = f" with B={views['B']}, V={views['V']}" if views else ""
        raise ValueError(f"{name}: expected shape (V, {rest}) or (B, V, {rest}){sizes}, got {got}") from None
    return x


def _pixel_sizes(model: MorphableModel, angles: Tensor, translation: Tensor, intrinsics: Tensor) -> list[float]:
    """Per subject, the median size of a pixel in mm at the depth of the mean head's landmarks over its views."""
    B, V = angles.shape[:2]
    points = model.mean[model.landmark_indices] if model.landmark_indices.numel() else model.mean
    centre = points.mean(0)
    R = euler_to_rotation_matrix(angles.reshape(-1, 3))
    depth = (R @ (centre + translation.reshape(-1, 3))[..., None])[:, 2, 0]
    return (depth / intrinsics.reshape(-1, 3)[:, 0]).reshape(B, V).median(dim=1).values.tolist()


def _check_spacings(vertex_spacing: object) -> list[float | None]:
    """``vertex_spacing`` as a list of finite spacings > 0 or ``None`` (a NaN spacing kept one vertex)."""
    spacings = list(vertex_spacing) if isinstance(vertex_spacing, Sequence) and not isinstance(vertex_spacing, str) \
        else [vertex_spacing]
    if not spacings:
        raise ValueError("vertex_spacing: expected a spacing, a non-empty sequence of spacings or None, got []")
    for spacing in spacings:
        if spacing is not None and not (isinstance(spacing, Real) and not isinstance(spacing, (bool, np.bool_))
                                         and math.isfinite(spacing) and spacing > 0):
            raise ValueError(f"vertex_spacing: expected finite spacings > 0 in pixels or None, got {vertex_spacing!r}")
    return spacings


def _check_normal_maps_encoding(normal_maps: Tensor, foreground: Tensor) -> None:
    """Refuse maps that are not unit camera-frame normals: scaled (0-255), encoded as colours
    ((n + 1) / 2) or in an OpenGL frame (z towards the viewer). Such maps fit without error to a
    head near the mean; the message names the view."""
    B, V = normal_maps.shape[:2]
    for b in range(B):
        for v in range(V):
            mask = foreground[b, v]
            if not bool(mask.any()):
                continue
            n = normal_maps[b, v][:, mask]  # (3, pixels)
            where = f"view {v}{f' of subject {b}' if B > 1 else ''}"
            length = float(n.norm(dim=0).median())
            if abs(length - 1.0) > 0.1:
                raise ValueError(
                    f"normal_maps: {where} holds normals of median length {length:.3g} where unit normals are "
                    "expected (a map scaled to 0-255 or encoded as colours (n + 1) / 2? decode it to unit "
                    "vectors, zero on background; docs/conventions.md)")
            facing = float((n[2] < 0).to(n.dtype).mean())
            if facing < 0.5:
                raise ValueError(
                    f"normal_maps: {where} has only {100 * facing:.0f} % of its normals facing the camera "
                    "(z < 0 in OpenCV's frame: x right, y down, z forward); a map in an OpenGL frame "
                    "(y up, z towards the viewer) needs its y and z negated (docs/conventions.md)")


#: A view whose map's x or y normal components make a cosine below this with those of the mean head
#: at its pre-aligned pose has that axis flipped; correct maps (exact or the network's) score 0.5-0.9
#: (x) and 0.5-0.6 (y), maps with the axis flipped -0.5 to -0.9.
FLIPPED_AXIS_COSINE = -0.3


def _normal_axis_cosines(normal_maps: Tensor, foreground: Tensor, model: MorphableModel, R: Tensor,
                         translation: Tensor, intrinsics: Tensor) -> tuple[Tensor, Tensor]:
    """Per view ``(B V, 2)``: the cosine of the map's x (and y) normal components with the mean head's,
    posed by the rotations ``R`` ``(B V, 3, 3)`` and ``translation``, at the nearest pixels of its
    front-facing vertices inside the map's foreground; and ``(B V,)`` how many such pixels there were."""
    B, V, _, H, W = normal_maps.shape
    dtype = normal_maps.dtype
    normals = model.mean_normals().to(dtype)
    camera = (model.mean.to(dtype)[None] + translation.reshape(-1, 1, 3).to(dtype)) @ R.transpose(1, 2)
    n_camera = normals[None] @ R.transpose(1, 2)
    K = intrinsics.reshape(-1, 3).to(dtype)
    z = camera[..., 2].clamp_min(1e-6)
    u = torch.round(K[:, None, 0] * camera[..., 0] / z + K[:, None, 1])
    v = torch.round(K[:, None, 0] * camera[..., 1] / z + K[:, None, 2])
    seen = (camera[..., 2] > 0) & ((n_camera * camera).sum(-1) < 0) & (u >= 0) & (u <= W - 1) & (v >= 0) & (v <= H - 1)
    index = v.clamp(0, H - 1).long() * W + u.clamp(0, W - 1).long()
    sampled = torch.gather(normal_maps.reshape(B * V, 3, H * W), 2, index[:, None].expand(-1, 3, -1)).transpose(1, 2)
    seen &= torch.gather(foreground.reshape(B * V, H * W), 1, index)
    weight = seen[..., None].to(dtype)
    a, c = sampled[..., :2] * weight, n_camera[..., :2] * weight
    cosine = (a * c).sum(1) / (a.norm(dim=1) * c.norm(dim=1)).clamp_min(1e-12)
    return cosine, seen.sum(1)


def _check_normal_axes(normal_maps: Tensor, foreground: Tensor, model: MorphableModel, angles: Tensor,
                       translation: Tensor, intrinsics: Tensor, landmark_mask: Tensor) -> None:
    """Refuse a view whose map has its x or y axis flipped (a mirrored map, y up): such maps pass
    :func:`_check_normal_maps_encoding` and fit without error to a head near the mean. Views whose
    pre-aligned head faces away from the camera are left alone: their landmarks, not their map, are
    wrong (spurious detections in a photo without a face), which callers such as
    :func:`~facenormals.reconstruct.reconstruct_views` report."""
    dtype = normal_maps.dtype
    R = euler_to_rotation_matrix(angles.reshape(-1, 3).to(dtype))  # (B V, 3, 3)
    cosine, count = _normal_axis_cosines(normal_maps, foreground, model, R, translation, intrinsics)
    views, L = cosine.shape[0], model.landmark_indices.shape[0]
    facing = torch.ones(views, dtype=torch.bool, device=cosine.device)  # a model without landmarks: a given pose
    if L:
        facing = facing_cosine(model.mean[model.landmark_indices].to(dtype).expand(views, L, 3),
                               model.landmark_normals().to(dtype).expand(views, L, 3), R,
                               translation.reshape(-1, 3).to(dtype), landmark_mask.reshape(views, L)) <= FACING_AWAY_COSINE
    flipped = (cosine < FLIPPED_AXIS_COSINE) & (count[:, None] >= 50) & facing[:, None]  # 50: enough face to tell
    if not bool(flipped.any()):
        return
    view, axis = (int(i) for i in flipped.nonzero()[0])
    V = normal_maps.shape[1]
    b, v = divmod(view, V)
    where = f"view {v}{f' of subject {b}' if normal_maps.shape[0] > 1 else ''}"
    name = "xy"[axis]
    raise NormalAxisError(
        f"normal_maps: {where}'s {name} components point against those of the head pre-aligned to its landmarks "
        f"(cosine {float(cosine[view, axis]):.2f} over {int(count[view])} pixels): is the map's {name} axis flipped "
        f"({'a mirrored map' if name == 'x' else 'y up'}; facenormals expects OpenCV's camera frame, x right and y "
        "down, docs/conventions.md), or do the landmarks not belong to this map?",
        subject=b, view=v, axis=name, cosine=float(cosine[view, axis]), pixels=int(count[view]))


class NormalAxisError(ValueError):
    """:func:`fit_head`'s refusal of a view whose normal map's ``axis`` (``"x"`` or ``"y"``) components
    point against those of the head pre-aligned to the view's landmarks (``cosine`` over ``pixels``):
    a mirrored or y-up map, or a map and landmarks that disagree (e.g. a network's, under-trained)."""

    def __init__(self, message: str, *, subject: int, view: int, axis: str, cosine: float, pixels: int) -> None:
        super().__init__(message)
        self.subject, self.view, self.axis, self.cosine, self.pixels = subject, view, axis, cosine, pixels


class FacingAwayWarning(RuntimeWarning):
    """:func:`fit_head` ended on a head turned away from the camera in some view
    (:attr:`FitResult.landmark_facing` above :data:`~facenormals.fitting.FACING_AWAY_COSINE`)."""


def _landmark_facing(vertices: Tensor, model: MorphableModel, rotation: Tensor, translation: Tensor,
                     landmark_mask: Tensor) -> Tensor:
    """``(B, V)`` :func:`facing_cosine` of the fitted heads' given landmarks per view, NaN without any."""
    B, V = rotation.shape[:2]
    index = model.landmark_indices
    mask = landmark_mask.reshape(B * V, -1)
    if not index.numel():
        return rotation.new_full((B, V), float("nan"))
    points = vertices[:, index]  # (B, L, 3)
    normals = vertex_normals(vertices, model.landmark_faces())[:, index]  # exact there, ~1/100 of the mesh
    cosine = facing_cosine(points[:, None].expand(B, V, -1, 3).reshape(B * V, -1, 3),
                           normals[:, None].expand(B, V, -1, 3).reshape(B * V, -1, 3),
                           rotation.reshape(B * V, 3, 3), translation.reshape(B * V, 3), mask)
    return cosine.masked_fill(~mask.any(-1), float("nan")).reshape(B, V)


def _name_views(pairs: list[list[int]], B: int, detail: Callable[[int, int], str]) -> str:
    """``view v (detail)`` for each ``(b, v)`` of ``pairs``, ``view v of subject b`` in a batch of ``B > 1``."""
    return ", ".join(f"view {v}{f' of subject {b}' if B > 1 else ''} ({detail(b, v)})" for b, v in pairs)


def _warn_facing_away(facing: Tensor, angles: Tensor) -> None:
    """Warn, naming the views, where the fitted head faces away from the camera: landmarks given as
    seen cannot sit on its far side, so they are most likely in another convention (left and right
    swapped, or (row, column)), and the fit, reported converged, is not a face seen from the front."""
    away = (facing > FACING_AWAY_COSINE).nonzero().tolist()
    if away:
        views = _name_views(away, facing.shape[0], lambda b, v: f"yaw {math.degrees(float(angles[b, v, 2])):+.0f} "
                                                                f"deg, cosine {float(facing[b, v]):.2f}")
        warnings.warn(f"fit_head: the fitted head faces away from the camera in {views}, with the landmarks said "
                      "to be seen on its far side: are they in model.landmark_names order with the subject's left "
                      "and right (not the image's), and in (x, y) = (column, row) pixels? See "
                      "FitResult.landmark_facing", FacingAwayWarning, stacklevel=3)


def _wrap_angles(angles: Tensor) -> Tensor:
    """Angles wrapped to (−π, π] (the same rotations)."""
    return math.pi - torch.remainder(math.pi - angles, 2 * math.pi)


def _warn_unconverged_prealignment(status: Tensor, rms_px: Tensor) -> None:
    """Warn, naming the views, where the landmark pre-alignment stopped without converging: the fit
    starts from that pose and may end in a wrong minimum while its own status says converged."""
    stuck = (status != LMStatus.CONVERGED).nonzero().tolist()
    if stuck:
        views = _name_views(stuck, status.shape[0],
                            lambda b, v: f"{float(rms_px[b, v]):.2g} px, {LMStatus(int(status[b, v])).name}")
        warnings.warn(f"fit_head: the landmark pre-alignment did not converge for {views}; the fit starts from "
                      "that pose and may end in a wrong one (a near-orthographic camera, f above ~10^4 px, or "
                      "inconsistent landmarks): check FitResult.prealignment_rms_px and landmark_rms_px, or pass "
                      "initial_pose", RuntimeWarning, stacklevel=3)


def fit_head(
    normal_maps: Tensor,
    landmarks: Tensor,
    model: MorphableModel,
    intrinsics: Tensor | None = None,
    landmark_mask: Tensor | None = None,
    weights: FitWeights = FitWeights(),
    fit_intrinsics: bool = True,
    fit_expression: bool = False,
    rounds: int = 3,
    iterations_per_round: int = 10,
    ftol: float = 3e-2,
    jacobian_dtype: torch.dtype | None = torch.float32,
    initial_pose: tuple[Tensor, Tensor] | None = None,
    min_facing: float = 0.2,
    robust_scale: float | None = 0.1,
    landmark_robust_scale: float | None = 3.0,
    vertex_spacing: float | Sequence[float] | None = (3.0, 0.75),
    visibility_rounds: int = 2,
) -> FitResult:
    r"""Fit a morphable model to normal maps and landmarks of one or more views.

    Minimises :math:`E = \lambda_N E_N + \lambda_Z E_Z + \lambda_P E_P` (plus weak priors on the
    intrinsics and, if fitted, the expression) over the shared shape ``y`` and each view's pose and
    intrinsics. A view whose normal map has no foreground contributes only its landmarks.

    Args:
        normal_maps: camera-frame normal maps, zero on background: ``(V, 3, H, W)`` for one subject or
            ``(B, V, 3, H, W)`` for ``B`` subjects fitted as one batch.
        landmarks: the model's landmarks in pixels ``(V, L, 2)`` / ``(B, V, L, 2)``; NaN where missing.
        model: the morphable model (float32 or float64; the fit runs in its dtype).
        intrinsics: ``(f, u0, v0)`` prior per view ``(V, 3)`` / ``(B, V, 3)``; default: focal length =
            image width, principal point at the image centre.
        landmark_mask: which landmarks are present; default: the finite ones.
        weights: the energy weights (paper defaults λN = 1, λZ = 0.8, λP = 0.4).
        fit_intrinsics: fit ``(f, u0, v0)`` per view (else they stay at the prior).
        fit_expression: also fit the model's expression coefficients.
        rounds: LM rounds; the robust weights are refreshed before each, visibility before the
            first ``visibility_rounds``.
        iterations_per_round: the most LM iterations per round; a round stops earlier once an
            accepted step lowers the energy by less than ``ftol`` (relative).
        ftol: relative energy decrease that ends a round (visibility and robust weights are then
            refreshed, so rounds need not converge tightly: 3e-2 and 1e-2 give the same accuracy).
        jacobian_dtype: dtype of the normal equations (float32 is ~3× faster on CPU, see
            :func:`~facenormals.optim.levenberg_marquardt`).
        initial_pose: optional ``(angles, translation)`` per view to skip the landmark pre-alignment.
        min_facing: vertices count only when :math:`-n \cdot \hat{X}_c` exceeds this: grazing vertices
            near the silhouette sample the map poorly (see :func:`~facenormals.render.visible_vertices`).
        robust_scale: Huber scale δ of the normal residuals' norms, applied by reweighting at the
            start of each round (IRLS); ``None`` gives the paper's plain least squares. Vertices whose
            map sample is unreliable (holes, sub-pixel detail) otherwise bias the shape: on oracle
            ICT maps at 128² it halves the error left when starting from the truth.
        landmark_robust_scale: Cauchy scale of the landmark residuals in pixels, reweighted like
            ``robust_scale`` (see :meth:`HeadFitProblem.update_robust_weights`); ``None`` gives
            plain least squares. A detector's (or the network's) spurious landmark tens of pixels off
            otherwise drags the shape (docs/model_card.md); exact landmarks stay well inside
            it, so fits to exact landmarks do not change. The pre-alignment reweights the same way.
        vertex_spacing: the normal term uses about one model vertex per cube of this many pixels
            (:func:`~facenormals.fitting.subsample.grid_subset` of the mean head, with the pixel size
            at the pre-aligned head's depth); vertices denser than the pixels add cost but little
            information. A sequence gives one spacing per round (the last one repeats); the default
            fits the first round, which mostly moves the pose and the coarse shape away from the mean
            head, to a 3-pixel subset (~1/10 of the rows) and the rest to a 0.75-pixel one: at the same
            accuracy, 6.5 instead of 8 LM iterations on exact maps and 6.6 instead of 11.8 on a
            network's (docs/accuracy.md). ``None`` uses every vertex.
        visibility_rounds: the rounds that start by recomputing visibility (z-buffer, ring and
            sparse layout: ~1/5 of a round's cost); later rounds keep the last visibility, unless
            their vertex subset differs, and refresh only the robust weights. By the third round the
            head moves by about a pixel: re-rasterising it changes the result by ~1 % (docs/accuracy.md).

    Returns:
        A :class:`FitResult`. The fit is not differentiable: inputs that require gradients are
        fitted as data (detached), and the result holds no graph.

    Raises:
        ValueError: on bad shapes or types, inputs on another device than the model, NaN normal maps
            or initial pose, normal maps that are not unit camera-frame normals (scaled,
            colour-encoded or in an OpenGL frame), ``fit_expression`` with a model without expressions,
            a view with fewer than 4 visible landmarks (with ``initial_pose``: a view with neither a
            face in its map nor a landmark); the message names the view.
    """
    import time

    start = time.perf_counter()
    fit_intrinsics = check_flag(fit_intrinsics, "fit_intrinsics")
    fit_expression = check_flag(fit_expression, "fit_expression")
    rounds = check_integer(rounds, "rounds", minimum=1)
    iterations_per_round = check_integer(iterations_per_round, "iterations_per_round", minimum=1)
    visibility_rounds = check_integer(visibility_rounds, "visibility_rounds", minimum=1)
    check_scale("robust_scale", robust_scale)
    check_scale("landmark_robust_scale", landmark_robust_scale)
    spacings = _check_spacings(vertex_spacing)
    min_facing = check_real(min_facing, "min_facing")
    if not -1.0 <= min_facing < 1.0:  # 1 or more leaves no vertex for the normal term
        raise ValueError(f"min_facing: expected a value in [-1, 1), got {min_facing!r}")
    if not isinstance(model, MorphableModel):
        raise ValueError(f"model: expected a MorphableModel (e.g. facenormals.load_model({model!r}) for a name or "
                         f"path), got {type(model).__name__}")
    if not isinstance(weights, FitWeights):
        raise ValueError(f"weights: expected a FitWeights, got {type(weights).__name__}")
    if jacobian_dtype not in (None, torch.float32, torch.float64):
        raise ValueError(f"jacobian_dtype: expected None, torch.float32 or torch.float64, got {jacobian_dtype!r}")
    if initial_pose is not None and not (isinstance(initial_pose, (tuple, list)) and len(initial_pose) == 2):
        raise ValueError("initial_pose: expected a pair (angles, translation) of (V, 3) or (B, V, 3) tensors, "
                         f"got {type(initial_pose).__name__}")
    if fit_expression and model.num_expressions == 0:
        raise ValueError(f"fit_expression: model {model.name!r} has no expression basis to fit")
    model.check_millimetres()
    if initial_pose is None:
        require_pose_landmarks(model)  # before the landmarks' shape, which names the model's count
    normal_maps = _as_views(normal_maps, "normal_maps", [3, "H", "W"])
    B, V, _, H, W = normal_maps.shape
    if B < 1 or V < 1 or H < 1 or W < 1:
        raise ValueError(f"normal_maps: expected at least one subject, one view and one pixel, got shape "
                         f"{tuple(normal_maps.shape)}")
    views = {"B": B, "V": V}
    try:
        landmarks = _as_views(landmarks, "landmarks", [model.landmark_indices.shape[0], 2], views)
    except ValueError as error:
        raise ValueError(f"{error}; landmarks follow model.landmark_names (model {model.name!r} names "
                         f"{model.landmark_indices.shape[0]}); the network's channels map onto them with "
                         "facenormals.reconstruct.landmark_channels(model)") from None
    dtype, device = model.mean.dtype, model.mean.device
    for name, x in (("normal_maps", normal_maps), ("landmarks", landmarks), ("intrinsics", intrinsics),
                    ("landmark_mask", landmark_mask)):
        if isinstance(x, Tensor) and x.device != device:  # the fit runs where the model is
            raise ValueError(f"{name}: expected device {device} (the model's: move one to the other), got {x.device}")
    check_floating(normal_maps, "normal_maps")  # an integer map would truncate the unit normals to 0
    check_floating(landmarks, "landmarks")
    _check_finite_views(normal_maps, "normal_maps")
    # the LM solve is not differentiable: a network's output is fitted as data, without its graph
    normal_maps, landmarks = normal_maps.detach().to(dtype), landmarks.detach().to(dtype)
    if intrinsics is None:
        intrinsics = torch.tensor([float(W), (W - 1) / 2, (H - 1) / 2], dtype=dtype, device=device).expand(B, V, 3)
    intrinsics = _as_views(intrinsics, "intrinsics", [3], views)
    check_floating(intrinsics, "intrinsics")  # a bool prior read as f = 1 px and fitted a garbage head
    intrinsics = intrinsics.detach().to(dtype)
    check_finite(intrinsics, "intrinsics")
    if not bool((intrinsics[..., 0] > 0).all()):
        raise ValueError(f"intrinsics: expected focal lengths f > 0, got {intrinsics[..., 0].min().item():g}")
    if landmark_mask is None:
        landmark_mask = torch.isfinite(landmarks).all(-1)
    landmark_mask = _as_views(landmark_mask, "landmark_mask", [landmarks.shape[2]], views)
    if landmark_mask.dtype != torch.bool:
        raise ValueError(f"landmark_mask: expected a bool tensor, got dtype {landmark_mask.dtype}")
    landmark_mask = landmark_mask & torch.isfinite(landmarks).all(-1)
    foreground = normal_maps.norm(dim=2) > 0.5
    _check_normal_maps_encoding(normal_maps, foreground)
    view_weights = (foreground.flatten(2).sum(-1) > 0).to(dtype)  # no face in the map: landmarks only

    # 1. Pre-alignment: the mean head's landmarks, per view.
    if initial_pose is None:
        flat_mask = landmark_mask.reshape(B * V, -1)
        for index, count in enumerate(flat_mask.sum(1).tolist()):
            if count < 4:
                b, v = divmod(index, V)
                raise ValueError(
                    f"landmarks: view {v}{f' of subject {b}' if B > 1 else ''} has {count} visible landmarks; "
                    "at least 4 are needed to pre-align it"
                )
        pose = prealign_pose(landmarks.reshape(B * V, -1, 2), model.mean[model.landmark_indices],
                             intrinsics.reshape(B * V, 3), flat_mask, robust_scale=landmark_robust_scale,
                             model_normals=model.landmark_normals())
        angles, translation = pose.angles.reshape(B, V, 3), pose.translation.reshape(B, V, 3)
        pre_rms = pose.rms_px.reshape(B, V)
        _warn_unconverged_prealignment(pose.status.reshape(B, V), pre_rms)
    else:
        angles, translation = (_as_views(p, f"initial_pose {n}", [3], views)
                               for p, n in zip(initial_pose, ("angles", "translation")))
        check_floating(angles, "initial_pose angles")  # integer angles truncate, a bool translation is 1 mm
        check_floating(translation, "initial_pose translation")
        angles, translation = angles.detach().to(dtype), translation.detach().to(dtype)
        check_finite(angles, "initial_pose angles")
        check_finite(translation, "initial_pose translation")
        pre_rms = torch.full((B, V), float("nan"), dtype=dtype, device=device)
        empty = (view_weights == 0) & ~landmark_mask.any(-1)
        if bool(empty.any()):
            b, v = (int(i) for i in empty.nonzero()[0])
            raise ValueError(f"normal_maps, landmarks: view {v}{f' of subject {b}' if B > 1 else ''} has neither a "
                             "face in its normal map nor a landmark; nothing in it constrains the fit")
    t_pre = time.perf_counter()
    _check_normal_axes(normal_maps, foreground, model, angles, translation, intrinsics, landmark_mask)

    # 2. Rounds of visibility + LM.
    # Per subject, so that a batch fits each subject exactly as alone.
    pixels = _pixel_sizes(model, angles, translation, intrinsics)
    subsets = {s: None if s is None else torch.stack([grid_subset(model.mean, s * p) for p in pixels]) for s in spacings}
    problem = HeadFitProblem(model, normal_maps, landmarks, landmark_mask, intrinsics, weights,
                             fit_intrinsics=fit_intrinsics, fit_expression=fit_expression, view_weights=view_weights)
    x = problem.pack(torch.zeros(B, model.num_shape, dtype=dtype, device=device), angles, translation, intrinsics)
    iterations = torch.zeros(B, dtype=torch.long, device=device)
    for round_ in range(rounds):
        subset = subsets[spacings[min(round_, len(spacings) - 1)]]
        if round_ < visibility_rounds or subset is not problem.vertex_subset:
            problem.vertex_subset = subset
            visible = problem.update_visibility(x, min_facing=min_facing)
        problem.update_robust_weights(x, robust_scale, landmark_robust_scale)
        result = levenberg_marquardt(
            problem.residuals, x,
            normal_equations_fn=lambda z, r, index: problem.normal_equations(z, r, index, dtype=jacobian_dtype),
            max_iterations=iterations_per_round, damping=1e-4, ftol=ftol, xtol=1e-7,
            jacobian_dtype=jacobian_dtype, active_subset=True,
        )
        x = result.x
        iterations += result.iterations
    p = problem.unpack(x)

    # 3. Report.
    terms = problem.residual_terms(x)
    energies = {
        "normals": 0.5 * terms[0].square().flatten(1).sum(1),
        "landmarks": 0.5 * terms[1].square().flatten(1).sum(1),
        "prior": 0.5 * terms[2].square().sum(1),
    }
    extra = terms[3:]
    if fit_expression:
        energies["expression_prior"] = 0.5 * extra.pop(0).square().sum(1)
    if fit_intrinsics:
        energies["intrinsics_prior"] = 0.5 * extra.pop(0).square().sum(1)
    lm_errors = problem.landmark_errors(x)
    if lm_errors.shape[-1] == 0:  # a model without landmarks (fitted from a given pose)
        lm_errors = lm_errors.new_full((*lm_errors.shape[:-1], 1), float("nan"))
    lm_rms = lm_errors.square().nanmean(-1).sqrt()
    vertices, angles = problem.vertices(x), _wrap_angles(p["angles"])
    rotation = euler_to_rotation_matrix(angles.reshape(-1, 3)).reshape(B, V, 3, 3)
    facing = _landmark_facing(vertices, model, rotation, p["translation"], landmark_mask)
    _warn_facing_away(facing, angles)
    return FitResult(
        vertices=vertices,
        faces=model.faces,
        shape_coeffs=p["shape"],
        expression_coeffs=p["expression"],
        angles=angles,
        rotation=rotation,
        translation=p["translation"],
        intrinsics=p["intrinsics"].expand(B, V, 3).clone(),  # not fitted, it is the caller's tensor
        energies=energies,
        iterations=iterations,
        status=result.status,
        reasons=result.reasons,
        visible=visible,
        landmark_rms_px=lm_rms,
        landmark_median_px=lm_errors.nanmedian(-1).values,
        prealignment_rms_px=pre_rms,
        landmark_facing=facing,
        timings={"prealign_s": t_pre - start, "total_s": time.perf_counter() - start},
    )
