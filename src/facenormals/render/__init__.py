"""Software rasterisation of meshes into normal and depth maps, and vertex visibility."""

from facenormals.render.normal_map import render_normal_map
from facenormals.render.overlay import draw_alignment, normal_map_to_image
from facenormals.render.rasterize import Fragments, interpolate_vertex_attributes, rasterize_depth, rasterize_triangles
from facenormals.render.shading import render_shaded, shade_normal_map
from facenormals.render.visibility import splat_zbuffer, unoccluded_points, visible_vertices

__all__ = [
    "Fragments",
    "draw_alignment",
    "interpolate_vertex_attributes",
    "normal_map_to_image",
    "rasterize_depth",
    "rasterize_triangles",
    "render_normal_map",
    "render_shaded",
    "shade_normal_map",
    "splat_zbuffer",
    "unoccluded_points",
    "visible_vertices",
]
