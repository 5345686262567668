"""Choose the shape-prior weight λP of the fit to the *network's* maps on validation heads.

The paper's λP = 0.4 suits maps as exact as the paper's network's; a network whose normals are
tens of degrees off needs a stronger prior, or the fit follows its errors. This script renders
validation heads of the held-out seed at indices 200,000+ (disjoint from the heads
``accuracy_network.py`` reports on, 100,000+, and from the 2,000 held-out metric images), runs the
network once per view, and fits each candidate λP (single view, |yaw| <= 30 deg, the recipe of
``facenormals reconstruct`` otherwise), scored after similarity alignment beside the mean head.
The chosen value goes into ``facenormals.reconstruct.NETWORK_FIT_WEIGHTS``.

    python benchmarks/tune_network_fit.py --heads 16 --priors 0.4,1,2,5,10
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import statistics

import numpy as np
import torch

from accuracy_network import images, score
from facenormals.data import SynthConfig, SyntheticHeadGenerator
from facenormals.fitting import fit_head
from facenormals.models import load_model
from facenormals.nn import load_weights
from facenormals.reconstruct import NETWORK_FIT_WEIGHTS, predict_maps
from facenormals.reconstruct.pipeline import DEFAULT_FOCAL, landmark_channels


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--heads", type=int, default=16)
    parser.add_argument("--priors", default="0.4,1,2,5,10", help="comma-separated candidate λP")
    parser.add_argument("--weights", default=None, help="network weights (default: the shipped ones)")
    parser.add_argument("--threads", type=int, default=None)
    args = parser.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    model = load_model("ict", dtype=torch.float32)
    net = load_weights(args.weights)
    generator = SyntheticHeadGenerator(model, SynthConfig(expression_probability=0.0))
    rng = np.random.default_rng(2)
    channels = landmark_channels(model)
    views, truths = [], []
    for i in range(args.heads):
        yaw = math.radians(rng.uniform(-30, 30))
        batch = generator.generate(1, [200_000 + i], angles=[(0.0, 0.0, yaw)])
        maps = predict_maps(net, images(batch))
        views.append((maps.normal_maps, maps.landmarks[:, channels]))
        truths.append(model(torch.from_numpy(batch.shape_coeffs))[0])
    base = [score(model, model.mean, t) for t in truths]
    b_p2p, b_corr = (statistics.mean(r[k] for r in base) for k in ("p2p sim", "corr sim"))
    size = views[0][0].shape[-1]
    intrinsics = torch.tensor([[DEFAULT_FOCAL, (size - 1) / 2, (size - 1) / 2]])
    lines = [f"{args.heads} validation heads (seed 1, indices 200,000+), network step {net.metadata.get('step')}; "
             f"mean head {b_p2p:.3f} / {b_corr:.3f} mm", "",
             "| λP | p2p RMSE, similarity | correspondence RMSE, similarity | ratio to mean head |", "|---|---|---|---|"]
    for prior in (float(p) for p in args.priors.split(",")):
        weights = dataclasses.replace(NETWORK_FIT_WEIGHTS, prior=prior)
        rows = []
        for (n, lm), t in zip(views, truths):
            try:
                rows.append(score(model, fit_head(n, lm, model, intrinsics=intrinsics, weights=weights).vertices[0], t))
            except ValueError as error:  # e.g. fewer than 4 landmarks detected: scored as the mean head
                print(f"fit failed ({error}); scored as the mean head")
                rows.append(score(model, model.mean, t))
        p2p, corr = (statistics.mean(r[k] for r in rows) for k in ("p2p sim", "corr sim"))
        lines.append(f"| {prior:g} | {p2p:.3f} | {corr:.3f} | {p2p / b_p2p:.2f} / {corr / b_corr:.2f} |")
        print(lines[-1], flush=True)
    print("\n".join(lines))


if __name__ == "__main__":
    main()
