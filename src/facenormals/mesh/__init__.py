"""Mesh ops: vertex normals."""

from facenormals.mesh.normals import VertexNormals, vertex_normals

__all__ = ["VertexNormals", "vertex_normals"]
