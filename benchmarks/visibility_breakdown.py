"""Where the network's landmark visibility decisions go wrong, and what geometry can fix (markdown).

On a held-out synthetic set (``facenormals synth --seed 1``), with the mirror-averaged peaks that
``facenormals reconstruct`` uses:

1. the wrong decisions of the peaks alone, by what the landmark's nearest pixel shows in the true
   render (skin in front of it, eyeball, hair, occluder, background ...), and per landmark;
2. the share of correct decisions of the peaks alone; after the pose gate
   (:func:`~facenormals.fitting.drop_hidden_landmarks`, what ``reconstruct`` fits with); with the
   peaks switched off where the predicted normal map has no foreground within 1 px (hair,
   occluders); and with the *true* head's z-buffer at the *true* pose (an upper bound for any
   geometric check after the fit; no hair, no expression);
3. with ``--calibration DIR``: per-landmark thresholds re-chosen for the gated decisions on
   training samples (``--calibration-range``), scored on the held-out set.

    python benchmarks/visibility_breakdown.py --holdout data/holdout [--weights PATH] \\
        [--calibration data/train --calibration-range 59000 60000]
"""

from __future__ import annotations

import argparse

import torch
import torch.nn.functional as F
from torch import Tensor
from torch.utils.data import DataLoader, Subset

from facenormals.data import SyntheticHeadDataset, landmarks_from_maps
from facenormals.data.scene import LABELS
from facenormals.fitting import drop_hidden_landmarks, hidden_landmarks
from facenormals.fitting.landmark_visibility import DEFAULT_FOCAL
from facenormals.models import load_model
from facenormals.nn import load_weights, mirror_averaged
from facenormals.reconstruct import landmark_channels
from facenormals.training import landmark_threshold


@torch.no_grad()
def predict(net, dataset, keys=("landmark_visible",)) -> dict[str, Tensor]:
    out: dict[str, list[Tensor]] = {"peak": [], "points": [], "foreground": [], **{k: [] for k in keys}}
    for batch in DataLoader(dataset, batch_size=50):
        pred = mirror_averaged(net, batch["image"])
        maps = pred.landmarks.float()
        points, _ = landmarks_from_maps(maps, threshold=float("-inf"))
        out["peak"].append(maps.flatten(2).amax(-1))
        out["points"].append(points)
        out["foreground"].append(pred.foreground()[:, 0])
        for k in keys:
            out[k].append(batch[k])
    return {k: torch.cat(v) for k, v in out.items()}


def pose_gate(points: Tensor, found: Tensor, model, size: int) -> Tensor:
    """``(B, L)`` the detections that ``drop_hidden_landmarks`` drops (hidden by the mean head
    pre-aligned to them; none in a view that would keep fewer than 4), as ``reconstruct`` does."""
    K = torch.tensor([DEFAULT_FOCAL, (size - 1) / 2, (size - 1) / 2], dtype=model.mean.dtype).expand(len(found), 3)
    dropped = torch.zeros_like(found)
    for chunk in torch.arange(len(found)).split(100):
        kept, _ = drop_hidden_landmarks(points[chunk].to(model.mean), found[chunk], model, K[chunk], (size, size))
        dropped[chunk] = found[chunk] & ~kept
    return dropped


def gated(peak: Tensor, points: Tensor, threshold: Tensor, model, size: int) -> Tensor:
    found = peak > threshold
    return found & ~pose_gate(points, found, model, size)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--holdout", required=True)
    parser.add_argument("--weights", default=None)
    parser.add_argument("--model", default="ict")
    parser.add_argument("--max-samples", type=int, default=None)
    parser.add_argument("--calibration", default=None, help="training set to re-choose the gated thresholds on")
    parser.add_argument("--calibration-range", type=int, nargs=2, default=(59000, 60000))
    args = parser.parse_args()
    if args.calibration:  # checked before the held-out set is predicted
        lo, hi = args.calibration_range
        size = len(SyntheticHeadDataset(args.calibration, with_landmark_maps=False))
        if not 0 <= lo < hi <= size:
            parser.error(f"--calibration-range {lo} {hi}: expected 0 <= LO < HI <= {size}, the size of {args.calibration}")
    net = load_weights(args.weights).eval()
    model = load_model(args.model, dtype=torch.float64)
    if landmark_channels(model) != list(range(len(model.landmark_names))):
        raise SystemExit(f"--model {args.model}: expected the network's 24 landmarks in its order")
    threshold = torch.as_tensor(landmark_threshold(net), dtype=torch.float32)
    dataset = SyntheticHeadDataset(args.holdout, with_landmark_maps=False)
    if args.max_samples:
        dataset = Subset(dataset, range(min(args.max_samples, len(dataset))))
    keys = ("landmark_visible", "landmarks", "segmentation", "rotation", "translation", "intrinsics", "shape_coeffs")
    d = predict(net, dataset, keys)
    visible, found, size = d["landmark_visible"], d["peak"] > threshold, d["foreground"].shape[-1]
    B, L = visible.shape
    print(f"weights: {args.weights or 'shipped'}; held-out set {args.holdout}: {B} images, {B * L} landmark slots\n")

    # 1. Wrong decisions by what the nearest pixel shows.
    uv = d["landmarks"].nan_to_num(-1.0).round().long()
    inside = ((uv >= 0) & (uv < size)).all(-1)
    label = d["segmentation"][torch.arange(B)[:, None], uv[..., 1].clamp(0, size - 1), uv[..., 0].clamp(0, size - 1)]
    label = torch.where(inside, label.long(), torch.tensor(-1))
    names = {-1: "outside the image", **{v: k for k, v in LABELS.items()}}
    print("| nearest pixel shows | truly visible | slots | wrong | wrong, share of all slots |")
    print("|---|---|---|---|---|")
    for value, name in names.items():
        for truth in (True, False):
            slots = (label == value) & (visible == truth)
            if int(slots.sum()):
                wrong = int((found[slots] != truth).sum())
                print(f"| {name} | {'yes' if truth else 'no'} | {int(slots.sum())} | {wrong} "
                      f"({100 * wrong / int(slots.sum()):.1f} %) | {100 * wrong / (B * L):.2f} % |")
    per = (found == visible).float().mean(0)
    print("\nper landmark, correct (peaks alone): " + ", ".join(f"{n} {100 * float(a):.0f} %"
                                                             for n, a in zip(model.landmark_names, per)))

    # 2. Decisions with geometry.
    def share(decision: Tensor) -> str:
        return f"{100 * float((decision == visible).float().mean()):.1f} %"

    rows = [("peaks alone (shipped thresholds)", share(found)),
            ("after the pose gate (`drop_hidden_landmarks`, what `reconstruct` uses)",
             share(gated(d["peak"], d["points"], threshold, model, size)))]
    near = F.max_pool2d(d["foreground"][:, None].float(), 3, 1, 1)[:, 0] > 0
    peak_uv = d["points"].round().long().clamp(0, size - 1)
    on_face = near[torch.arange(B)[:, None], peak_uv[..., 1], peak_uv[..., 0]]
    rows.append(("peaks alone, off where the predicted normal map has no foreground within 1 px", share(found & on_face)))
    true_hidden = torch.cat([
        hidden_landmarks(model, d["rotation"][i].double(), d["translation"][i].double(), d["intrinsics"][i].double(),
                         (size, size), shape=d["shape_coeffs"][i].double(), tolerance=5.0)
        for i in torch.arange(B).split(100)])
    rows.append(("peaks and the true head's z-buffer at the true pose (5 mm slack; upper bound)",
                 share(found & ~true_hidden)))

    # 3. Thresholds re-chosen for the gated decisions (alternating: gate at the current thresholds,
    # then per landmark the threshold with the most correct gated decisions).
    if args.calibration:
        lo, hi = args.calibration_range
        cal = predict(net, Subset(SyntheticHeadDataset(args.calibration, with_landmark_maps=False), range(lo, hi)))
        candidates, chosen = torch.linspace(0.05, 0.95, 37), threshold.clone()
        for _ in range(3):
            gate = pose_gate(cal["points"], cal["peak"] > chosen, model, size)
            correct = torch.stack([(((cal["peak"] > t) & ~gate) == cal["landmark_visible"]).float().mean(0)
                                   for t in candidates])
            best = [torch.nonzero(correct[:, c] == correct[:, c].max()).squeeze(1) for c in range(L)]
            chosen = torch.stack([candidates[b[len(b) // 2]] for b in best])
        rows.append((f"after the pose gate, thresholds re-chosen on {args.calibration}[{lo}:{hi}] "
                     f"(peaks alone then {share(d['peak'] > chosen)})",
                     share(gated(d["peak"], d["points"], chosen, model, size))))
        print("\nre-chosen thresholds: " + ", ".join(f"{float(t):.3f}" for t in chosen))
    print("\n| decision | correct |\n|---|---|")
    for name, value in rows:
        print(f"| {name} | {value} |")


if __name__ == "__main__":
    main()
