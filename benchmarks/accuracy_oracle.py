"""Accuracy of the fit with oracle maps (exact normal maps and landmarks), by the paper's protocol.

For N random ICT heads (y ~ N(0, 1)), render exact 128x128 normal maps and visible landmarks, fit,
and score the face region (95 mm around the nose tip) after rigid and after similarity alignment:

- the mean head (y = 0) as the baseline,
- landmarks only (lambda_N = 0),
- single view, |yaw| <= 30 deg,
- three views at 0 and +-45 deg.

    python benchmarks/accuracy_oracle.py --heads 50 [--out TABLE.md]
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch

from facenormals.eval import evaluate_reconstruction
from facenormals.fitting import FitWeights, fit_head
from facenormals.fitting.oracle import render_oracle_views
from facenormals.models import load_model

METRICS = [
    ("similarity", "point_to_plane_rmse", "p2p RMSE, similarity"),
    ("similarity", "correspondence_rmse", "correspondence RMSE, similarity"),
    ("rigid", "point_to_plane_rmse", "p2p RMSE, rigid"),
    ("rigid", "correspondence_rmse", "correspondence RMSE, rigid"),
]


def score(model, vertices, truth):
    report = evaluate_reconstruction(vertices.double(), model.faces, truth.double(), model.faces, model.face_region,
                                     correspondences=model.landmarks)
    out = {name: getattr(getattr(report, kind), attr) for kind, attr, name in METRICS}
    out["depth median, similarity"] = report.similarity.depth.median
    out["depth delta90, similarity"] = report.similarity.depth.delta90
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--heads", type=int, default=50)
    parser.add_argument("--model", default="ict")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default=None, help="write the markdown table here")
    args = parser.parse_args()
    model = load_model(args.model, dtype=torch.float32)
    g = torch.Generator().manual_seed(args.seed)
    rows: dict[str, list[dict[str, float]]] = {k: [] for k in ("mean head", "landmarks only", "single view", "three views")}
    times = []
    start = time.perf_counter()
    for i in range(args.heads):
        y = model.sample_shape_coeffs(1, generator=g)
        yaw = float((torch.rand(1, generator=g) * 2 - 1) * 30.0)
        single = render_oracle_views(model, y, [yaw])
        three = render_oracle_views(model, y, [-45.0, 0.0, 45.0])
        truth = single.vertices[0]
        rows["mean head"].append(score(model, model.mean, truth))
        t0 = time.perf_counter()
        fit = fit_head(single.normal_maps, single.landmarks, model, intrinsics=single.intrinsics)
        times.append(time.perf_counter() - t0)
        rows["single view"].append(score(model, fit.vertices[0], truth))
        lm = fit_head(single.normal_maps, single.landmarks, model, intrinsics=single.intrinsics,
                      weights=FitWeights(normals=0.0))
        rows["landmarks only"].append(score(model, lm.vertices[0], truth))
        fit3 = fit_head(three.normal_maps, three.landmarks, model, intrinsics=three.intrinsics)
        rows["three views"].append(score(model, fit3.vertices[0], truth))
        print(f"head {i + 1}/{args.heads} (yaw {yaw:+.0f}): single "
              f"{rows['single view'][-1]['p2p RMSE, similarity']:.3f} mm, three "
              f"{rows['three views'][-1]['p2p RMSE, similarity']:.3f} mm, mean head "
              f"{rows['mean head'][-1]['p2p RMSE, similarity']:.3f} mm ({time.perf_counter() - start:.0f} s)", flush=True)

    names = list(rows["mean head"][0])
    mean = {k: {n: statistics.fmean(r[n] for r in v) for n in names} for k, v in rows.items()}
    lines = [
        f"{args.heads} random {model.name} heads (y ~ N(0, 1)), oracle 128x128 normal maps and visible landmarks; "
        "face region = 95 mm around the nose tip; errors in mm, mean over heads "
        "(ratio to the mean-head baseline in brackets).",
        "",
        "| method | " + " | ".join(names) + " |",
        "|---|" + "---|" * len(names),
    ]
    for k, v in mean.items():
        cells = [f"{v[n]:.3f}" + ("" if k == "mean head" else f" ({v[n] / mean['mean head'][n]:.2f})") for n in names]
        lines.append(f"| {k} | " + " | ".join(cells) + " |")
    lines += ["", f"Single-view fit time: median {statistics.median(times) * 1e3:.0f} ms (includes pre-alignment)."]
    text = "\n".join(lines)
    print(text)
    if args.out:
        with open(args.out, "w") as handle:
            handle.write("# Accuracy with oracle maps\n\nMade by `python benchmarks/accuracy_oracle.py "
                         f"--heads {args.heads} --out {args.out}` (seed {args.seed}).\n\n" + text + "\n")


if __name__ == "__main__":
    main()
