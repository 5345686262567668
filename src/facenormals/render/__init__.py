"""Software rasterisation of meshes into normal, depth and landmark maps."""

from facenormals.render.rasterize import Fragments, interpolate_vertex_attributes, rasterize_triangles

__all__ = ["Fragments", "interpolate_vertex_attributes", "rasterize_triangles"]
