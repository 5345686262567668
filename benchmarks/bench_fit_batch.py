"""Batched fitting throughput on one device: B subjects as one batch vs B sequential fits.

The full single-view recipe (:func:`~facenormals.fitting.fit_head`: pre-alignment, three LM rounds)
on oracle maps of random ICT heads at 128x128, fitted on ``--device``. Every timing waits for the
device (``torch.cuda.synchronize``) and takes the median of ``--repeats`` runs after a warm-up.

    python benchmarks/bench_fit_batch.py --device cuda --batch 1 16 64 [--model ict]
"""

from __future__ import annotations

import argparse
import platform
import statistics
import time

import torch

from facenormals.fitting import fit_head
from facenormals.fitting.oracle import render_oracle_views
from facenormals.models import load_model


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def timed(fn, device: torch.device, repeats: int) -> float:
    """Median wall time of ``fn()`` in seconds, after one warm-up call."""
    fn()
    times = []
    for _ in range(repeats):
        _sync(device)
        start = time.perf_counter()
        fn()
        _sync(device)
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--batch", type=int, nargs="+", default=[1, 16])
    parser.add_argument("--model", default="ict")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--threads", type=int, default=None, help="torch CPU threads")
    args = parser.parse_args()
    if args.device.startswith("cuda") and not torch.cuda.is_available():
        parser.error(f"--device {args.device}: this torch build ({torch.__version__}) has no CUDA device")
    if args.threads:
        torch.set_num_threads(args.threads)
    device = torch.device(args.device)
    model = load_model(args.model, dtype=torch.float32)
    name = torch.cuda.get_device_name(device) if device.type == "cuda" else platform.processor() or platform.machine()
    print(f"device: {device} ({name}), torch {torch.__version__}, {torch.get_num_threads()} CPU threads; "
          f"model {model.name}: {model.num_vertices} vertices, {model.num_shape} shape components")
    g = torch.Generator().manual_seed(0)
    largest = max(args.batch)
    heads = []
    for _ in range(largest):
        yaw = float((torch.rand(1, generator=g) * 2 - 1) * 30.0)
        heads.append(render_oracle_views(model, model.sample_shape_coeffs(1, generator=g), [yaw]))
    model.to(device)  # after rendering the oracle maps on the CPU (nn.Module.to moves in place)
    maps = torch.cat([h.normal_maps for h in heads]).to(device)
    lms = torch.cat([h.landmarks for h in heads]).to(device)
    K = torch.cat([h.intrinsics for h in heads]).to(device)

    def fit(lo: int, hi: int):
        return fit_head(maps[lo:hi], lms[lo:hi], model, intrinsics=K[lo:hi])

    # Every subject alone (median of its repeats), so that B subjects in a batch compare with the
    # same B subjects one after the other (subjects differ: 6 to 23 LM iterations).
    alone = [timed(lambda i=i: fit(i, i + 1), device, args.repeats) for i in range(largest)]
    sizes = sorted(set(args.batch))
    per_call = {b: timed(lambda b=b: fit(0, b), device, args.repeats) for b in sizes}
    print("\n| subjects per call | ms per call | ms per subject | throughput vs the same subjects one at a time |"
          "\n|---|---|---|---|")
    for b in sizes:
        t = per_call[b]
        print(f"| {b} | {t * 1e3:.1f} | {t / b * 1e3:.2f} | {sum(alone[:b]) / t:.2f}x |")
    if largest > 1:
        sequential = timed(lambda: [fit(i, i + 1) for i in range(largest)], device, 1)
        batched = timed(lambda: fit(0, largest), device, 1)
        print(f"\nB={largest}: one batch {batched * 1e3:.0f} ms vs {largest} sequential fits {sequential * 1e3:.0f} ms: "
              f"{sequential / batched:.2f}x throughput (timed back to back, one run each)")


if __name__ == "__main__":
    main()
