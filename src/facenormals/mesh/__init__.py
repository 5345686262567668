"""Mesh ops: vertex normals, their analytic derivatives, and mesh files."""

from facenormals.mesh.io import load_mesh, save_mesh
from facenormals.mesh.normals import VertexNormals, vertex_normals
from facenormals.mesh.normals_jvp import VertexNormalsJacobian, vertex_normals_jvp

__all__ = ["VertexNormals", "VertexNormalsJacobian", "load_mesh", "save_mesh", "vertex_normals", "vertex_normals_jvp"]
