"""Make the figures of docs/models.md: the 24 landmarks on ICT-FaceKit and the built-in head,
and the built-in head's mean with ±2σ samples.

    python docs/scripts/make_model_figures.py   # writes docs/img/*.png
"""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import torch

from facenormals.geometry import euler_to_rotation_matrix, project_points
from facenormals.models import BUILTIN_PARAMETERS, builtin_head_model, find_ict_archive, load_ict_npz
from facenormals.render import render_shaded, visible_vertices
from facenormals.render.rasterize import rasterize_triangles
from facenormals.geometry import transform_points
from facenormals.mesh import vertex_normals

OUT = Path(__file__).resolve().parents[1] / "img"


def view(yaw_deg: float, size: int, focal: float, distance: float = 900.0, dtype=torch.float64):
    R = euler_to_rotation_matrix(torch.tensor([[0.0, 0.0, math.radians(yaw_deg)]], dtype=dtype))
    t = torch.tensor([[0.0, -15.0, distance]], dtype=dtype) @ R[0]
    K = torch.tensor([[focal, (size - 1) / 2, (size - 1) / 2]], dtype=dtype)
    return R, t, K


def shaded(vertices, faces, R, t, K, size):
    img = render_shaded(vertices, faces, R, t, K, (size, size))[0, 0]
    grey = (img.clamp(0, 1) * 235 + 20 * (img > 0)).numpy().astype(np.uint8)
    return cv2.cvtColor(grey, cv2.COLOR_GRAY2BGR)


def landmark_figure(model, path: Path, size: int = 520) -> None:
    vertices = model.mean[None].double()
    panels = []
    for yaw in (0.0, 50.0):
        R, t, K = view(yaw, size, focal=1500.0)
        img = shaded(vertices, model.faces, R, t, K, size)
        uv, z = project_points(vertices, R, t, K)
        zbuf = rasterize_triangles(uv, z, model.faces, (size, size)).depth
        normals = vertex_normals(vertices, model.faces) @ R.transpose(1, 2)
        vis = visible_vertices(uv, z, normals, transform_points(vertices, R, t), zbuf)
        for k, (name, index) in enumerate(model.landmarks.items()):
            if not vis[0, index]:
                continue
            u, v = (int(round(c)) for c in uv[0, index].tolist())
            cv2.circle(img, (u, v), 4, (40, 40, 220), -1)
            label = f"{k}"
            cv2.putText(img, label, (u + 5, v - 4), cv2.FONT_HERSHEY_SIMPLEX, 0.38, (160, 30, 30), 1, cv2.LINE_AA)
        panels.append(img)
    legend = np.full((size, 230, 3), 255, np.uint8)
    for k, name in enumerate(model.landmarks):
        cv2.putText(legend, f"{k:2d} {name}", (8, 20 + 20 * k), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (60, 60, 60), 1, cv2.LINE_AA)
    cv2.imwrite(str(path), np.concatenate(panels + [legend], axis=1))


def samples_figure(model, path: Path, size: int = 220) -> None:
    names = ["head_length", "nose_projection", "jaw_width", "ear_protrusion", "face_height"]
    rows = []
    R, t, K = view(35.0, size, focal=650.0)
    mean = model.mean[None].double()
    header = [shaded(mean, model.faces, R, t, K, size) for _ in range(1)]
    g = torch.Generator().manual_seed(3)
    randoms = [model(model.shape_std[None] * torch.randn(1, model.num_shape, generator=g)).double() for _ in range(2)]
    top = header + [shaded(v, model.faces, R, t, K, size) for v in randoms]
    cv2.putText(top[0], "mean", (8, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (230, 230, 230), 1, cv2.LINE_AA)
    for img in top[1:]:
        cv2.putText(img, "random y ~ N(0, sigma^2)", (8, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (230, 230, 230), 1, cv2.LINE_AA)
    rows.append(np.concatenate(top, axis=1))
    index = [p.name for p in BUILTIN_PARAMETERS]
    for name in names:
        k = index.index(name)
        cells = []
        for s in (-2.0, 0.0, 2.0):
            y = torch.zeros(1, model.num_shape)
            y[0, k] = s * float(model.shape_std[k])
            img = shaded(model(y).double(), model.faces, R, t, K, size)
            cv2.putText(img, f"{name} {s:+.0f} sigma", (8, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (230, 230, 230), 1, cv2.LINE_AA)
            cells.append(img)
        rows.append(np.concatenate(cells, axis=1))
    cv2.imwrite(str(path), np.concatenate(rows, axis=0))


def main() -> None:
    OUT.mkdir(parents=True, exist_ok=True)
    builtin = builtin_head_model()
    landmark_figure(builtin, OUT / "builtin_landmarks.png")
    samples_figure(builtin, OUT / "builtin_samples.png")
    archive = find_ict_archive()
    if archive is None:
        print("ICT-FaceKit not found: skipped docs/img/ict_landmarks.png")
    else:
        landmark_figure(load_ict_npz(archive), OUT / "ict_landmarks.png")
    print(f"wrote figures to {OUT}")


if __name__ == "__main__":
    main()
