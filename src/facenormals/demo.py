"""The synthetic demo (``facenormals demo``): synthesise a random head's normal map and landmarks, then recover it.

Every step is a public op or the public recipe: the model samples a head; ``render_oracle_views``
renders its exact camera-frame normal map and visible landmarks (standing in for the network);
``fit_head`` pre-aligns the mean head on the landmarks and fits shape, pose and intrinsics to
``E = λN·EN + λZ·EZ + λP·EP``; ``evaluate_reconstruction`` scores the face region in mm by the
paper's protocol, against the mean head as the baseline.
"""

from __future__ import annotations

import copy
import math
import time
from dataclasses import dataclass
from pathlib import Path

import torch

from facenormals.core.check import check_folder_name, check_integer
from facenormals.core.files import StagedFiles
from facenormals.eval import evaluate_reconstruction
from facenormals.fitting import fit_head
from facenormals.fitting.oracle import render_oracle_views
from facenormals.geometry import euler_to_rotation_matrix, project_points
from facenormals.models import MorphableModel
from facenormals.render import draw_alignment, normal_map_to_image

__all__ = ["DemoReport", "run_demo"]


@dataclass
class DemoReport:
    model: str
    mean_head_rmse_mm: float
    fitted_rmse_mm: float
    mean_head_correspondence_mm: float
    fitted_correspondence_mm: float
    landmark_error_px: float
    yaw_error_deg: float
    fit_seconds: float
    seconds: float
    mesh_path: Path | None
    overlay_path: Path | None


def run_demo(
    model: MorphableModel,
    seed: int = 0,
    out_dir: str | Path | None = None,
    image_size: int = 128,
    log=print,
) -> DemoReport:
    """Run the synthetic recover-a-random-head demo and return its report (see the module docstring)."""
    start = time.perf_counter()
    seed = check_integer(seed, "seed", minimum=0)
    image_size = check_integer(image_size, "image_size", minimum=8)
    check_folder_name(out_dir, "out_dir")
    if seed >= 2**63:  # torch's generators take a signed 64-bit seed
        raise ValueError(f"seed: expected an integer below 2**63, got {seed}")
    if model.mean.dtype != torch.float32:  # .to() converts a module in place: the caller's model stays as it is
        model = copy.deepcopy(model).to(torch.float32)
    g = torch.Generator().manual_seed(seed)
    y_true = model.sample_shape_coeffs(1, generator=g)
    yaw = float((torch.rand(1, generator=g) * 2 - 1) * 30.0)
    log(f"[1/4] model {model.name}: {model.num_vertices} vertices, {model.num_shape} shape components; "
        f"a random head at yaw {yaw:+.1f} deg")

    obs = render_oracle_views(model, y_true, [yaw], image_size=image_size)
    log(f"[2/4] synthesised its {image_size}x{image_size} normal map and {int(obs.landmark_mask.sum())}"
        f"/{obs.landmark_mask.shape[-1]} visible landmarks")

    t0 = time.perf_counter()
    result = fit_head(obs.normal_maps, obs.landmarks, model, intrinsics=obs.intrinsics)
    fit_seconds = time.perf_counter() - t0
    log(f"[3/4] pre-aligned and fitted in {fit_seconds * 1e3:.0f} ms: {result.summary()}")

    truth = obs.vertices[0].double()

    def score(vertices):
        report = evaluate_reconstruction(vertices.double(), model.faces, truth, model.faces, model.face_region,
                                         correspondences=model.landmarks)
        return report.similarity.point_to_plane_rmse, report.similarity.correspondence_rmse

    base_p2p, base_corr = score(model.mean)
    fit_p2p, fit_corr = score(result.vertices[0])
    log("[4/4] scored the face region (95 mm around the nose tip) after similarity alignment")

    report = DemoReport(
        model=model.name,
        mean_head_rmse_mm=base_p2p,
        fitted_rmse_mm=fit_p2p,
        mean_head_correspondence_mm=base_corr,
        fitted_correspondence_mm=fit_corr,
        landmark_error_px=float(result.landmark_rms_px[0, 0]),
        yaw_error_deg=abs(math.degrees(float(result.angles[0, 0, 2] - obs.angles[0, 0, 2]))),
        fit_seconds=fit_seconds,
        seconds=time.perf_counter() - start,
        mesh_path=None,
        overlay_path=None,
    )
    if out_dir is not None:  # both files or neither: a failure leaves the folder's earlier pair as it was
        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
        mesh_path, overlay_path = out / "demo_fit.ply", out / "demo_overlay.png"
        R = euler_to_rotation_matrix(result.angles[0])
        pixels, _ = project_points(result.vertices, R, result.translation[0], result.intrinsics[0])
        staged = StagedFiles()
        try:
            staged.write(mesh_path, result.export)
            staged.write(overlay_path, lambda part: draw_alignment(
                normal_map_to_image(obs.normal_maps[0, 0]), pixels[0], obs.landmarks[0, 0],
                visible=result.visible[0, 0], path=part))
            staged.commit()
        finally:
            staged.discard()
        report.mesh_path, report.overlay_path = mesh_path, overlay_path
    return report
