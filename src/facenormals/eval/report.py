"""The evaluation protocol: rough alignment, ICP, errors, and their summary over a data set.

:func:`evaluate_reconstruction` scores a predicted mesh against a reference scan or mesh, twice:
after a **rigid** and after a **similarity** alignment (the latter forgives a wrong overall size).
Each alignment is

1. a closed-form fit (:func:`~facenormals.eval.align.fit_similarity`) of corresponding points:
   the six landmarks :data:`~facenormals.eval.align.DEFAULT_ALIGNMENT_LANDMARKS`, caller-given
   index pairs, or, for meshes of the same topology given nothing else, all face-region
   vertices;
2. refined by point-to-plane ICP (:func:`~facenormals.eval.icp.icp_point_to_plane`) of the
   prediction's vertices onto the reference face region and its vertex normals, each reference
   vertex paired with the nearest prediction vertex (``direction="target_to_source"``, so the
   rest of the predicted head does not pull), pairs farther apart than ``icp_max_distance``
   (default 10 mm) left out of the fit (not out of the errors);
3. scored over the reference face region by the errors of :mod:`facenormals.eval.metrics`:
   point-to-plane RMSE against the prediction's surface, per-vertex correspondence RMSE when the
   topologies agree (ICP errors can flatter a reconstruction that slides along the surface), and
   absolute depth-error statistics along the frontal viewing direction over the face-region
   vertices whose surface faces the viewer (the reference normal and every reference triangle
   around the vertex · viewing direction < 0, as a depth map would see them; grazing and
   back-facing vertices make depth differences meaningless, and at a vertex on a silhouette, where
   some of its triangles turn away, a rounding-level shift moves the line onto another layer). The
   correspondence errors use the same (ICP-refined) transform as the other errors.

:func:`summarise` averages the reports of a data set and divides by a baseline (the paper's
tables compare against the mean head).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Mapping, Sequence

import numpy as np
import torch
from torch import Tensor

from facenormals.core.check import (INWARD_SHARE, MILLIMETRE_SPAN, check_finite, check_floating, check_integer,
                                    check_nonnegative, check_positive, check_real, check_shape,
                                    outside_millimetre_span, outward_share)
from facenormals.eval.align import (DEFAULT_ALIGNMENT_LANDMARKS, apply_similarity, fit_similarity,
                                    landmark_correspondences)
from facenormals.eval.icp import icp_point_to_plane
from facenormals.eval.metrics import (
    DepthStatistics,
    _check_faces,
    correspondence_errors,
    depth_errors,
    depth_statistics,
    point_to_plane_errors,
)
from facenormals.mesh.normals import vertex_normals

__all__ = ["AlignmentResult", "EvaluationReport", "evaluate_reconstruction", "shares_vertex_order", "summarise"]

#: Metrics of :meth:`AlignmentResult.as_dict` averaged by :func:`summarise`.
SUMMARY_METRICS = (
    "point_to_plane_rmse", "correspondence_rmse", "depth_mean", "depth_std", "depth_median",
    "depth_delta90", "depth_coverage", "scale", "icp_iterations",
)  # fmt: skip
#: The error metrics divided by the baseline in :func:`summarise`.
RATIO_METRICS = (
    "point_to_plane_rmse", "correspondence_rmse", "depth_mean", "depth_std", "depth_median", "depth_delta90",
)  # fmt: skip
ALIGNMENTS = ("rigid", "similarity")
#: RMS distance (mm) of the rough alignment's corresponding points above which a report warns: the
#: six default landmarks of random ICT identities (y ~ N(0, 1)) stay 2.5 mm apart (median, 7 at
#: most over 100), of y ~ 3·N(0, 1) 8 mm (21 at most); left and right eyes swapped leave 27 mm.
ALIGNMENT_RMS_WARNING = 20.0
#: Below this share of the reference's points finding the prediction's surface along the viewing
#: direction, the depth statistics describe a fraction of the face (holes, a cropped or degenerate mesh).
DEPTH_COVERAGE_WARNING = 0.5
#: Smallest bounding-box diagonal (mm) of the reference face region: a face region spans about
#: 150-250 mm in mm (the ICT region: 229 mm for the mean head, 149-362 for identities y ~ 3·N(0, 1))
#: but 15-36 units in centimetres, which the whole head's 50-unit floor can let through. 50 keeps
#: smaller regions in mm (a nose and cheeks) and stays above any face in cm.
FACE_REGION_MIN_SPAN = 50.0
#: Plausible range of the size ratio of the two meshes (reference / prediction) and of the
#: similarity alignment's scale: the six landmarks of ICT identities y ~ 3·N(0, 1) against the mean
#: head spread 0.64-1.62 times as wide; meshes in centimetres and millimetres give 10 or 0.1.
SCALE_RANGE = (0.5, 2.0)


@dataclass(frozen=True)
class AlignmentResult:
    """Errors (mm) of a prediction after one kind of alignment; the transform maps the prediction
    into the reference frame, ``aligned = scale · rotation · p + translation``."""

    point_to_plane_rmse: float
    correspondence_rmse: float | None
    depth: DepthStatistics
    scale: float
    rotation: Tensor
    translation: Tensor
    icp_iterations: int
    icp_converged: bool
    alignment_rms: float = math.nan  # the rough alignment's corresponding points: RMS distance after its fit, mm

    def as_dict(self) -> dict[str, object]:
        """Plain JSON-serialisable values; the depth statistics flattened as ``depth_*``."""
        out: dict[str, object] = {
            "point_to_plane_rmse": self.point_to_plane_rmse,
            "correspondence_rmse": self.correspondence_rmse,
        }
        out.update({f"depth_{k}": v for k, v in self.depth.as_dict().items()})
        out.update(
            scale=self.scale,
            alignment_rms=self.alignment_rms,
            icp_iterations=self.icp_iterations,
            icp_converged=self.icp_converged,
            rotation=self.rotation.tolist(),
            translation=self.translation.tolist(),
        )
        return out


@dataclass(frozen=True)
class EvaluationReport:
    """The result of :func:`evaluate_reconstruction`.

    Attributes:
        rigid: errors after rigid alignment.
        similarity: errors after similarity alignment.
        same_topology: whether correspondence errors were computed.
        num_points: reference face-region vertices scored.
        num_alignment_points: corresponding points of the rough alignment.
        num_depth_points: reference points of the depth statistics (the front-facing ones of the
            face region by default: vertex normal and triangles around it); ``None``: ``num_points``.
    """

    rigid: AlignmentResult
    similarity: AlignmentResult
    same_topology: bool
    num_points: int
    num_alignment_points: int
    num_depth_points: int | None = None

    def as_dict(self) -> dict[str, object]:
        """Plain JSON-serialisable values, :attr:`warnings` (a list of strings) included."""
        return {
            "same_topology": self.same_topology,
            "num_points": self.num_points,
            "num_depth_points": self._depth_total,
            "num_alignment_points": self.num_alignment_points,
            "rigid": self.rigid.as_dict(),
            "similarity": self.similarity.as_dict(),
            "warnings": self.warnings,
        }

    @property
    def _depth_total(self) -> int:
        return self.num_points if self.num_depth_points is None else self.num_depth_points

    def __str__(self) -> str:
        rows = [
            ("point-to-plane RMSE", "point_to_plane_rmse", "mm"),
            ("correspondence RMSE", "correspondence_rmse", "mm"),
            ("depth |dz| mean", "depth_mean", "mm"),
            ("depth |dz| std", "depth_std", "mm"),
            ("depth |dz| median", "depth_median", "mm"),
            ("depth |dz| delta90", "depth_delta90", "mm"),
            ("depth points", "depth_count", ""),
            ("depth coverage", "depth_coverage", ""),
            ("scale", "scale", ""),
            ("alignment RMS", "alignment_rms", "mm"),
            ("ICP iterations", "icp_iterations", ""),
            ("ICP converged", "icp_converged", ""),
        ]
        data = {a: getattr(self, a).as_dict() for a in ALIGNMENTS}
        lines = [f"{'':<22}{'rigid':>12}{'similarity':>12}", "-" * 50]
        for label, key, unit in rows:
            cells = [_format(data[a][key]) for a in ALIGNMENTS]
            lines.append(f"{label:<22}{cells[0]:>12}{cells[1]:>12}  {unit}".rstrip())
        lines.append(f"({self.num_points} reference points, {self.num_alignment_points} alignment points)")
        lines.extend(f"warning: {w}" for w in self.warnings)
        return "\n".join(lines)

    @property
    def warnings(self) -> list[str]:
        """Signs that the numbers may be those of a wrong alignment rather than of the shape: the
        rough alignment's points left more than :data:`ALIGNMENT_RMS_WARNING` mm apart (wrong
        correspondences: left and right swapped, another vertex order), depth statistics over
        less than :data:`DEPTH_COVERAGE_WARNING` of the reference points they consider, or a
        similarity scale outside :data:`SCALE_RANGE` (meshes of such different sizes are no
        reconstruction of one another, or not in one unit). (ICP's own convergence is
        in the table but no warning: between two different heads its closest pairs often end in a
        2-cycle, which :func:`icp_point_to_plane` detects and counts as converged.)"""
        out = []
        for name in ALIGNMENTS:
            result = getattr(self, name)
            if result.alignment_rms > ALIGNMENT_RMS_WARNING:
                if self.similarity.alignment_rms <= ALIGNMENT_RMS_WARNING:  # only the rigid fit: a size difference
                    cause = (f", but {self.similarity.alignment_rms:.1f} mm with a scale ({self.similarity.scale:.3g}): "
                             "the meshes differ in size, which one photo cannot fix; the similarity column scores the "
                             "shape")
                else:
                    cause = (f"; above {ALIGNMENT_RMS_WARNING:g} mm the correspondences are likely wrong (left and "
                             "right swapped, another vertex order): check them")
                out.append(f"{name} alignment: its {self.num_alignment_points} corresponding points stay "
                           f"{result.alignment_rms:.1f} mm apart (RMS) after the rough fit{cause}")
            if not result.depth.coverage >= DEPTH_COVERAGE_WARNING:  # NaN too
                total = self._depth_total
                which = "front-facing reference points" if total < self.num_points else "reference points"
                out.append(f"{name} alignment: only {result.depth.count} of the {total} {which} "
                           f"({100 * result.depth.coverage:.0f} %) meet the prediction's surface along the viewing "
                           "direction, so the depth statistics describe little of the face (holes, a cropped "
                           "prediction, or triangles without area)")
        low, high = SCALE_RANGE
        if not low <= self.similarity.scale <= high:
            out.append(f"similarity alignment: it scales the prediction by {self.similarity.scale:.3g}, outside "
                       f"{low:g}-{high:g}; the prediction is then no reconstruction of the reference's size (wrong "
                       "correspondences, or meshes in different units: both must be in millimetres)")
        return out


def _format(value: object) -> str:
    if value is None:
        return "-"
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, int):
        return str(value)
    return f"{float(value):.4f}" if abs(float(value)) < 10 else f"{float(value):.2f}"


def _landmarks_of(x: object) -> Mapping[str, int] | None:
    if isinstance(x, Mapping):
        return x
    landmarks = getattr(x, "landmarks", None)
    return landmarks if isinstance(landmarks, Mapping) else None


def _named_pairs(prediction: Mapping[str, int], reference: Mapping[str, int], names: Sequence[str]) -> Tensor:
    return landmark_correspondences(prediction, reference, names, source_name="correspondences: prediction landmarks",
                                    target_name="correspondences: reference landmarks")


def _describe(x: object) -> str:
    if isinstance(x, (Tensor, np.ndarray)):
        return f"{type(x).__name__} of shape {tuple(x.shape)} and dtype {x.dtype}"
    if isinstance(x, (tuple, list)):
        kinds = sorted({type(c).__name__ for c in x})
        return f"{type(x).__name__} of {len(x)} {'/'.join(kinds) or 'items'}"
    return type(x).__name__


def _index_pairs(correspondences: object) -> Tensor:
    """A ``(K, 2)`` integer tensor (CPU) from a tensor, an array or a sequence of index pairs (tensors too)."""
    expected = "correspondences: expected (K, 2) integer pairs (prediction index, reference index)"
    if isinstance(correspondences, Tensor):
        pairs = correspondences.detach().cpu()
    else:
        try:
            if (isinstance(correspondences, (tuple, list)) and correspondences
                    and all(isinstance(c, Tensor) for c in correspondences)):
                pairs = torch.stack([c.detach().cpu() for c in correspondences])
            else:
                pairs = torch.as_tensor(np.asarray(correspondences))
        except (TypeError, ValueError, RuntimeError):  # ragged, strings, objects
            raise ValueError(f"{expected}, got {_describe(correspondences)}") from None
    if pairs.dim() != 2 or pairs.shape[1] != 2:
        hint = (" (for index lists (prediction_indices, reference_indices) pass torch.stack(them, dim=1))"
                if pairs.dim() == 2 and pairs.shape[0] == 2 else "")
        raise ValueError(f"{expected}, got shape {tuple(pairs.shape)}{hint}")
    if pairs.dtype.is_floating_point or pairs.dtype.is_complex or pairs.dtype == torch.bool:
        raise ValueError(f"correspondences: expected integer index pairs, got dtype {pairs.dtype}")
    return pairs.long()


def _resolve_pairs(
    correspondences: object,
    same_topology: bool,
    region: Tensor,
    num_prediction: int,
    num_reference: int,
    landmark_names: Sequence[str],
) -> Tensor:
    """Index pairs ``(K, 2)`` = ``(prediction vertex, reference vertex)`` of the rough alignment."""
    if correspondences is None:
        if not same_topology:
            raise ValueError(
                "correspondences: required when the meshes do not share a topology "
                "(index pairs (K, 2), or landmark mappings / models for both meshes)"
            )
        index = torch.nonzero(region).reshape(-1)
        return torch.stack([index, index], dim=1)
    single = _landmarks_of(correspondences)
    if single is not None:
        if not same_topology:
            raise ValueError(
                "correspondences: one landmark mapping needs meshes of the same topology; "
                "pass (prediction_landmarks, reference_landmarks)"
            )
        pairs, what = _named_pairs(single, single, landmark_names), "landmark vertex indices"
    elif (isinstance(correspondences, (tuple, list)) and len(correspondences) == 2
          and all(_landmarks_of(c) is not None for c in correspondences)):
        pairs = _named_pairs(_landmarks_of(correspondences[0]), _landmarks_of(correspondences[1]), landmark_names)
        what = "landmark vertex indices"
    else:
        pairs, what = _index_pairs(correspondences), "indices"
    for column, size, mesh in ((0, num_prediction, "prediction"), (1, num_reference, "reference")):
        col = pairs[:, column]
        if col.numel() and (int(col.min()) < 0 or int(col.max()) >= size):
            raise ValueError(
                f"correspondences: expected {mesh} {what} (column {column}) in [0, {size}), "
                f"got values in [{int(col.min())}, {int(col.max())}]"
            )
    return pairs


def _check_mesh(vertices: object, faces: object, prefix: str) -> tuple[Tensor, np.ndarray]:
    """Shapes, finite values, millimetres and outward-facing triangles of one mesh."""
    check_shape(vertices, ["N", 3], f"{prefix}_vertices")
    check_floating(vertices, f"{prefix}_vertices")
    check_finite(vertices, f"{prefix}_vertices")
    vertices = vertices.detach().cpu().double()
    triangles = _check_faces(faces, vertices.shape[0], f"{prefix}_faces")
    corners = vertices[torch.from_numpy(triangles)]  # (F, 3, 3): the vertices in use
    span = outside_millimetre_span(corners)
    if span is not None:
        low, high = MILLIMETRE_SPAN
        raise ValueError(
            f"{prefix}_vertices: the mesh spans {span:.3g} units across, not the {low:g}-{high:g} of a face or head "
            "in millimetres; every error is reported in mm (a mesh in metres needs its vertices times 1000, "
            "in centimetres times 10)"
        )
    # Outward normals point away from the surface's centre over most of a head's or a face's area;
    # triangles wound the other way would make the depth test hit the back of the head.
    outward = outward_share(vertices, torch.from_numpy(triangles))
    if outward < INWARD_SHARE:
        raise ValueError(
            f"{prefix}_faces: the triangles face inward (their normals point towards the mesh's centre over "
            f"{50 * (1 - outward):.0f} % of its area): they are wound clockwise seen from outside; "
            "reverse them (faces[:, [0, 2, 1]])"
        )
    return vertices, triangles


def shares_vertex_order(faces: Tensor, reference_faces: Tensor, min_shared: float = 0.9) -> bool:
    """Whether two triangle lists index one vertex order: at least ``min_shared`` of the reference's
    edges are edges of ``faces``. Triangles may be listed in another order, start at another corner,
    be wound the other way or split a quad along the other diagonal; a mesh whose vertices were
    reordered shares almost no edge.

    Raises:
        ValueError: naming ``faces`` or ``reference_faces`` unless it is ``(F, 3)`` integer vertex indices
            in ``[0, 2**31)``, or ``min_shared`` unless it is a share in ``[0, 1]``.

    Example:
        >>> quad = torch.tensor([[0, 1, 2], [0, 2, 3]])
        >>> shares_vertex_order(torch.tensor([[1, 2, 0], [2, 3, 0]]), quad), shares_vertex_order(quad[:, [0, 2, 1]], quad)
        (True, True)
        >>> shares_vertex_order(torch.tensor([[3, 2, 1], [3, 1, 0]]), quad, min_shared=1.0)
        False
    """
    for name, f in (("faces", faces), ("reference_faces", reference_faces)):
        f = torch.as_tensor(f)
        if f.dim() != 2 or f.shape[1] != 3:
            raise ValueError(f"{name}: expected shape (F, 3), got {tuple(f.shape)}")
        if f.dtype.is_floating_point or f.dtype.is_complex or f.dtype == torch.bool:
            raise ValueError(f"{name}: expected integer vertex indices, got dtype {f.dtype}")
    if not 0.0 <= check_real(min_shared, "min_shared") <= 1.0:
        raise ValueError(f"min_shared: expected a share in [0, 1], got {min_shared!r}")
    faces, reference_faces = (torch.as_tensor(f).detach().cpu().long() for f in (faces, reference_faces))
    for name, f in (("faces", faces), ("reference_faces", reference_faces)):
        # a negative index would make an edge key of another edge (-1 * size - 2 ...) and match wrongly;
        # beyond 2**31 the keys low * size + high overflow
        if f.numel() and (int(f.min()) < 0 or int(f.max()) >= 2**31):
            raise ValueError(f"{name}: expected vertex indices in [0, 2**31), got values in [{int(f.min())}, "
                             f"{int(f.max())}]")
    if faces.numel() == 0 or reference_faces.numel() == 0:
        return False
    size = int(max(faces.max(), reference_faces.max())) + 1

    def keys(f: Tensor) -> Tensor:  # each undirected edge once, as low * size + high
        pairs = torch.cat([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
        return torch.unique(pairs.min(1).values * size + pairs.max(1).values)

    mine, theirs = keys(faces), keys(reference_faces)
    return float(torch.isin(theirs, mine).float().mean()) >= min_shared


def _front_facing_surface(vertices: Tensor, faces: Tensor, direction: Tensor) -> Tensor:
    """``(N,)``: no triangle around the vertex turns away from a viewer looking along ``direction``
    (outward normal, counter-clockwise winding, · direction ≥ 0; degenerate triangles ignored)."""
    faces = faces.detach().cpu().long()
    corners = vertices[faces]  # (F, 3, 3)
    facing = torch.linalg.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]) @ direction.to(vertices)
    away = torch.zeros(vertices.shape[0], dtype=torch.bool)
    away[faces[facing > 0].flatten()] = True
    return ~away


def _check_facing(normals: Tensor, direction: Tensor) -> None:
    """The reference face region must face the viewer (against ``direction``) for depth errors."""
    mean = normals.mean(0)
    if float(mean.norm()) < 0.3:  # a closed surface (a sphere, a whole head): no one facing direction
        return
    cosine = float(-(mean @ direction) / (mean.norm() * direction.norm()))
    if cosine < math.cos(math.radians(45.0)):
        raise ValueError(
            f"reference_vertices: the face region faces {math.degrees(math.acos(max(-1.0, min(1.0, cosine)))):.0f}° "
            "away from the viewer, who looks along view_direction (default +z: the model frame, face along -z, "
            "docs/conventions.md); depth errors would be measured across the face. Rotate the reference into the "
            "model frame (a mesh in an OpenGL-style frame, face along +z, needs y and z negated) or pass "
            "view_direction"
        )


def _check_region_size(points: Tensor) -> None:
    """The face region must be a face's size in millimetres (a reference in cm passes the whole-mesh check)."""
    span = float((points.amax(0) - points.amin(0)).norm())
    if span < FACE_REGION_MIN_SPAN:
        raise ValueError(
            f"reference_vertices: its face region (reference_face_region) spans {span:.3g} units across, not the "
            f"150-250 of a face in millimetres (at least {FACE_REGION_MIN_SPAN:g}); the reference looks like it is in "
            "centimetres (vertices times 10) or metres (times 1000), and every error is reported in mm"
        )


def _rms_radius(points: Tensor) -> float:
    return float((points - points.mean(0)).square().sum(1).mean().sqrt())


def _check_relative_size(pred_points: Tensor, ref_points: Tensor) -> None:
    """The rough alignment's corresponding points must spread about as wide in both meshes: a
    similarity alignment would otherwise hide a unit mix-up (its errors look plausible)."""
    ratio = _rms_radius(ref_points) / _rms_radius(pred_points)
    low, high = SCALE_RANGE
    if not low <= ratio <= high:
        unit = ("is the prediction in centimetres (vertices times 10)?" if ratio > high else
                "is the prediction in another unit, or the reference in centimetres (times 10)?")
        raise ValueError(
            f"prediction_vertices: its {pred_points.shape[0]} corresponding points spread {1 / ratio:.3g} times as wide "
            f"as the reference's: {unit} Both meshes must be in millimetres; a similarity alignment would scale by "
            f"{ratio:.3g}, outside {low:g}-{high:g}, and hide the mix-up (or the correspondences pick points of "
            "different extent)"
        )


def _rough_alignment(pred_points: Tensor, ref_points: Tensor, scale: bool) -> tuple[tuple[Tensor, ...], float]:
    """Closed-form fit ``(s, R, t)`` of corresponding points ``(K, 3)`` and its RMS distance (mm)."""
    try:
        init = fit_similarity(pred_points[None], ref_points[None], scale=scale)
    except ValueError as error:
        raise ValueError(f"correspondences: the rough alignment's {pred_points.shape[0]} point pairs cannot fix a "
                         f"transform ({error})") from None
    moved = apply_similarity(pred_points[None], *init)[0]
    return init, float((moved - ref_points).square().sum(1).mean().sqrt())


def evaluate_reconstruction(
    prediction_vertices: Tensor,
    prediction_faces: Tensor,
    reference_vertices: Tensor,
    reference_faces: Tensor,
    reference_face_region: Tensor,
    correspondences: object = None,
    same_topology: bool | None = None,
    *,
    landmark_names: Sequence[str] = DEFAULT_ALIGNMENT_LANDMARKS,
    icp_max_iterations: int = 50,
    icp_tolerance: float = 1e-6,
    icp_max_distance: float | None = 10.0,
    view_direction: Tensor | None = None,
    depth_front_facing: bool = True,
) -> EvaluationReport:
    """Score a predicted head mesh against a reference after rigid and after similarity alignment.

    Args:
        prediction_vertices: ``(M, 3)`` predicted vertices (mm, any pose).
        prediction_faces: ``(G, 3)`` predicted triangles.
        reference_vertices: ``(N, 3)`` reference vertices (mm, model frame: face along −z).
        reference_faces: ``(F, 3)`` reference triangles (for the reference normals).
        reference_face_region: ``(N,)`` bool mask of the scored reference vertices (at least 7,
            spanning at least :data:`FACE_REGION_MIN_SPAN` = 50 mm, above any face in cm).
        correspondences: the rough alignment's corresponding points: a ``(K, 2)`` integer tensor
            or array, or a sequence of ``(prediction index, reference index)`` pairs (lists or
            2-element tensors; K ≥ 3); a pair
            ``(prediction_landmarks, reference_landmarks)`` of name → vertex mappings or
            :class:`~facenormals.models.MorphableModel`-like objects with ``.landmarks`` (the
            ``landmark_names`` are used; iBUG-68 names are understood); one mapping/model when the
            topology is shared; or ``None``: all face-region vertices when the topology is shared.
        same_topology: ``True`` or ``False``, whether vertex ``i`` of both meshes is the same
            point; default ``None``: true when the vertex counts agree and
            :func:`shares_vertex_order` says so.
        landmark_names: landmarks used from landmark mappings (default: eye corners ×4, nose tip,
            chin).
        icp_max_iterations: ICP iterations (see :func:`icp_point_to_plane`).
        icp_tolerance: ICP convergence tolerance.
        icp_max_distance: ICP pairs farther apart than this (mm) are left out of the fit; ``None``
            keeps all.
        view_direction: ``(3,)`` viewing direction of the depth errors, default ``(0, 0, 1)``.
        depth_front_facing: take the depth statistics over the face-region vertices whose
            reference normal and reference triangles (all those around the vertex) face the viewer
            (``n · view_direction < 0``) only; ``False``: over the whole face region. At a vertex on
            a silhouette (its normal faces the viewer, some of its triangles do not) the line along
            the view misses the front-facing surface under a rounding-level shift and scores
            another layer: a copy of the reference rounded to float32 scored up to 28 mm there.

    Returns:
        :class:`EvaluationReport`; the transforms' ``rotation`` and ``translation`` have the dtype
        and device of ``prediction_vertices`` (computed in float64 on the CPU).

    Raises:
        ValueError: on bad shapes, dtypes, NaN vertices, out-of-range indices, missing landmarks,
            ``same_topology`` not ``None``/``True``/``False`` or ``True`` with different vertex
            counts, a mesh not in millimetres (its bounding box spans less than 50 or more than
            5,000 units; the reference face region less than 50; the rough alignment's points
            spread more than twice as wide in one mesh as in the other), triangles wound inward,
            or a reference face region of fewer than 7 vertices or facing more than 45° away from
            the viewer (not in the model frame). A sign of a wrong alignment, the rough alignment's
            points more than 20 mm apart or a similarity scale outside 0.5-2, does not raise: it is
            in :attr:`EvaluationReport.warnings`; ICP's convergence is in
            :attr:`AlignmentResult.icp_converged`.

    Example:
        >>> from facenormals.models import builtin_head_model
        >>> model = builtin_head_model()
        >>> prediction = model.mean * 1.02 + torch.tensor([1.0, 2.0, 3.0])
        >>> report = evaluate_reconstruction(prediction, model.faces, model.mean, model.faces,
        ...                                  model.face_region, correspondences=model)
        >>> round(report.similarity.scale, 3), report.similarity.point_to_plane_rmse < 1e-3
        (0.98, True)
        >>> report.rigid.point_to_plane_rmse > 0.1
        True
    """
    pred, pred_faces = _check_mesh(prediction_vertices, prediction_faces, "prediction")
    ref, _ = _check_mesh(reference_vertices, reference_faces, "reference")
    check_shape(reference_face_region, [ref.shape[0]], "reference_face_region")
    if reference_face_region.dtype != torch.bool:
        raise ValueError(f"reference_face_region: expected a bool tensor, got dtype {reference_face_region.dtype}")
    region = reference_face_region.detach().cpu()
    if int(region.sum()) < 7:  # ICP's unknowns with scale
        raise ValueError(f"reference_face_region: expected at least 7 selected vertices (the unknowns of a similarity "
                         f"alignment), got {int(region.sum())}")
    if same_topology is not None and not isinstance(same_topology, (bool, np.bool_)):
        raise ValueError(f"same_topology: expected None, True or False, got {type(same_topology).__name__} "
                         f"{same_topology!r}")
    same_shape = pred.shape[0] == ref.shape[0]
    if same_topology is None:
        same_topology = same_shape and shares_vertex_order(prediction_faces, reference_faces)
    elif same_topology and not same_shape:
        raise ValueError(
            f"same_topology: True needs equal vertex counts, got prediction_vertices {tuple(pred.shape)} "
            f"and reference_vertices {tuple(ref.shape)}"
        )
    icp_max_iterations = check_integer(icp_max_iterations, "icp_max_iterations", minimum=0)
    icp_tolerance = check_nonnegative(icp_tolerance, "icp_tolerance")
    if icp_max_distance is not None:
        icp_max_distance = check_positive(icp_max_distance, "icp_max_distance")
    pairs = _resolve_pairs(correspondences, same_topology, region, pred.shape[0], ref.shape[0], landmark_names)
    if pairs.shape[0] < 3:
        raise ValueError(f"correspondences: expected at least 3 pairs, got {pairs.shape[0]}")
    normals = vertex_normals(ref[None], reference_faces.detach().cpu().long())[0]
    stray = region & ~(normals.norm(dim=1) > 0)
    if bool(stray.any()):
        raise ValueError(
            f"reference_face_region: {int(stray.sum())} of its vertices (first: vertex {int(stray.nonzero()[0])}) lie "
            "on no (non-degenerate) reference triangle, so they have no normal to measure along; a cropped reference "
            "keeps vertices its triangles no longer use: leave them out of the region"
        )
    points, point_normals = ref[region], normals[region]
    _check_region_size(points)
    if view_direction is not None:
        check_shape(view_direction, [3], "view_direction")
        check_floating(view_direction, "view_direction")
        check_finite(view_direction, "view_direction")
        direction = view_direction.detach().cpu().double()
        if not float(direction.norm()) > 0:
            raise ValueError("view_direction: expected a non-zero vector")
    else:
        direction = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    _check_facing(point_normals, direction)
    depth_points = points[_front_facing_surface(ref, reference_faces, direction)[region]
                          & (point_normals @ direction < 0)] if depth_front_facing else points
    pred_faces_t = torch.from_numpy(pred_faces)
    surface = pred[torch.from_numpy(np.unique(pred_faces))]  # ICP pairs with the surface, not stray vertices
    pred_pairs, ref_pairs = pred[pairs[:, 0]], ref[pairs[:, 1]]
    rough = {name: _rough_alignment(pred_pairs, ref_pairs, name == "similarity") for name in ALIGNMENTS}
    _check_relative_size(pred_pairs, ref_pairs)
    like = {"dtype": prediction_vertices.dtype, "device": prediction_vertices.device}  # the outputs follow the input
    results = {}
    for name in ALIGNMENTS:
        (init, alignment_rms), scale = rough[name], name == "similarity"
        icp = icp_point_to_plane(
            surface,
            points,
            point_normals,
            init=init,
            scale=scale,
            max_iterations=icp_max_iterations,
            tolerance=icp_tolerance,
            max_distance=icp_max_distance,
            direction="target_to_source",
        )
        aligned = icp.s * pred @ icp.R.T + icp.t
        p2p = point_to_plane_errors(points, point_normals, aligned, pred_faces_t)
        corr = correspondence_errors(points, aligned[region]) if same_topology else None
        depth = depth_statistics(depth_errors(depth_points, aligned, pred_faces_t, direction))
        results[name] = AlignmentResult(
            point_to_plane_rmse=float(p2p.square().mean().sqrt()),
            correspondence_rmse=None if corr is None else float(corr.square().mean().sqrt()),
            depth=depth,
            scale=icp.s,
            rotation=icp.R.to(**like),
            translation=icp.t.to(**like),
            icp_iterations=icp.iterations,
            icp_converged=icp.converged,
            alignment_rms=alignment_rms,
        )
    return EvaluationReport(
        rigid=results["rigid"],
        similarity=results["similarity"],
        same_topology=bool(same_topology),
        num_points=int(points.shape[0]),
        num_alignment_points=int(pairs.shape[0]),
        num_depth_points=int(depth_points.shape[0]),
    )


def _mean_metrics(reports: Sequence[EvaluationReport]) -> dict[str, dict[str, float | None]]:
    out: dict[str, dict[str, float | None]] = {}
    for alignment in ALIGNMENTS:
        rows = [getattr(r, alignment).as_dict() for r in reports]
        out[alignment] = {}
        for key in SUMMARY_METRICS:
            values = [row[key] for row in rows]
            out[alignment][key] = None if any(v is None for v in values) else float(np.mean(values))
    return out


def _check_reports(reports: object, name: str, count: int | None = None) -> list[EvaluationReport]:
    if not isinstance(reports, Sequence) or not all(isinstance(r, EvaluationReport) for r in reports):
        raise ValueError(f"{name}: expected a sequence of EvaluationReport")
    if len(reports) == 0:
        raise ValueError(f"{name}: expected at least one report, got 0")
    if count is not None and len(reports) != count:
        raise ValueError(f"{name}: expected {count} reports (one per report of reports), got {len(reports)}")
    return list(reports)


def summarise(
    reports: Sequence[EvaluationReport], baseline_reports: Sequence[EvaluationReport] | None = None
) -> dict[str, object]:
    """Average a data set's reports, and compare with a baseline (e.g. the mean head) of the same subjects.

    Every metric is the arithmetic mean over the reports of the per-subject value (so an RMSE row
    is the mean of per-subject RMSEs). A metric that is ``None`` in any report (correspondence
    RMSE without a shared topology) averages to ``None``. Depth statistics that are NaN (no hit)
    propagate. The ratio is ``mean / baseline mean`` (ratio of means; below 1 beats the baseline),
    for the error metrics only.

    Returns:
        ``{"count": n, "mean": {"rigid": {...}, "similarity": {...}}}`` plus, with a baseline,
        ``"baseline_mean"`` (same layout) and ``"ratio"`` (``{alignment: {error metric: ratio}}``).

    Raises:
        ValueError: on an empty list, non-report entries, or a baseline of a different length.

    Example:
        >>> from facenormals.models import builtin_head_model
        >>> m = builtin_head_model()
        >>> run = lambda v: evaluate_reconstruction(v, m.faces, m.mean, m.faces, m.face_region, m)
        >>> ours = [run(m.mean + 0.5 * m.shape_basis[0])]; mean_head = [run(m.mean + 2.0 * m.shape_basis[0])]
        >>> summary = summarise(ours, mean_head)
        >>> print(summary["count"], *sorted(summary))
        1 baseline_mean count mean ratio
        >>> ratio = summary["ratio"]
        >>> 0 < ratio.get("rigid").get("correspondence_rmse") < 1
        True
    """
    reports = _check_reports(reports, "reports")
    out: dict[str, object] = {"count": len(reports), "mean": _mean_metrics(reports)}
    if baseline_reports is not None:
        baseline = _mean_metrics(_check_reports(baseline_reports, "baseline_reports", len(reports)))
        mean = out["mean"]
        ratio: dict[str, dict[str, float | None]] = {}
        for alignment in ALIGNMENTS:
            ratio[alignment] = {}
            for key in RATIO_METRICS:
                a, b = mean[alignment][key], baseline[alignment][key]
                if a is None or b is None:
                    ratio[alignment][key] = None
                else:
                    ratio[alignment][key] = a / b if b != 0 else (math.nan if a == 0 else math.inf)
        out["baseline_mean"] = baseline
        out["ratio"] = ratio
    return out
