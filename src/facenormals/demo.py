"""The demo main job: synthesise a random head's normal map and landmarks, then recover it.

Every step is a public op: the model samples a head, ``render_normal_map`` and ``project_points``
synthesise the observations, a batched ``levenberg_marquardt`` over several yaw starts pre-aligns
the mean head on the landmarks, and a second LM fits shape and pose to
``E = λN·EN + λZ·EZ + λP·EP`` built from ``normal_residuals``, ``landmark_residuals`` and
``prior_residuals``. Visibility is recomputed between LM rounds with the z-buffer.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from pathlib import Path

import torch
from torch import Tensor

from facenormals.energy import landmark_residuals, normal_residuals, prior_residuals
from facenormals.geometry import euler_to_rotation_matrix, project_points, transform_points
from facenormals.mesh import vertex_normals
from facenormals.models import MorphableModel
from facenormals.optim import levenberg_marquardt
from facenormals.render import rasterize_triangles, render_normal_map, visible_vertices

__all__ = ["DemoReport", "run_demo"]


@dataclass
class DemoReport:
    model: str
    mean_head_rmse_mm: float
    fitted_rmse_mm: float
    landmark_error_px: float
    normal_error_deg: float
    yaw_error_deg: float
    seconds: float
    mesh_path: Path | None


def _pose(x: Tensor) -> tuple[Tensor, Tensor]:
    """Split ``(B, 6)`` pose parameters (roll, pitch, yaw, tx, ty, tz) into ``R`` and ``t``."""
    return euler_to_rotation_matrix(x[:, :3]), x[:, 3:6]


def _visibility(model: MorphableModel, vertices: Tensor, R: Tensor, t: Tensor, K: Tensor, size: int) -> Tensor:
    pixels, depth = project_points(vertices, R, t, K)
    zbuffer = rasterize_triangles(pixels, depth, model.faces, (size, size)).depth
    normals = torch.matmul(vertex_normals(vertices, model.faces), R.transpose(1, 2))
    return visible_vertices(pixels, depth, normals, transform_points(vertices, R, t), zbuffer)


def run_demo(
    model: MorphableModel,
    seed: int = 0,
    out_dir: str | Path | None = None,
    image_size: int = 128,
    weights: tuple[float, float, float] = (1.0, 0.8, 0.4),
    log=print,
) -> DemoReport:
    """Run the synthetic recover-a-random-head demo and return its report (see the module docstring)."""
    start = time.perf_counter()
    model = model.to(torch.float64)
    g = torch.Generator().manual_seed(seed)
    K_dim = model.num_shape
    lam_n, lam_z, lam_p = weights

    # 1. A random head, pose and camera.
    y_true = model.sample_shape_coeffs(1, generator=g)
    angles_true = (torch.rand(1, 3, generator=g, dtype=torch.float64) * 2 - 1) * torch.tensor(
        [math.radians(8), math.radians(12), math.radians(30)], dtype=torch.float64
    )
    distance = 600.0
    width = float(model.mean[:, 0].max() - model.mean[:, 0].min())
    focal = 0.75 * image_size * distance / width
    K = torch.tensor([[focal, (image_size - 1) / 2, (image_size - 1) / 2]], dtype=torch.float64)
    R_true = euler_to_rotation_matrix(angles_true)
    t_true = (R_true.transpose(1, 2) @ torch.tensor([0.0, 0.0, distance], dtype=torch.float64))
    t_true = t_true + torch.randn(1, 3, generator=g, dtype=torch.float64) * 5.0
    vertices_true = model(y_true)
    log(f"[1/4] model {model.name}: {model.num_vertices} vertices, {K_dim} shape components; "
        f"true yaw {math.degrees(angles_true[0, 2]):+.1f} deg")

    # 2. Observations: the exact normal map and the visible landmarks.
    normal_map, _ = render_normal_map(vertices_true, model.faces, R_true, t_true, K, (image_size, image_size))
    visible_true = _visibility(model, vertices_true, R_true, t_true, K, image_size)
    lm_index = model.landmark_indices
    lm_pixels, _ = project_points(vertices_true[:, lm_index], R_true, t_true, K)
    lm_mask = visible_true[:, lm_index]
    log(f"[2/4] synthesised a {image_size}x{image_size} normal map and {int(lm_mask.sum())}/{len(lm_index)} "
        "visible landmarks")

    # 3. Pre-alignment: mean shape, 6-DoF pose from landmarks, several yaw starts as one batch.
    mean_landmarks = model.mean[lm_index][None]
    yaws = torch.tensor([-60.0, -30.0, 0.0, 30.0, 60.0], dtype=torch.float64).deg2rad()
    starts = torch.zeros(len(yaws), 6, dtype=torch.float64)
    starts[:, 2] = yaws
    starts[:, 3:] = (euler_to_rotation_matrix(starts[:, :3]).transpose(1, 2)
                     @ torch.tensor([0.0, 0.0, distance], dtype=torch.float64))
    targets = lm_pixels.expand(len(yaws), -1, -1)
    mask = lm_mask.expand(len(yaws), -1)

    def pose_residuals(x: Tensor) -> Tensor:
        R, t = _pose(x)
        uv, _ = project_points(mean_landmarks.expand(x.shape[0], -1, -1), R, t, K.expand(x.shape[0], -1))
        return landmark_residuals(uv, targets[: x.shape[0]], mask[: x.shape[0]]).flatten(1)

    pre = levenberg_marquardt(pose_residuals, starts, max_iterations=50)
    best = int(torch.argmin(pre.cost))
    pose = pre.x[best : best + 1]
    log(f"[3/4] pre-aligned from {len(yaws)} yaw starts in one batch: yaw {math.degrees(pose[0, 2]):+.1f} deg, "
        f"landmark RMS {math.sqrt(2 * float(pre.cost[best]) / max(int(lm_mask.sum()), 1) / 2):.2f} px")

    # 4. Fit shape and pose to normals + landmarks + prior, refreshing visibility between rounds.
    x = torch.cat([torch.zeros(1, K_dim, dtype=torch.float64), pose], dim=1)
    for round_index in range(3):
        R, t = _pose(x[:, K_dim:])
        visible = _visibility(model, model(x[:, :K_dim]), R, t, K, image_size)

        def fit_residuals(params: Tensor, visible=visible) -> Tensor:
            y, p = params[:, :K_dim], params[:, K_dim:]
            R, t = _pose(p)
            verts = model(y)
            uv, _ = project_points(verts, R, t, K)
            normals = torch.matmul(vertex_normals(verts, model.faces), R.transpose(1, 2))
            r_n, _ = normal_residuals(normal_map, uv, normals, visible, weight=lam_n)
            r_z = landmark_residuals(uv[:, lm_index], lm_pixels, lm_mask, weight=lam_z)
            r_p = prior_residuals(y, model.shape_std, weight=lam_p)
            return torch.cat([r_n.flatten(1), r_z.flatten(1), r_p], dim=1)

        result = levenberg_marquardt(fit_residuals, x, max_iterations=8)
        x = result.x
        log(f"[4/4] round {round_index + 1}: {int(visible.sum())} visible vertices, energy {float(result.cost[0]):.3f}, "
            f"{int(result.iterations[0])} LM iterations ({result.reasons[0]})")

    y_fit = x[:, :K_dim]
    R_fit, t_fit = _pose(x[:, K_dim:])
    vertices_fit = model(y_fit)
    # Errors over the vertices the camera saw; the back of the head is unobserved.
    rmse = lambda a, b: float(((a - b) ** 2).sum(-1).mean().sqrt())  # noqa: E731
    uv_fit, _ = project_points(vertices_fit[:, lm_index], R_fit, t_fit, K)
    lm_err = float((uv_fit - lm_pixels).norm(dim=-1)[lm_mask].mean())
    n_fit = torch.matmul(vertex_normals(vertices_fit, model.faces), R_fit.transpose(1, 2))
    n_true = torch.matmul(vertex_normals(vertices_true, model.faces), R_true.transpose(1, 2))
    cos = (n_fit * n_true).sum(-1).clamp(-1, 1)[visible_true]
    report = DemoReport(
        model=model.name,
        mean_head_rmse_mm=rmse(model.mean[None][visible_true], vertices_true[visible_true]),
        fitted_rmse_mm=rmse(vertices_fit[visible_true], vertices_true[visible_true]),
        landmark_error_px=lm_err,
        normal_error_deg=float(torch.rad2deg(torch.acos(cos)).mean()),
        yaw_error_deg=abs(math.degrees(float(x[0, K_dim + 2] - angles_true[0, 2]))),
        seconds=time.perf_counter() - start,
        mesh_path=None,
    )
    if out_dir is not None:
        import trimesh

        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
        report.mesh_path = out / "demo_fit.ply"
        mesh = trimesh.Trimesh(vertices_fit[0].numpy(), model.faces.numpy(), process=False)
        mesh.export(report.mesh_path)
    return report
