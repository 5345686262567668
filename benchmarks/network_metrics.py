"""Held-out metrics of the network (the network issue's targets), as a markdown table.

Scores the weights on a held-out synthetic dataset (``facenormals synth --seed 1 --count 2000``,
a seed that training never sees) with :func:`facenormals.training.evaluate_network`:
normal angles over the true foreground, landmark errors of truly visible landmarks at the peak
of their map, visibility decisions (of the peaks alone, and after dropping the detections that the
pre-aligned mean head hides, as ``facenormals reconstruct`` does), foreground IoU; for the
mirror-averaged predictions that ``facenormals reconstruct`` uses (``mirror_averaged``) and for
the plain network.

    facenormals synth --count 2000 --seed 1 --out data/holdout --workers 2
    python benchmarks/network_metrics.py --holdout data/holdout [--weights PATH]
"""

from __future__ import annotations

import argparse

from facenormals.data import SyntheticHeadDataset
from facenormals.models import load_model
from facenormals.nn import load_weights
from facenormals.training import evaluate_network

TARGETS = {"normal_mean_deg": ("<=", 12.0), "normal_median_deg": ("<=", 8.0), "landmark_median_px": ("<=", 1.5),
           "landmark_mean_px": ("<=", 2.5), "visibility_accuracy": (">=", 0.95),
           "visibility_accuracy_posed": (">=", 0.95)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--holdout", required=True)
    parser.add_argument("--weights", default=None)
    parser.add_argument("--max-samples", type=int, default=None)
    parser.add_argument("--model", default="ict", help="model whose mean head judges hidden landmarks")
    args = parser.parse_args()
    net = load_weights(args.weights)
    model = load_model(args.model)
    dataset = SyntheticHeadDataset(args.holdout, with_landmark_maps=False)
    mirrored = evaluate_network(net, dataset, max_samples=args.max_samples, workers=1, mirror=True, model=model)
    plain = evaluate_network(net, dataset, max_samples=args.max_samples, workers=1, mirror=False, model=model)
    print(f"weights: {args.weights or 'shipped'} (step {net.metadata.get('step')}, "
          f"{net.metadata.get('samples_seen')} samples seen); held-out set {args.holdout}: {mirrored.samples} images\n")
    print("| metric | mirror-averaged (reconstruct) | plain network | target | met (mirror-averaged) |")
    print("|---|---|---|---|---|")

    def show(key, value):
        return f"{100 * value:.1f} %" if key.startswith("visibility_accuracy") else f"{value:.3f}"

    for key, value in mirrored.as_dict().items():
        if key == "samples":
            continue
        op, target = TARGETS.get(key, (None, None))
        ok = "" if op is None else ("yes" if (value <= target if op == "<=" else value >= target) else "**no**")
        goal = "" if op is None else f"{op} {100 * target:.0f} %" if key.startswith("visibility") else f"{op} {target}"
        print(f"| {key} | {show(key, value)} | {show(key, plain.as_dict()[key])} | {goal} | {ok} |")


if __name__ == "__main__":
    main()
