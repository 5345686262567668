"""Rotations and camera projection."""

from facenormals.geometry.projection import project_points, transform_points
from facenormals.geometry.rotation import euler_to_rotation_matrix, rotation_matrix_to_euler

__all__ = [
    "euler_to_rotation_matrix",
    "project_points",
    "rotation_matrix_to_euler",
    "transform_points",
]
