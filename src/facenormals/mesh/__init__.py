"""Mesh ops: vertex normals and mesh files."""

from facenormals.mesh.io import load_mesh, save_mesh
from facenormals.mesh.normals import VertexNormals, vertex_normals

__all__ = ["VertexNormals", "load_mesh", "save_mesh", "vertex_normals"]
