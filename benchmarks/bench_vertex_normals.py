"""Vertex normals of the ICT head (11,248 vertices, 22,288 faces): function and module, per mesh.

Times :func:`facenormals.mesh.vertex_normals` and :class:`facenormals.mesh.VertexNormals` for
both modes at B=1 and B=32 in float32 (forward, and forward + backward), and prints a markdown
table of milliseconds per mesh: the median over the repeats after a warm-up, with the minimum in
brackets (the minimum is the better guide on a busy machine: with more torch threads than idle
cores, every parallel op can wait a scheduler tick for a descheduled thread). Targets: <= 3 ms per mesh at B=1
and <= 1 ms per mesh at B=32 (forward).

    python benchmarks/bench_vertex_normals.py [--threads 2] [--repeats 30] [--device cpu]
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import sys
import time

import numpy as np
import torch

from facenormals.mesh import VertexNormals, vertex_normals
from facenormals.models import find_ict_archive

TARGETS_MS = {1: 3.0, 32: 1.0}


def _time(fn, repeats: int, warmup: int, sync) -> list[float]:
    for _ in range(warmup):
        fn()
    sync()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        sync()
        times.append(time.perf_counter() - start)
    return times


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--threads", type=int, default=2, help="torch.set_num_threads (default 2)")
    parser.add_argument("--repeats", type=int, default=30)
    parser.add_argument("--warmup", type=int, default=5)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--batches", type=int, nargs="+", default=[1, 32])
    args = parser.parse_args()
    if args.device.startswith("cuda") and not torch.cuda.is_available():
        parser.error(f"--device {args.device}: this torch build ({torch.__version__}) has no CUDA device")

    ict = find_ict_archive()
    if ict is None:
        print("error: the ICT head is needed ($FACENORMALS_ICT, `facenormals models fetch ict`, or the shared "
              "data folder beside the repository)", file=sys.stderr)
        return 1
    torch.set_num_threads(args.threads)
    device = torch.device(args.device)
    sync = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)
    data = np.load(ict)
    mean = torch.from_numpy(np.ascontiguousarray(data["mean"], dtype=np.float32)).to(device)
    faces = torch.from_numpy(data["faces"].astype(np.int64)).to(device)

    print(f"machine: {platform.processor() or platform.machine()} ({platform.platform()}), "
          f"{os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.2f}, torch {torch.__version__}, "
          f"threads {torch.get_num_threads()}, device {device}")
    print(f"mesh: {mean.shape[0]} vertices, {faces.shape[0]} faces, float32; ms per mesh, "
          f"median (min) of {args.repeats} after {args.warmup} warm-up calls\n")
    print("| op | mode | B | forward | forward + backward | target (forward) |")
    print("|---|---|---|---|---|---|")
    missed = []
    for mode in ("ring", "area"):
        module = VertexNormals(faces, mean.shape[0], mode=mode).to(device)
        ops = {"vertex_normals": lambda v, mode=mode: vertex_normals(v, faces, mode), "VertexNormals": module}
        for name, op in ops.items():
            for b in args.batches:
                gen = torch.Generator().manual_seed(b)
                verts = (mean + 0.1 * torch.randn(b, *mean.shape, generator=gen).to(device)).contiguous()
                with torch.no_grad():
                    fwd = _time(lambda: op(verts), args.repeats, args.warmup, sync)
                leaf = verts.clone().requires_grad_(True)

                def step():
                    leaf.grad = None
                    op(leaf).sum().backward()

                both = _time(step, max(args.repeats // 3, 5), 2, sync)
                med, low = statistics.median(fwd) * 1e3 / b, min(fwd) * 1e3 / b
                target = TARGETS_MS.get(b)
                ok = "" if target is None else (f"<= {target:g} ok" if med <= target else f"<= {target:g} MISSED")
                if target is not None and med > target:
                    missed.append(f"{name} {mode} B={b}")
                print(f"| {name} | {mode} | {b} | {med:.3f} ({low:.3f}) | "
                      f"{statistics.median(both) * 1e3 / b:.3f} ({min(both) * 1e3 / b:.3f}) | {ok} |")
    if missed:
        print(f"\ntargets missed (median): {', '.join(missed)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
