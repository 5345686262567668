"""Choose the weights λN and λP of the fit to the *network's* maps on validation heads.

The paper's λN = 1, λP = 0.4 suit maps as exact as the paper's network's; a network whose normals
are ten degrees off needs a weaker normal term or a stronger prior, or the fit follows its errors. This script renders
validation heads of the held-out seed at indices 200,000+ (disjoint from the heads
``accuracy_network.py`` reports on, 100,000+, and from the 2,000 held-out metric images), runs the
network once per view, and fits each candidate (λN, λP) pair (single view, |yaw| <= 30 deg, the recipe of
``facenormals reconstruct`` otherwise), scored after similarity alignment beside the mean head.
``--store`` writes the best row's λN and λP into the weight file's metadata (``fit_weights``), which
``facenormals reconstruct`` uses for that network (:func:`facenormals.reconstruct.network_fit_weights`;
``NETWORK_FIT_WEIGHTS`` is the fallback for weights without them). Each row also gives
the mean per-head change of the p2p RMSE against the first row, with its standard error: the
spread between heads is large, so a difference of one or two standard errors is not a finding.

    python benchmarks/tune_network_fit.py --heads 32 --normals 1,0.25,0.1,0 --priors 1,2
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
from facenormals.models import find_ict_archive, load_model
from facenormals.nn import load_weights, pretrained_weights_path, update_weight_metadata
from facenormals.reconstruct import fit_inputs, network_fit_weights, predict_maps


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--heads", type=int, default=16)
    parser.add_argument("--priors", default="0.4,1,2,5,10", help="comma-separated candidate λP")
    parser.add_argument("--normals", default="1", help="comma-separated candidate λN")
    parser.add_argument("--weights", default=None, help="network weights (default: the shipped ones)")
    parser.add_argument("--threads", type=int, default=None)
    parser.add_argument("--store", action="store_true",
                        help="write the best (λN, λP) by mean p2p RMSE into the weight file's metadata")
    args = parser.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    if find_ict_archive() is None:  # the weights are tuned for (and stored with) the ICT-FaceKit fit
        raise SystemExit("tune_network_fit.py needs ICT-FaceKit: `facenormals models fetch ict` (or set FACENORMALS_ICT)")
    model = load_model("ict", dtype=torch.float32)
    net = load_weights(args.weights)
    generator = SyntheticHeadGenerator(model, SynthConfig(expression_probability=0.0))
    rng = np.random.default_rng(2)
    views, truths = [], []
    for i in range(args.heads):
        yaw = math.radians(rng.uniform(-30, 30))
        batch = generator.generate(1, [200_000 + i], angles=[(0.0, 0.0, yaw)])
        inputs = fit_inputs(predict_maps(net, images(batch)), model)  # as facenormals reconstruct does
        views.append(inputs)
        truths.append(model(torch.from_numpy(batch.shape_coeffs))[0])
    base = [score(model, model.mean, t) for t in truths]
    b_p2p, b_corr = (statistics.mean(r[k] for r in base) for k in ("p2p sim", "corr sim"))
    lines = [f"{args.heads} validation heads (seed 1, indices 200,000+), network step {net.metadata.get('step')}; "
             f"mean head {b_p2p:.3f} / {b_corr:.3f} mm", "",
             "| λN | λP | p2p RMSE, similarity | correspondence RMSE, similarity | ratio to mean head "
             "| p2p change per head vs the first row (± s.e.) |", "|---|---|---|---|---|---|"]
    first, best = None, None
    for normal, prior in ((float(n), float(p)) for n in args.normals.split(",") for p in args.priors.split(",")):
        weights = dataclasses.replace(network_fit_weights(net), normals=normal, prior=prior)
        rows = []
        for inputs, t in zip(views, truths):
            try:
                fit = fit_head(inputs.normal_maps, inputs.landmarks, model, intrinsics=inputs.intrinsics,
                               weights=weights, initial_pose=inputs.initial_pose)
                rows.append(score(model, fit.vertices[0], t))
            except ValueError as error:  # e.g. fewer than 4 landmarks detected: scored as the mean head
                print(f"fit failed ({error}); scored as the mean head")
                rows.append(score(model, model.mean, t))
        p2p, corr = (statistics.mean(r[k] for r in rows) for k in ("p2p sim", "corr sim"))
        per_head = [r["p2p sim"] for r in rows]
        first = per_head if first is None else first
        change = [a - b for a, b in zip(per_head, first)]
        error = statistics.stdev(change) / math.sqrt(len(change)) if len(change) > 1 else 0.0
        lines.append(f"| {normal:g} | {prior:g} | {p2p:.3f} | {corr:.3f} | {p2p / b_p2p:.3f} / {corr / b_corr:.3f} "
                     f"| {statistics.mean(change):+.3f} ± {error:.3f} |")
        print(lines[-1], flush=True)
        if best is None or p2p < best[0]:
            best = (p2p, normal, prior)
    print("\n".join(lines))
    if args.store:
        path = update_weight_metadata(args.weights or pretrained_weights_path(),
                                      fit_weights={"normals": best[1], "prior": best[2]})
        print(f"stored fit_weights λN = {best[1]:g}, λP = {best[2]:g} in {path}")


if __name__ == "__main__":
    main()
