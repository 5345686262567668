"""Make the figures of the tutorials (docs/tutorials/*.md) under docs/img/tutorials/.

Regenerate all of them with one command from the repository root (shipped weights, ICT-FaceKit;
RUN is the training run folder of the shipped weights, holding log.csv and eval.csv):

    python docs/scripts/make_tutorial_figures.py --run RUN

`--weights PATH` uses another weight file and `--model` another morphable model (default ict).
Without `--run` the training-curve figure is left as it is. About 30 s on a 2-core CPU. Every figure is computed from scratch (no random state outside the
fixed seeds), so the same weights and model give the same pictures.

Figures:

- astronaut_outputs.png: the photo with the detected face and head crop, then the files
  `facenormals reconstruct` writes for it: view0_overlay.png, view0_normals.png (N), view0_landmarks.png (Z);
- astronaut_mesh.png: the reconstructed head.ply rendered with pyrender (headless EGL) from three sides;
- multiview.png: three synthetic views of one held-out identity (seed 1), their overlays and predicted N,
  the fitted mesh and the ground truth, rendered at the views' yaws;
- evaluate_errors.png: per-vertex point-to-plane errors of that fit against the ground truth after
  similarity alignment, on the reference face region;
- training_curves.png (with --run): training losses from log.csv and held-out metrics from eval.csv.
"""

from __future__ import annotations

import argparse
import csv
import math
import shutil
import tempfile
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[2]
OUT = ROOT / "docs" / "img" / "tutorials"
PHOTO = ROOT / "examples" / "data" / "astronaut.jpg"
#: The held-out identity of the multi-view figure: dataset seed 1 (the held-out set), sample 0.
HELDOUT_SEED, HELDOUT_INDEX = 1, 0
YAWS = (-0.785, 0.0, 0.785)
PANEL = 256
WHITE = (255, 255, 255)


# --------------------------------------------------------------------------------------- drawing


def write_png(name: str, rgb: np.ndarray) -> Path:
    import cv2

    path = OUT / name
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), np.ascontiguousarray(rgb[..., ::-1]), [cv2.IMWRITE_PNG_COMPRESSION, 9])
    print(f"wrote {path.relative_to(ROOT)} ({path.stat().st_size / 1e3:.0f} kB)")
    return path


def fit_panel(rgb: np.ndarray, size: int = PANEL) -> np.ndarray:
    import cv2

    interpolation = cv2.INTER_AREA if rgb.shape[0] > size else cv2.INTER_NEAREST
    return cv2.resize(rgb, (size, size), interpolation=interpolation)


def label(rgb: np.ndarray, text: str) -> np.ndarray:
    """A caption strip above a panel."""
    import cv2

    strip = np.full((22, rgb.shape[1], 3), 255, np.uint8)
    cv2.putText(strip, text, (4, 16), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
    return np.concatenate([strip, rgb])


def grid(rows: list[list[np.ndarray]], gap: int = 4) -> np.ndarray:
    """Panels of equal height per row, separated by white gaps; rows padded to the widest."""
    lines = []
    for row in rows:
        parts = []
        for panel in row:
            if parts:
                parts.append(np.full((panel.shape[0], gap, 3), 255, np.uint8))
            parts.append(panel)
        lines.append(np.concatenate(parts, axis=1))
    width = max(line.shape[1] for line in lines)
    out = []
    for line in lines:
        if out:
            out.append(np.full((gap, width, 3), 255, np.uint8))
        pad = np.full((line.shape[0], width - line.shape[1], 3), 255, np.uint8)
        out.append(np.concatenate([line, pad], axis=1))
    return np.concatenate(out)


# ------------------------------------------------------------------------------ pyrender meshes


def look_from(position: np.ndarray) -> np.ndarray:
    """Pose of a light (or camera) at ``position`` (OpenGL frame) looking at the origin along its -z."""
    z = position / np.linalg.norm(position)
    x = np.cross([0.0, 1.0, 0.0], z)
    x /= np.linalg.norm(x)
    pose = np.eye(4)
    pose[:3, :3] = np.stack([x, np.cross(z, x), z], axis=1)
    return pose


class MeshRenderer:
    """Shaded renders of model-frame meshes (mm; face along -z, y down) with pyrender, offscreen.

    The headless platform is chosen by :func:`facenormals.data.select_gl_platform` (EGL, else OSMesa)
    before pyrender imports OpenGL. One renderer serves the whole script.
    """

    def __init__(self, size: int = PANEL, supersample: int = 2) -> None:
        from facenormals.data import select_gl_platform

        select_gl_platform()
        import pyrender

        self.pyrender = pyrender
        self.size, self.supersample = size, supersample
        self.renderer = pyrender.OffscreenRenderer(size * supersample, size * supersample)

    def render(self, vertices: torch.Tensor, faces: torch.Tensor, yaw: float = 0.0, colors: np.ndarray | None = None,
               extent: float | None = None, center: np.ndarray | None = None) -> np.ndarray:
        """RGB ``(size, size, 3)`` of the mesh turned by ``yaw`` (radians, the library's convention:
        positive turns the face towards image left), lit from the camera and from the upper left.

        ``colors``: optional ``(N, 3)`` uint8 vertex colours; ``extent``/``center``: framing in mm
        (default: the mesh's bounding box), so several renders can share one scale.
        """
        import cv2
        import trimesh

        from facenormals.geometry import euler_to_rotation_matrix

        pyrender = self.pyrender
        v = vertices.detach().cpu().double()
        if center is None:
            center = 0.5 * (v.min(0).values + v.max(0).values).numpy()
        if extent is None:
            extent = float((v.max(0).values - v.min(0).values)[:2].max())
        R = euler_to_rotation_matrix(torch.tensor([[0.0, 0.0, yaw]], dtype=torch.float64))[0]
        turned = (v - torch.from_numpy(np.asarray(center))) @ R.T
        gl = turned.numpy() * np.array([1.0, -1.0, -1.0])  # model frame (y down, face -z) -> OpenGL (y up, face +z)
        mesh = trimesh.Trimesh(gl, faces.cpu().numpy(), vertex_colors=colors, process=False)
        material = None
        if colors is None:
            material = pyrender.MetallicRoughnessMaterial(baseColorFactor=(0.80, 0.74, 0.68, 1.0),
                                                          metallicFactor=0.0, roughnessFactor=0.75)
        scene = pyrender.Scene(bg_color=(1.0, 1.0, 1.0, 1.0), ambient_light=(0.25, 0.25, 0.25))
        scene.add(pyrender.Mesh.from_trimesh(mesh, material=material, smooth=True))
        yfov = math.radians(20.0)
        distance = 0.6 * extent / math.tan(yfov / 2) + float(np.abs(gl[:, 2]).max())
        camera = np.eye(4)
        camera[2, 3] = distance
        scene.add(pyrender.PerspectiveCamera(yfov=yfov, znear=10.0, zfar=distance + 1000.0), pose=camera)
        scene.add(pyrender.DirectionalLight(intensity=2.2), pose=camera)
        key = look_from(np.array([-1.0, 1.0, 1.2]))  # upper left, in front
        scene.add(pyrender.DirectionalLight(intensity=1.8), pose=key)
        color, _ = self.renderer.render(scene)
        return cv2.resize(color[..., :3], (self.size, self.size), interpolation=cv2.INTER_AREA)

    def close(self) -> None:
        self.renderer.delete()


# ------------------------------------------------------------------------------------- figures


def astronaut_figures(args: argparse.Namespace, model, renderer: MeshRenderer, work: Path) -> None:
    """Run the product path on the example photo and picture its outputs and mesh."""
    import cv2

    from facenormals.reconstruct import detect_faces, read_image, reconstruct_photos

    out = work / "astronaut"
    rec = reconstruct_photos([PHOTO], out, model=model, weights=args.weights, log=print)
    photo = read_image(PHOTO)
    face = detect_faces(photo)[0]
    x0, y0, side = rec.views[0].box
    boxes = photo.copy()
    thickness = max(2, photo.shape[0] // 200)
    cv2.rectangle(boxes, (round(face.x), round(face.y)), (round(face.x + face.width), round(face.y + face.height)),
                  (40, 200, 40), thickness, cv2.LINE_AA)
    cv2.rectangle(boxes, (round(x0), round(y0)), (round(x0 + side), round(y0 + side)), (255, 140, 0), thickness,
                  cv2.LINE_AA)
    panels = [label(fit_panel(boxes), "photo: face box, head crop")]
    for name, text in (("view0_overlay.png", "view0_overlay.png"), ("view0_normals.png", "view0_normals.png (N)"),
                       ("view0_landmarks.png", "view0_landmarks.png (Z)")):
        panels.append(label(fit_panel(read_image(out / name)), text))
    write_png("astronaut_outputs.png", grid([panels]))

    fit = rec.fit
    renders = [label(renderer.render(fit.vertices[0], fit.faces, yaw), f"head.ply, yaw {math.degrees(yaw):+.0f} deg")
               for yaw in (0.0, 0.785, 1.571)]
    write_png("astronaut_mesh.png", grid([renders]))


def multiview_figures(args: argparse.Namespace, model, renderer: MeshRenderer) -> None:
    """Three synthetic views of one held-out person: inputs, overlays, N, fitted mesh vs truth, errors."""
    import cv2

    from facenormals.data import SyntheticHeadGenerator
    from facenormals.eval import evaluate_reconstruction, point_to_plane_errors
    from facenormals.geometry import euler_to_rotation_matrix, project_points
    from facenormals.mesh import vertex_normals
    from facenormals.nn import load_weights
    from facenormals.reconstruct import reconstruct_views
    from facenormals.render import draw_alignment, normal_map_to_image

    index = HELDOUT_INDEX
    with SyntheticHeadGenerator(model) as generator:
        batch = generator.generate(HELDOUT_SEED, [index, index, index], angles=[(0, 0, yaw) for yaw in YAWS])
    crops = torch.from_numpy(batch.image).permute(0, 3, 1, 2).float() / 255.0  # (3, 3, 128, 128)
    net = load_weights(args.weights)
    maps, fit = reconstruct_views(crops, net, model, log=print)

    R = euler_to_rotation_matrix(fit.angles[0])
    pixels, _ = project_points(fit.vertices.expand(3, -1, -1), R, fit.translation[0], fit.intrinsics[0])
    truth = model(torch.from_numpy(batch.shape_coeffs[:1]), torch.from_numpy(batch.expression_coeffs[:1]))[0]
    extent = float((truth.max(0).values - truth.min(0).values)[:2].max())
    rows = [[], [], [], [], []]
    for v, yaw in enumerate(YAWS):
        deg = f"{math.degrees(yaw):+.0f} deg"
        rows[0].append(label(fit_panel(batch.image[v], 192), f"input, yaw {deg}"))
        overlay = draw_alignment(batch.image[v], pixels[v], maps.landmarks[v], visible=fit.visible[0, v])
        rows[1].append(label(fit_panel(overlay, 192), "overlay"))
        rows[2].append(label(fit_panel(normal_map_to_image(maps.normal_maps[v]), 192), "predicted N"))
        rows[3].append(label(renderer.render(fit.vertices[0], fit.faces, yaw, extent=extent)[32:-32, 32:-32],
                             "fitted (one shape)"))
        rows[4].append(label(renderer.render(truth, model.faces, yaw, extent=extent)[32:-32, 32:-32], "ground truth"))
    write_png("multiview.png", grid(rows))

    report = evaluate_reconstruction(fit.vertices[0].double(), fit.faces, truth.double(), model.faces,
                                     model.face_region, correspondences=model)
    print(report)
    sim = report.similarity
    aligned = sim.scale * fit.vertices[0].double() @ sim.rotation.T + sim.translation
    normals = vertex_normals(truth.double()[None], model.faces)[0]
    region = model.face_region
    errors = point_to_plane_errors(truth.double()[region], normals[region], aligned, fit.faces).abs()
    limit = 3.0  # mm at the top of the colour scale
    value = np.zeros(model.num_vertices)
    value[region.numpy()] = (errors.numpy() / limit).clip(0, 1)
    colors = cv2.applyColorMap((value * 255).astype(np.uint8)[:, None], cv2.COLORMAP_VIRIDIS)[:, 0, ::-1].copy()
    colors[~region.numpy()] = (200, 200, 200)
    panels = [label(renderer.render(truth, model.faces, yaw, colors=colors, extent=extent)[16:-16, 16:-16],
                    f"|point-to-plane| error, yaw {math.degrees(yaw):+.0f} deg") for yaw in (0.0, 0.785)]
    bar_height = panels[0].shape[0] - 22
    ramp = np.linspace(1.0, 0.0, bar_height)
    bar = cv2.applyColorMap((ramp * 255).astype(np.uint8)[:, None], cv2.COLORMAP_VIRIDIS)[:, :, ::-1]
    bar = np.repeat(bar, 18, axis=1)
    scale = np.full((bar_height, 70, 3), 255, np.uint8)
    scale[:, :18] = bar
    for mm in range(int(limit) + 1):
        y = round((1 - mm / limit) * (bar_height - 1))
        cv2.putText(scale, f"{mm} mm" + ("+" if mm == int(limit) else ""), (22, min(max(y + 4, 10), bar_height - 2)),
                    cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 0, 0), 1, cv2.LINE_AA)
    panels.append(label(scale, ""))
    write_png("evaluate_errors.png", grid([panels]))


def read_csv(path: Path) -> dict[str, np.ndarray]:
    with path.open(newline="") as handle:
        rows = list(csv.DictReader(handle))
    return {key: np.array([float(row[key]) for row in rows]) for key in (rows[0] if rows else {})}


def nice_step(span: float) -> float:
    """1, 2 or 5 times a power of ten, at least ``span``."""
    if not span > 0:
        return 1.0
    power = 10.0 ** math.floor(math.log10(span))
    return next(m * power for m in (1, 2, 5, 10) if m * power >= span)


def plot(series: list[tuple[np.ndarray, np.ndarray, tuple[int, int, int], str]], title: str, log_y: bool = False,
         x_label: str = "million samples seen",
         size: tuple[int, int] = (440, 300)) -> np.ndarray:
    """A line plot drawn with OpenCV: ``series`` of ``(x, y, rgb, name)``; log10 y axis if ``log_y``."""
    import cv2

    width, height = size
    left, right, top, bottom = 58, 12, 46, 36
    img = np.full((height, width, 3), 255, np.uint8)
    xs = np.concatenate([s[0] for s in series])
    ys = np.concatenate([s[1] for s in series])
    ys = ys[np.isfinite(ys) & ((ys > 0) if log_y else True)]
    if xs.size == 0 or ys.size == 0:
        return img
    f = np.log10 if log_y else (lambda a: a)
    x_lo, x_hi = 0.0, float(xs.max()) or 1.0
    y_lo, y_hi = float(f(ys).min()), float(f(ys).max())
    if log_y:
        y_lo, y_hi = math.floor(y_lo), math.ceil(y_hi)
    else:
        y_lo = min(0.0, y_lo)
        y_hi = y_hi if y_hi > y_lo else y_lo + 1.0
        step = nice_step((y_hi - y_lo) / 4)
        y_lo, y_hi = step * math.floor(y_lo / step), step * math.ceil(y_hi / step)
    if y_hi <= y_lo:
        y_hi = y_lo + 1.0
    x_step = nice_step(x_hi / 4)
    x_hi = x_step * math.ceil(x_hi / x_step)

    def to_px(x: np.ndarray, y: np.ndarray) -> np.ndarray:
        u = left + (x - x_lo) / (x_hi - x_lo) * (width - left - right)
        v = top + (1 - (f(y) - y_lo) / (y_hi - y_lo)) * (height - top - bottom)
        return np.stack([u, v], -1)

    grey, black = (225, 225, 225), (0, 0, 0)
    ticks = np.arange(y_lo, y_hi + 1e-9) if log_y else np.arange(y_lo, y_hi + 1e-9 * step, step)
    for t in ticks:
        v = round(top + (1 - (t - y_lo) / (y_hi - y_lo)) * (height - top - bottom))
        cv2.line(img, (left, v), (width - right, v), grey, 1)
        text = f"1e{int(t)}" if log_y else f"{t:g}"
        cv2.putText(img, text, (4, v + 4), cv2.FONT_HERSHEY_SIMPLEX, 0.38, black, 1, cv2.LINE_AA)
    for t in np.arange(x_lo, x_hi + 1e-9 * x_step, x_step):
        u = round(left + (t - x_lo) / (x_hi - x_lo) * (width - left - right))
        cv2.line(img, (u, top), (u, height - bottom), grey, 1)
        label = f"{t:g}"
        w = cv2.getTextSize(label, cv2.FONT_HERSHEY_SIMPLEX, 0.38, 1)[0][0]
        x_text = min(u - w // 2, width - w - 2)  # centred under the tick, never past the right edge
        cv2.putText(img, label, (x_text, height - bottom + 14), cv2.FONT_HERSHEY_SIMPLEX, 0.38, black, 1,
                    cv2.LINE_AA)
    cv2.rectangle(img, (left, top), (width - right, height - bottom), black, 1)
    label_width = cv2.getTextSize(x_label, cv2.FONT_HERSHEY_SIMPLEX, 0.4, 1)[0][0]
    cv2.putText(img, x_label, (width // 2 - label_width // 2, height - 6), cv2.FONT_HERSHEY_SIMPLEX, 0.4, black, 1,
                cv2.LINE_AA)
    cv2.putText(img, title, (left, 18), cv2.FONT_HERSHEY_SIMPLEX, 0.45, black, 1, cv2.LINE_AA)
    x_text = left
    for x, y, rgb, name in series:
        keep = np.isfinite(y) & ((y > 0) if log_y else True)
        points = to_px(x[keep], y[keep]).round().astype(np.int32)
        if len(points) > 1:
            cv2.polylines(img, [points], False, rgb, 2, cv2.LINE_AA)
        for p in points if len(points) <= 20 else []:
            cv2.circle(img, tuple(int(c) for c in p), 3, rgb, -1, cv2.LINE_AA)
        cv2.line(img, (x_text, 32), (x_text + 18, 32), rgb, 2)
        cv2.putText(img, name, (x_text + 22, 36), cv2.FONT_HERSHEY_SIMPLEX, 0.38, black, 1, cv2.LINE_AA)
        x_text += 34 + cv2.getTextSize(name, cv2.FONT_HERSHEY_SIMPLEX, 0.38, 1)[0][0]
    return img


def training_figure(run: Path) -> None:
    """Losses (log.csv) and held-out metrics of the averaged weights (eval.csv) of a training run,
    against millions of samples seen (runs of different batch sizes share one axis)."""
    log = read_csv(run / "log.csv")
    x = log["samples_seen"] / 1e6
    blue, orange, green, red = (31, 119, 180), (255, 127, 14), (44, 160, 44), (214, 39, 40)
    panels = [plot([(x, log["loss"], blue, "total"), (x, log["normals"], orange, "L_N"),
                    (x, log["landmarks"], green, "L_Z (unweighted)"), (x, log["foreground"], red, "foreground")],
                   "training loss", log_y=True)]
    if (run / "eval.csv").exists():
        ev = read_csv(run / "eval.csv")
        if ev:
            xe = ev["samples_seen"] / 1e6
            panels.append(plot([(xe, ev["normal_mean_deg"], blue, "mean"),
                                (xe, ev["normal_median_deg"], orange, "median")],
                               "held out: normal angle, deg"))
            panels.append(plot([(xe, ev["landmark_mean_px"], blue, "mean"),
                                (xe, ev["landmark_median_px"], orange, "median")],
                               "held out: landmark error, px"))
    write_png("training_curves.png", grid([panels]))


def main() -> None:
    from facenormals.models import load_model
    from facenormals.nn import pretrained_weights_path

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--weights", default=str(pretrained_weights_path()), help="network weights (default: shipped)")
    parser.add_argument("--model", default="ict", help="morphable model: ict (default), builtin, auto or a path")
    parser.add_argument("--run", default=None, help="training run folder (log.csv, eval.csv) for training_curves.png")
    args = parser.parse_args()
    model = load_model(args.model).to(torch.float32)
    work = Path(tempfile.mkdtemp(prefix="facenormals_tutorial_"))
    renderer = MeshRenderer()
    try:
        astronaut_figures(args, model, renderer, work)
        multiview_figures(args, model, renderer)
        if args.run is not None:
            training_figure(Path(args.run))
    finally:
        renderer.close()
        shutil.rmtree(work, ignore_errors=True)

if __name__ == "__main__":
    main()
