"""Throughput of the synthetic data generator: samples per second, end to end, written to shards.

Runs ``write_dataset`` twice into fresh folders (``--small`` and ``--count`` samples) and reports the
steady-state rate ``(count - small) / (t_count - t_small)``, which cancels the start-up (spawning
workers, loading the model, creating OpenGL contexts), plus the raw end-to-end rate. Also times
the generator alone in this process (rendering + sampling, no files).

    python benchmarks/bench_synth.py                 # 2 workers, 1280 samples
    python benchmarks/bench_synth.py --workers 1 --count 640
"""

from __future__ import annotations

import argparse
import os
import platform
import shutil
import tempfile
import time

import torch


def _run(count: int, args, root: str) -> float:
    from facenormals.data import write_dataset

    path = os.path.join(root, f"ds_{count}")
    shutil.rmtree(path, ignore_errors=True)
    start = time.perf_counter()
    write_dataset(path, count, workers=args.workers, seed=args.seed, model_spec=args.model, shard_size=args.shard_size,
                  progress=False, render_threads=args.render_threads)
    seconds = time.perf_counter() - start
    size = sum(os.path.getsize(os.path.join(path, f)) for f in os.listdir(path))
    print(f"  write_dataset count={count}: {seconds:.1f} s ({count / seconds:.1f} samples/s end to end), "
          f"{size / count / 1024:.1f} KiB/sample on disk")
    shutil.rmtree(path, ignore_errors=True)
    return seconds


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--count", type=int, default=1280)
    parser.add_argument("--small", type=int, default=256)
    parser.add_argument("--shard-size", type=int, default=1000)
    parser.add_argument("--model", default="auto")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--render-threads", type=int, default=None, help="LP_NUM_THREADS in the workers")
    parser.add_argument("--skip-single", action="store_true", help="skip the in-process generator timing")
    args = parser.parse_args()
    print(f"machine: {platform.machine()}, {os.cpu_count()} CPUs, torch {torch.__version__}, "
          f"LP_NUM_THREADS={os.environ.get('LP_NUM_THREADS', 'default')}")

    if not args.skip_single:
        from facenormals.data import SyntheticHeadGenerator

        torch.set_num_threads(1)
        with SyntheticHeadGenerator(args.model) as generator:
            generator.generate(args.seed, range(64))  # warm-up: context, shaders, noise banks
            start = time.perf_counter()
            generator.generate(args.seed, range(64, 320))
            seconds = time.perf_counter() - start
            print(f"generator in this process ({generator.model.name}, 1 torch thread): "
                  f"{256 / seconds:.1f} samples/s ({seconds / 256 * 1e3:.1f} ms/sample)")

    root = tempfile.mkdtemp(prefix="bench_synth_")
    try:
        print(f"write_dataset with {args.workers} worker(s):")
        t_small = _run(args.small, args, root)
        t_count = _run(args.count, args, root)
        rate = (args.count - args.small) / max(t_count - t_small, 1e-9)
        print(f"steady state: {rate:.1f} samples/s with {args.workers} worker(s); start-up about "
              f"{max(t_small - args.small / rate, 0.0):.1f} s; 60,000 samples take about "
              f"{60000 / rate / 60 + max(t_small - args.small / rate, 0.0) / 60:.0f} min")
    finally:
        shutil.rmtree(root, ignore_errors=True)


if __name__ == "__main__":
    main()
