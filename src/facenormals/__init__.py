"""facenormals: differentiable ops for reconstructing 3D heads from normals and landmarks.

Every public op is importable from here and from its subpackage (``facenormals.geometry`` ...). They
load on first use (PEP 562): ``import facenormals``, and the ``facenormals`` command, start without
importing torch, so the command answers Ctrl-C with its one-line message from its first moment.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from facenormals._lazy import lazy_names

__version__ = "0.1.0"

#: each top-level name and the subpackage it comes from
_SOURCES = {
    "Fragments": "render",
    "LANDMARK_NAMES": "models",
    "LMResult": "optim",
    "LMStatus": "optim",
    "ModelFileError": "models",
    "MorphableModel": "models",
    "NormalLandmarkUNet": "nn",
    "UNetOutput": "nn",
    "VertexNormals": "mesh",
    "builtin_head_model": "models",
    "check_finite": "core",
    "check_floating": "core",
    "check_shape": "core",
    "euler_rotation_derivatives": "geometry",
    "euler_to_rotation_matrix": "geometry",
    "interpolate_vertex_attributes": "render",
    "landmark_residuals": "energy",
    "levenberg_marquardt": "optim",
    "load_ict_npz": "models",
    "load_model": "models",
    "normal_landmark_loss": "nn",
    "normal_residuals": "energy",
    "prior_residuals": "energy",
    "project_points": "geometry",
    "projection_jacobian": "geometry",
    "rasterize_triangles": "render",
    "render_normal_map": "render",
    "rotation_matrix_to_euler": "geometry",
    "sample_bicubic": "sampling",
    "sample_bicubic_with_gradient": "sampling",
    "transform_points": "geometry",
    "vertex_normals": "mesh",
    "visible_vertices": "render",
}

__all__ = [  # the keys of _SOURCES, spelt out for linters
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


__getattr__, __dir__ = lazy_names(__name__, _SOURCES, globals(), subpackages=True)

if TYPE_CHECKING:  # type checkers and editors do not run __getattr__
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
