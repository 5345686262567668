"""Model loading and forward-pass speed: ICT archive load, built-in head build, forward at B=1 and B=32.

    python benchmarks/bench_models.py
"""

from __future__ import annotations

import argparse
import platform
import statistics
import time

import torch

from facenormals.models import builtin_head_model, find_ict_archive, load_ict_npz
from facenormals.models.builtin import _build


def median_ms(fn, repeats: int = 20, warmup: int = 3) -> float:
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return statistics.median(times) * 1e3


def main() -> None:
    argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter).parse_args()
    print(f"machine: {platform.machine()}, torch {torch.__version__} ({torch.get_num_threads()} threads)")
    rows = []
    archive = find_ict_archive()
    models = {}
    if archive is not None:
        rows.append(("load ICT-FaceKit archive (load_ict_npz)", median_ms(lambda: load_ict_npz(archive), 5, 1), "<= 500"))
        models["ict"] = load_ict_npz(archive)
    else:
        print("ICT-FaceKit not found: skipping its rows")

    def build():
        _build.cache_clear()
        return builtin_head_model()

    rows.append(("build the built-in head (uncached)", median_ms(build, 5, 1), ""))
    models["builtin"] = builtin_head_model()
    for name, model in models.items():
        for batch in (1, 32):
            y = torch.randn(batch, model.num_shape)
            ms = median_ms(lambda: model(y))
            rows.append((f"{name} forward, B={batch} (float32)", ms, "<= 10" if batch == 32 else ""))
    print("\n| operation | median ms | target ms |\n|---|---|---|")
    for name, ms, target in rows:
        print(f"| {name} | {ms:.2f} | {target} |")


if __name__ == "__main__":
    main()
