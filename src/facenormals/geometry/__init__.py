"""Rotations and camera projection."""

from facenormals.geometry.projection import project_points, projection_jacobian, transform_points
from facenormals.geometry.rotation import (
    euler_rotation_derivatives,
    euler_to_rotation_matrix,
    rotation_matrix_to_euler,
)

__all__ = [
    "euler_rotation_derivatives",
    "euler_to_rotation_matrix",
    "project_points",
    "projection_jacobian",
    "rotation_matrix_to_euler",
    "transform_points",
]
