"""Oracle observations: exact normal maps and landmarks of known heads, for tests and accuracy studies."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import torch
from torch import Tensor

from facenormals.geometry import euler_to_rotation_matrix, project_points, transform_points
from facenormals.mesh import vertex_normals
from facenormals.models import MorphableModel
from facenormals.render import render_normal_map, visible_vertices

__all__ = ["OracleViews", "render_oracle_views"]


@dataclass
class OracleViews:
    """Ground truth and observations of one head seen in ``V`` views (batch of 1 subject)."""

    shape_coeffs: Tensor  # (1, K)
    vertices: Tensor  # (1, N, 3)
    angles: Tensor  # (1, V, 3)
    translation: Tensor  # (1, V, 3)
    intrinsics: Tensor  # (1, V, 3)
    normal_maps: Tensor  # (1, V, 3, H, W)
    landmarks: Tensor  # (1, V, L, 2), NaN where hidden
    landmark_mask: Tensor  # (1, V, L)


def render_oracle_views(
    model: MorphableModel,
    shape_coeffs: Tensor,
    yaws_deg: Sequence[float],
    image_size: int = 128,
    distance: float = 600.0,
    fill: float = 0.65,
    pitch_deg: float = 0.0,
    roll_deg: float = 0.0,
) -> OracleViews:
    """Render exact normal maps and visible landmarks of the head ``shape_coeffs`` ``(1, K)``.

    The focal length makes the head's width fill ``fill`` of the image; the principal point is the
    image centre. Hidden landmarks (z-buffer, back-facing) are NaN and masked out.
    """
    dtype = model.mean.dtype
    vertices = model(shape_coeffs.to(dtype))
    width = float(model.mean[:, 0].max() - model.mean[:, 0].min())
    focal = fill * image_size * distance / width
    maps, lms, masks, angles, translations = [], [], [], [], []
    K = torch.tensor([[focal, (image_size - 1) / 2, (image_size - 1) / 2]], dtype=dtype)
    normals = vertex_normals(vertices, model.faces)
    for yaw in yaws_deg:
        a = torch.tensor([[math.radians(roll_deg), math.radians(pitch_deg), math.radians(yaw)]], dtype=dtype)
        R = euler_to_rotation_matrix(a)
        t = torch.tensor([[0.0, 0.0, distance]], dtype=dtype) @ R[0]
        nmap, frags = render_normal_map(vertices, model.faces, R, t, K, (image_size, image_size), normals=normals)
        pixels, depth = project_points(vertices, R, t, K)
        visible = visible_vertices(pixels, depth, normals @ R.transpose(1, 2), transform_points(vertices, R, t),
                                   frags.depth)
        lm_visible = visible[:, model.landmark_indices]
        lm = pixels[:, model.landmark_indices]
        maps.append(nmap)
        lms.append(torch.where(lm_visible[..., None], lm, torch.full_like(lm, float("nan"))))
        masks.append(lm_visible)
        angles.append(a)
        translations.append(t)
    V = len(yaws_deg)
    return OracleViews(
        shape_coeffs=shape_coeffs,
        vertices=vertices,
        angles=torch.cat(angles)[None],
        translation=torch.cat(translations)[None],
        intrinsics=K.expand(V, 3)[None].clone(),
        normal_maps=torch.cat(maps)[None],
        landmarks=torch.cat(lms)[None],
        landmark_mask=torch.cat(masks)[None],
    )
