"""Train the normal + landmark U-Net on synthetic data, then score and export it.

Step by step, with the library's public pieces (the same as ``facenormals synth`` and
``facenormals train``):

1. render a training set and a held-out set (``write_dataset``; deterministic per (seed, index),
   resumable, shardable by rank);
2. train (``train``; resumes from ``OUT/last.pt``; CPU, CUDA, or several GPUs with
   ``torchrun --nproc-per-node N examples/train_unet.py ...``);
3. score the moving-average weights on the held-out set (``evaluate_network``);
4. export them as a small fp16 weight file (``export_weights``) that ``facenormals reconstruct
   --weights`` and ``load_weights`` read.

A quick run that finishes in a few minutes on a laptop CPU::

    python examples/train_unet.py --count 2000 --holdout-count 200 --steps 300 --out runs/quick

The shipped weights were trained from this recipe in four stages, with warm restarts, two GPU
stages at batch 256 and a CPU fine-tuning stage, on 2.29 M samples from four datasets
(``docs/model_card.md`` has the history).
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

from torch.utils.data import Subset

from facenormals.data import SyntheticHeadDataset, write_dataset
from facenormals.nn import load_weights
from facenormals.training import TrainConfig, evaluate_network, export_weights, train


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", default="runs/unet")
    parser.add_argument("--data", default=None, help="training set folder (default: OUT/data)")
    parser.add_argument("--count", type=int, default=60_000)
    parser.add_argument("--holdout-count", type=int, default=2_000)
    parser.add_argument("--steps", type=int, default=TrainConfig.steps)
    parser.add_argument("--batch-size", type=int, default=TrainConfig.batch_size)
    parser.add_argument("--workers", type=int, default=2, help="data generation processes (training loads with one worker: on 2 cores a second one only "
                        "competes with the training threads)")
    parser.add_argument("--model", default="auto", help="morphable model rendered: ict, builtin, auto or a path")
    args = parser.parse_args()
    out = Path(args.out)
    data = Path(args.data) if args.data else out / "data"
    holdout = out / "holdout"
    rank, world = int(os.environ.get("RANK", 0)), int(os.environ.get("WORLD_SIZE", 1))

    # 1. Data: every rank renders its share of the shards; finished shards are skipped on a rerun.
    write_dataset(data, args.count, workers=args.workers, seed=0, model_spec=args.model, rank=rank, world_size=world)
    write_dataset(holdout, args.holdout_count, workers=args.workers, seed=1, model_spec=args.model, rank=rank,
                  world_size=world)
    if world > 1:  # wait until every rank's shards exist
        import torch.distributed as dist

        dist.init_process_group("gloo")
        dist.barrier()
        dist.destroy_process_group()

    # 2. Train (resumes from out/run/last.pt).
    config = TrainConfig(data=str(data), out=str(out / "run"), holdout=str(holdout), steps=args.steps,
                         batch_size=args.batch_size, workers=min(args.workers, 1),
                         warmup_steps=min(TrainConfig.warmup_steps, max(1, args.steps // 10)))
    summary = train(config)
    if summary.stopped_by == "signal":  # Ctrl-C / SIGTERM: the checkpoint is saved; no half-trained export
        print(f"stopped at step {summary.step}; rerun the same command to resume from {summary.checkpoint}")
        sys.exit(130)
    if rank != 0:
        return
    print(f"trained to step {summary.step} ({summary.samples_seen} samples, stopped by {summary.stopped_by})")

    # 3. + 4. Export the averaged weights, with the landmark detection threshold calibrated on the
    # last (up to) 1,000 training samples, and score them on the whole held-out set.
    train_set = SyntheticHeadDataset(data, with_landmark_maps=False)
    calibration = Subset(train_set, range(max(0, len(train_set) - 1000), len(train_set)))
    weights = export_weights(summary.checkpoint, out / "normal_landmark_unet.pt", calibration_data=calibration)
    metrics = evaluate_network(load_weights(weights), SyntheticHeadDataset(holdout, with_landmark_maps=False))
    print(f"held out: {metrics}")
    print(f"weights: {weights} ({weights.stat().st_size / 1e6:.1f} MB); use them with "
          f"`facenormals reconstruct photo.jpg -o out --weights {weights}`")


if __name__ == "__main__":
    main()
