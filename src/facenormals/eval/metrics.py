r"""Per-vertex reconstruction errors (mm) of an aligned reconstruction against a reference.

All functions take the reference points already restricted to the region to score (e.g.
``vertices[model.face_region]``) and a reconstruction already aligned to the reference frame.

Definitions, for a reference vertex :math:`p_i` with unit normal :math:`n_i`:

* **point-to-plane error** (signed): :math:`e_i = (q_i - p_i) \cdot n_i`, with :math:`q_i` the
  closest point *on the reconstruction's triangles* (not its closest vertex). Positive when the
  reconstruction lies outside the reference. RMSE :math:`= \sqrt{\operatorname{mean}_i e_i^2}`.
* **correspondence error** (same topology): :math:`\lVert q_i - p_i \rVert` with :math:`q_i` the
  reconstruction vertex of the same index.
* **depth error** (signed): :math:`\Delta z_i = z(h_i) - z(p_i)`, where :math:`h_i` is the
  intersection of the line through :math:`p_i` along the viewing direction (default the model
  frame's z axis, the frontal camera's optical axis) with the reconstruction's triangles that face
  the viewer, the one nearest to :math:`p_i`; NaN where the line misses them. Statistics are taken over
  :math:`|\Delta z_i|` of the hits: mean, standard deviation (population, ``ddof=0``), median and
  :math:`\delta_{90}` = the 90th percentile of :math:`|\Delta z_i|` (linear interpolation between
  order statistics, :func:`numpy.percentile`'s default): about 90 % of the hit vertices have an
  absolute depth error of at most :math:`\delta_{90}`, exactly 90 % only when it falls on an order
  statistic (e.g. 89.99 % of ICT's 4,556 depth points).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
import torch
from torch import Tensor

from facenormals.core.check import check_finite, check_floating, check_shape
from facenormals.eval.surface import closest_points_on_mesh, intersect_lines_along_z

__all__ = [
    "DepthStatistics",
    "correspondence_errors",
    "depth_errors",
    "depth_statistics",
    "point_to_plane_errors",
]


def _check_points(x: object, name: str, shape, dims=None) -> dict[str, int]:
    dims = check_shape(x, shape, name, dims)
    check_floating(x, name)
    check_finite(x, name)
    return dims


def _check_faces(faces: object, num_vertices: int, name: str = "reconstruction_faces") -> np.ndarray:
    dims = check_shape(faces, ["F", 3], name)
    if faces.dtype.is_floating_point or faces.dtype.is_complex or faces.dtype == torch.bool:
        raise ValueError(f"{name}: expected an integer tensor, got dtype {faces.dtype}")
    if dims["F"] == 0:
        raise ValueError(f"{name}: expected at least one triangle, got shape {tuple(faces.shape)}")
    lo, hi = int(faces.min()), int(faces.max())
    if lo < 0 or hi >= num_vertices:
        raise ValueError(f"{name}: expected vertex indices in [0, {num_vertices}), got values in [{lo}, {hi}]")
    return faces.detach().cpu().numpy().astype(np.int64)


def _numpy(x: Tensor) -> np.ndarray:
    return x.detach().cpu().double().numpy()


def point_to_plane_errors(
    reference_vertices: Tensor,
    reference_normals: Tensor,
    reconstruction_vertices: Tensor,
    reconstruction_faces: Tensor,
) -> Tensor:
    r"""Signed point-to-plane errors :math:`e_i = (q_i - p_i) \cdot n_i` against the reconstruction surface.

    :math:`q_i` is the exact closest point on the reconstruction's triangles
    (:func:`facenormals.eval.surface.closest_points_on_mesh`, about 0.3 s for 11k points against
    22k triangles on one CPU core).

    Args:
        reference_vertices: reference points :math:`p_i` (mm), e.g. the face region.
        reference_normals: their unit normals :math:`n_i` (normalised here).
        reconstruction_vertices: the aligned reconstruction's vertices (mm).
        reconstruction_faces: its triangles.

    Returns:
        ``(N,)`` signed errors in mm, dtype and device of ``reference_vertices``.

    Raises:
        ValueError: on bad shapes or dtypes, NaN/inf values, zero normals, or out-of-range faces.

    Shape:
        - reference_vertices, reference_normals: :math:`(N, 3)`
        - reconstruction_vertices: :math:`(M, 3)`; reconstruction_faces: :math:`(F, 3)`

    Example:
        >>> v = torch.tensor([[0.0, 0, 0], [10, 0, 0], [0, 10, 0]]); f = torch.tensor([[0, 1, 2]])
        >>> p = torch.tensor([[1.0, 1, -2], [2, 2, 3]]); n = torch.tensor([[0.0, 0, 1], [0, 0, 1]])
        >>> point_to_plane_errors(p, n, v, f)
        tensor([ 2., -3.])
    """
    dims = _check_points(reference_vertices, "reference_vertices", ["N", 3])
    _check_points(reference_normals, "reference_normals", ["N", 3], dims)
    rdims = _check_points(reconstruction_vertices, "reconstruction_vertices", ["M", 3])
    faces = _check_faces(reconstruction_faces, rdims["M"])
    p = _numpy(reference_vertices)
    n = _numpy(reference_normals)
    length = np.linalg.norm(n, axis=1, keepdims=True)
    zero = np.nonzero(length[:, 0] <= 1e-12)[0]
    if len(zero):
        raise ValueError(f"reference_normals: expected non-zero normals, got {len(zero)} zero rows "
                         f"(first at index {int(zero[0])}): a vertex without a normal has no plane to score against")
    n = n / length
    q, _, _ = closest_points_on_mesh(p, _numpy(reconstruction_vertices), faces)
    errors = ((q - p) * n).sum(1)
    return torch.from_numpy(errors).to(reference_vertices)


def correspondence_errors(reference_vertices: Tensor, reconstruction_vertices: Tensor) -> Tensor:
    """Per-vertex distances :math:`\\lVert q_i - p_i \\rVert` between meshes of the same topology (mm).

    Shape:
        - reference_vertices, reconstruction_vertices: :math:`(N, 3)`; output :math:`(N,)`

    Example:
        >>> correspondence_errors(torch.zeros(2, 3), torch.tensor([[3.0, 4, 0], [0, 0, 1]]))
        tensor([5., 1.])
    """
    dims = _check_points(reference_vertices, "reference_vertices", ["N", 3])
    _check_points(reconstruction_vertices, "reconstruction_vertices", ["N", 3], dims)
    return torch.linalg.vector_norm(reconstruction_vertices.to(reference_vertices) - reference_vertices, dim=-1)


def _rotation_to_z(direction: np.ndarray) -> np.ndarray:
    """A rotation taking the unit vector ``direction`` to +z."""
    if direction[2] < 0:  # the formula below divides by 1 + cos: turn about x first, then z is near +z
        flip = np.diag([1.0, -1.0, -1.0])
        return _rotation_to_z(flip @ direction) @ flip
    v = np.array([direction[1], -direction[0], 0.0])  # direction x z
    k = np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])
    return np.eye(3) + k + k @ k / (1.0 + float(direction[2]))


def depth_errors(
    reference_vertices: Tensor,
    reconstruction_vertices: Tensor,
    reconstruction_faces: Tensor,
    view_direction: Tensor | None = None,
    front_facing: bool = True,
) -> Tensor:
    r"""Signed depth errors :math:`\Delta z_i` along the viewing direction (mm), NaN where there is no hit.

    :math:`\Delta z_i` is the coordinate along ``view_direction`` of the reconstruction's
    intersection with the line through :math:`p_i` parallel to ``view_direction`` (the
    intersection nearest to :math:`p_i` when the line crosses the reconstruction several times),
    minus that of :math:`p_i`. Only triangles facing the viewer count (outward normal ·
    ``view_direction`` < 0, counter-clockwise winding), so a line through a hole of the
    reconstruction (open eyes, mouth) does not score the inside of the back of the head. It equals
    the difference of two orthographic depth maps rendered along that direction wherever both
    surfaces are single-layered. For identical meshes it is 0 at every vertex whose vertex normal
    faces the viewer; robustly to rounding only where every triangle around it faces the viewer too
    (at a silhouette vertex the line may slip past the front-facing surface onto another layer:
    :func:`~facenormals.eval.evaluate_reconstruction` leaves such vertices out).

    Args:
        reference_vertices: reference points (mm).
        reconstruction_vertices: the aligned reconstruction's vertices (mm).
        reconstruction_faces: its triangles.
        view_direction: ``(3,)`` viewing direction; default ``(0, 0, 1)``, the optical axis of a
            frontal camera in the model frame (``docs/conventions.md``).
        front_facing: intersect only the triangles facing the viewer (default); ``False``: all.

    Returns:
        ``(N,)`` signed depth errors, NaN for reference points outside the reconstruction's
        silhouette, dtype and device of ``reference_vertices``.

    Example:
        >>> v = torch.tensor([[-10.0, -10, 1], [0, 10, 1], [10, -10, 1]]); f = torch.tensor([[0, 1, 2]])
        >>> depth_errors(torch.tensor([[0.0, 0, 0], [50, 0, 0]]), v, f)
        tensor([1., nan])
    """
    _check_points(reference_vertices, "reference_vertices", ["N", 3])
    rdims = _check_points(reconstruction_vertices, "reconstruction_vertices", ["M", 3])
    faces = _check_faces(reconstruction_faces, rdims["M"])
    p, v = _numpy(reference_vertices), _numpy(reconstruction_vertices)
    if view_direction is not None:
        _check_points(view_direction, "view_direction", [3])
        d = _numpy(view_direction)
        if np.linalg.norm(d) < 1e-12:
            raise ValueError("view_direction: expected a non-zero vector")
        rotation = _rotation_to_z(d / np.linalg.norm(d))
        p, v = p @ rotation.T, v @ rotation.T
    z = intersect_lines_along_z(p, v, faces, front_facing=front_facing)
    return torch.from_numpy(z - p[:, 2]).to(reference_vertices)


@dataclass(frozen=True)
class DepthStatistics:
    """Statistics of the absolute depth errors :math:`|\\Delta z|` (mm) over the hit vertices.

    Attributes:
        mean, std, median: of :math:`|\\Delta z|` (``std`` with ``ddof=0``).
        delta90: the 90th percentile of :math:`|\\Delta z|` (linear interpolation).
        coverage: fraction of the vertices whose line hit the reconstruction (the others are
            left out of the statistics).
        count: number of vertices in the statistics (the hits).
    """

    mean: float
    std: float
    median: float
    delta90: float
    coverage: float
    count: int

    def as_dict(self) -> dict[str, float]:
        return asdict(self)


def depth_statistics(errors: Tensor) -> DepthStatistics:
    """Mean, std, median and δ90 of ``|errors|`` over the finite entries (NaN = no hit).

    All statistics are NaN when no entry is finite.

    Example:
        >>> depth_statistics(torch.tensor([1.0, -2.0, 3.0, float("nan")]))
        DepthStatistics(mean=2.0, std=0.816..., median=2.0, delta90=2.8..., coverage=0.75, count=3)
    """
    check_shape(errors, ["N"], "errors")
    check_floating(errors, "errors")
    if bool(torch.isinf(errors).any()):  # NaN means no hit; an infinite error is a bug upstream
        raise ValueError(f"errors: expected finite values or NaN (no hit), got {int(torch.isinf(errors).sum())} "
                         "infinite")
    e = np.abs(_numpy(errors))
    hit = e[np.isfinite(e)]
    coverage = float(len(hit) / len(e)) if len(e) else 0.0
    if len(hit) == 0:
        nan = float("nan")
        return DepthStatistics(nan, nan, nan, nan, coverage, 0)
    return DepthStatistics(
        mean=float(hit.mean()),
        std=float(hit.std()),
        median=float(np.median(hit)),
        delta90=float(np.percentile(hit, 90)),
        coverage=coverage,
        count=len(hit),
    )
