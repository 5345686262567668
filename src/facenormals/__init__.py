"""facenormals: differentiable ops for reconstructing 3D heads from normals and landmarks.

Every public op is importable from here and from its subpackage (``facenormals.geometry`` ...).
"""

from facenormals.core import check_finite, check_floating, check_shape
from facenormals.energy import landmark_residuals, normal_residuals, prior_residuals
from facenormals.geometry import (
    euler_rotation_derivatives,
    euler_to_rotation_matrix,
    project_points,
    projection_jacobian,
    rotation_matrix_to_euler,
    transform_points,
)
from facenormals.mesh import VertexNormals, vertex_normals
from facenormals.models import (
    LANDMARK_NAMES,
    ModelFileError,
    MorphableModel,
    builtin_head_model,
    load_ict_npz,
    load_model,
)
from facenormals.nn import NormalLandmarkUNet, UNetOutput, normal_landmark_loss
from facenormals.optim import LMResult, LMStatus, levenberg_marquardt
from facenormals.render import (
    Fragments,
    interpolate_vertex_attributes,
    rasterize_triangles,
    render_normal_map,
    visible_vertices,
)
from facenormals.sampling import sample_bicubic, sample_bicubic_with_gradient

__version__ = "0.1.0"

__all__ = [
    "Fragments",
    "LANDMARK_NAMES",
    "LMResult",
    "LMStatus",
    "ModelFileError",
    "MorphableModel",
    "NormalLandmarkUNet",
    "UNetOutput",
    "VertexNormals",
    "builtin_head_model",
    "check_finite",
    "check_floating",
    "check_shape",
    "euler_rotation_derivatives",
    "euler_to_rotation_matrix",
    "interpolate_vertex_attributes",
    "landmark_residuals",
    "levenberg_marquardt",
    "load_ict_npz",
    "load_model",
    "normal_landmark_loss",
    "normal_residuals",
    "prior_residuals",
    "project_points",
    "projection_jacobian",
    "rasterize_triangles",
    "render_normal_map",
    "rotation_matrix_to_euler",
    "sample_bicubic",
    "sample_bicubic_with_gradient",
    "transform_points",
    "vertex_normals",
    "visible_vertices",
]
