"""Compose the ops by hand: project a head, render its normal map, sample it and fit a pose by LM.

    python examples/compose_ops.py
"""

import argparse
import math

import torch

import facenormals as fn

argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter).parse_args()
torch.manual_seed(0)
model = fn.load_model("builtin", dtype=torch.float64)  # no download needed
vertices = model(model.sample_shape_coeffs(1))  # (1, N, 3), mm

# A camera 600 mm away looking at the head turned by 20 degrees of yaw.
angles = torch.tensor([[0.0, math.radians(5), math.radians(20)]], dtype=torch.float64)
R = fn.euler_to_rotation_matrix(angles)
t = torch.tensor([[0.0, 0.0, 600.0]], dtype=torch.float64) @ R[0]  # R (p + t) puts the head at z = 600
K = torch.tensor([[300.0, 63.5, 63.5]], dtype=torch.float64)  # (f, u0, v0)

# Observations: an exact normal map and the projected landmarks.
normal_map, fragments = fn.render_normal_map(vertices, model.faces, R, t, K, (128, 128))
landmarks, _ = fn.project_points(model.landmark_vertices(vertices), R, t, K)
print("normal map", tuple(normal_map.shape), "foreground pixels", int(fragments.mask.sum()))

# The normal residual of the true head is small: sample N at the projected vertices.
pixels, depth = fn.project_points(vertices, R, t, K)
camera_normals = fn.vertex_normals(vertices, model.faces) @ R.transpose(1, 2)
visible = fn.visible_vertices(pixels, depth, camera_normals, fn.transform_points(vertices, R, t), fragments.depth)
r_n, valid = fn.normal_residuals(normal_map, pixels, camera_normals, visible)
print(f"normal residual RMS at the truth: {r_n[valid].norm(dim=-1).pow(2).mean().sqrt():.4f} over {int(valid.sum())} vertices")

# Fit the 6-DoF pose of the true shape to the landmarks, from a frontal start.
points = model.landmark_vertices(vertices)


def residuals(x):
    R_x = fn.euler_to_rotation_matrix(x[:, :3])
    uv, _ = fn.project_points(points.expand(x.shape[0], -1, -1), R_x, x[:, 3:], K.expand(x.shape[0], -1))
    return fn.landmark_residuals(uv, landmarks.expand(x.shape[0], -1, -1)).flatten(1)


x0 = torch.tensor([[0.0, 0.0, 0.0, 0.0, 0.0, 600.0]], dtype=torch.float64)
result = fn.levenberg_marquardt(residuals, x0)
print(result.summary())
print("recovered yaw (deg):", math.degrees(result.x[0, 2]), "true:", math.degrees(angles[0, 2]))
