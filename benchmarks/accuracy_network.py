"""Accuracy of the whole method with the *network's* maps on held-out synthetic renders, in mm.

For N held-out identities of the synthetic generator (dataset seed 1, the held-out seed, which
training never sees; ICT heads with y ~ N(0, 1), neutral expression, full appearance: skin, hair,
eyes, occluders, backgrounds), render

- one view with |yaw| <= 30 deg,
- three views of the same person at yaw 0 and +-45 deg, and
- one side view with |yaw| in 50-75 deg (no target; it shows what the far side's hidden landmarks
  do to the fit),

run the network on each 128x128 image, decode its landmarks, fit (the shipped recipe,
``reconstruct_views``), and score the face region (95 mm around the nose tip) after similarity and
rigid alignment against the true mesh, beside the mean head (y = 0) as the baseline. The fit does
not know the true intrinsics: it starts from the same focal prior as ``facenormals reconstruct``.

    python benchmarks/accuracy_network.py --heads 50 --out docs/network_accuracy.md
"""

from __future__ import annotations

import argparse
import math
import statistics
import time

import numpy as np
import torch

from facenormals.data import SynthConfig, SyntheticHeadGenerator
from facenormals.eval import evaluate_reconstruction
from facenormals.models import load_model
from facenormals.nn import load_weights
from facenormals.reconstruct import reconstruct_views

KEYS = [("similarity", "point_to_plane_rmse", "p2p sim"), ("similarity", "correspondence_rmse", "corr sim"),
        ("rigid", "point_to_plane_rmse", "p2p rigid"), ("rigid", "correspondence_rmse", "corr rigid")]


def score(model, vertices, truth):
    report = evaluate_reconstruction(vertices.double(), model.faces, truth.double(), model.faces, model.face_region,
                                     correspondences=model.landmarks)
    return {name: getattr(getattr(report, kind), attr) for kind, attr, name in KEYS}


def images(batch) -> torch.Tensor:
    return torch.from_numpy(batch.image).permute(0, 3, 1, 2).float() / 255.0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--heads", type=int, default=50)
    parser.add_argument("--weights", default=None, help="network weights (default: the shipped ones)")
    parser.add_argument("--model", default="ict")
    parser.add_argument("--seed", type=int, default=1, help="synthetic dataset seed (1 = the held-out seed)")
    parser.add_argument("--out", default=None, help="write the markdown table here")
    args = parser.parse_args()
    model = load_model(args.model, dtype=torch.float32)
    net = load_weights(args.weights)
    generator = SyntheticHeadGenerator(model, SynthConfig(expression_probability=0.0))
    rng = np.random.default_rng(args.seed)
    side_rng = np.random.default_rng(args.seed + 1000)  # apart, so the other settings keep their yaws
    rows = {k: {} for k in ("mean head", "single view", "three views", "side view")}  # head index -> scores
    start = time.perf_counter()
    failures = []
    for i in range(args.heads):
        index = 100_000 + i  # beyond the 2,000 held-out images
        yaw = math.radians(rng.uniform(-30, 30))
        single = generator.generate(args.seed, [index], angles=[(0.0, 0.0, yaw)])
        three = generator.generate(args.seed, [index] * 3, angles=[(0.0, 0.0, math.radians(a)) for a in (-45, 0, 45)])
        side_yaw = math.radians(side_rng.choice([-1.0, 1.0]) * side_rng.uniform(50, 75))
        side = generator.generate(args.seed, [index], angles=[(0.0, 0.0, side_yaw)])
        truth = model(torch.from_numpy(single.shape_coeffs))[0]
        rows["mean head"][i] = score(model, model.mean, truth)
        for name, batch in (("single view", single), ("three views", three), ("side view", side)):
            try:
                _, fit = reconstruct_views(images(batch), net, model)
            except ValueError as error:  # e.g. too few landmarks detected in a view
                failures.append(f"head {i} {name}: {error}")
                continue
            rows[name][i] = score(model, fit.vertices[0], truth)
        scores = ", ".join(f"{name} " + (f"{rows[name][i]['p2p sim']:.3f} mm" if i in rows[name] else "failed")
                           for name in rows)
        print(f"head {i + 1}/{args.heads}: {scores} ({time.perf_counter() - start:.0f} s)", flush=True)

    lines = [
        f"Network weights: `{args.weights or 'shipped'}` (step {net.metadata.get('step')}, "
        f"{net.metadata.get('samples_seen')} training samples seen); {args.heads} held-out heads, "
        f"model {model.name}; {len(failures)} failed fits.",
        "",
        "| setting | p2p RMSE, similarity | correspondence RMSE, similarity | p2p RMSE, rigid | "
        "correspondence RMSE, rigid | ratio to mean head (p2p / corr, similarity; over the same heads) |",
        "|---|---|---|---|---|---|",
    ]
    for name, values in rows.items():
        if not values:
            continue
        m = {k: statistics.mean(r[k] for r in values.values()) for _, _, k in KEYS}
        base = {k: statistics.mean(rows["mean head"][i][k] for i in values) for _, _, k in KEYS}
        lines.append(f"| {name} ({len(values)}) | {m['p2p sim']:.3f} | {m['corr sim']:.3f} | {m['p2p rigid']:.3f} | "
                     f"{m['corr rigid']:.3f} | {m['p2p sim'] / base['p2p sim']:.2f} / "
                     f"{m['corr sim'] / base['corr sim']:.2f} |")
    lines += ["", *[f"- {f}" for f in failures]]
    table = "\n".join(lines)
    print(table)
    if args.out:
        with open(args.out, "w") as handle:
            handle.write("<!-- generated by benchmarks/accuracy_network.py -->\n" + table + "\n")


if __name__ == "__main__":
    main()
