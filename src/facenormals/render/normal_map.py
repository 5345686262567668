"""Exact normal maps of a posed mesh, from the software rasteriser."""

from __future__ import annotations

import torch
from torch import Tensor

from facenormals.core.check import check_all_finite, check_floating, check_same_dtype_device, check_shape
from facenormals.geometry.projection import project_points
from facenormals.mesh import vertex_normals
from facenormals.render.rasterize import Fragments, interpolate_vertex_attributes, rasterize_triangles

__all__ = ["render_normal_map"]


@torch.no_grad()
def render_normal_map(
    vertices: Tensor,
    faces: Tensor,
    rotation: Tensor,
    translation: Tensor,
    intrinsics: Tensor,
    image_size: tuple[int, int],
    normals: Tensor | None = None,
) -> tuple[Tensor, Fragments]:
    r"""Render the camera-frame normal map of a mesh posed by :math:`X_c = R (p + t)`.

    Vertex normals (the paper's ring estimator unless ``normals`` is given) are rotated into the
    camera frame, interpolated with perspective-correct barycentrics and renormalised. Background
    pixels are exactly zero, following ``docs/conventions.md``.

    Args:
        vertices: mesh vertices in the model frame, mm.
        faces: triangles.
        rotation: rotation matrices ``(B, 3, 3)``, as in :func:`~facenormals.geometry.project_points`.
        translation: translations ``(B, 3)`` in the model frame, mm.
        intrinsics: ``(f, u0, v0)`` per view, ``(B, 3)``.
        image_size: ``(H, W)``.
        normals: optional model-frame vertex normals; computed with ``vertex_normals`` if omitted.

    Returns:
        ``(normal_map, fragments)`` with the normal map of shape :math:`(B, 3, H, W)`.

    Example:
        >>> from facenormals.models import builtin_head_model
        >>> model = builtin_head_model()
        >>> v = model(torch.zeros(1, model.num_shape))
        >>> nmap, frags = render_normal_map(v, model.faces, torch.eye(3)[None],
        ...     torch.tensor([[0.0, 0.0, 600.0]]), torch.tensor([[250.0, 31.5, 31.5]]), (64, 64))
        >>> nmap.shape, bool(frags.mask.any())
        (torch.Size([1, 3, 64, 64]), True)
    """
    dims = check_shape(vertices, ["B", "N", 3], "vertices")
    check_floating(vertices, "vertices")
    if normals is None:
        normals = vertex_normals(vertices, faces)
    check_shape(normals, ["B", "N", 3], "normals", dims)
    check_shape(rotation, ["B", 3, 3], "rotation", dims)
    check_shape(translation, ["B", 3], "translation", dims)
    check_shape(intrinsics, ["B", 3], "intrinsics", dims)
    check_same_dtype_device(vertices, "vertices", normals=normals, rotation=rotation, translation=translation,
                            intrinsics=intrinsics)
    # NaN would silently read as background (its triangles are skipped, its normals zeroed)
    check_all_finite(vertices=vertices, normals=normals, rotation=rotation, translation=translation,
                     intrinsics=intrinsics)
    pixels, depth = project_points(vertices, rotation, translation, intrinsics)
    fragments = rasterize_triangles(pixels, depth, faces, image_size)
    camera_normals = torch.matmul(normals, rotation.transpose(1, 2))
    normal_map = interpolate_vertex_attributes(fragments, faces, camera_normals)
    norm = normal_map.norm(dim=1, keepdim=True)
    normal_map = torch.where(norm > 0, normal_map / norm.clamp(min=1e-12), torch.zeros_like(normal_map))
    return normal_map, fragments
