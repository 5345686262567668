"""The paper's evaluation protocol: landmark alignment, point-to-plane ICP and reconstruction errors (mm).

See :func:`evaluate_reconstruction` for the protocol and :mod:`facenormals.eval.metrics` for the
exact error definitions.
"""

from facenormals.eval.align import (
    DEFAULT_ALIGNMENT_LANDMARKS,
    apply_similarity,
    fit_similarity,
    landmark_correspondences,
)
from facenormals.eval.icp import ICPResult, icp_point_to_plane
from facenormals.eval.metrics import (
    DepthStatistics,
    correspondence_errors,
    depth_errors,
    depth_statistics,
    point_to_plane_errors,
)
from facenormals.eval.report import (
    AlignmentResult,
    EvaluationReport,
    evaluate_reconstruction,
    shares_vertex_order,
    summarise,
)
from facenormals.eval.surface import closest_points_on_mesh

__all__ = [
    "AlignmentResult",
    "DEFAULT_ALIGNMENT_LANDMARKS",
    "DepthStatistics",
    "EvaluationReport",
    "ICPResult",
    "apply_similarity",
    "closest_points_on_mesh",
    "correspondence_errors",
    "depth_errors",
    "depth_statistics",
    "evaluate_reconstruction",
    "fit_similarity",
    "icp_point_to_plane",
    "landmark_correspondences",
    "point_to_plane_errors",
    "shares_vertex_order",
    "summarise",
]
