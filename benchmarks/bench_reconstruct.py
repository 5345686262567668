"""Speed of the product path on CPU: U-Net inference and `facenormals reconstruct` end to end.

1. U-Net inference on one 128x128 image (batch 1), eval mode, median over repeats; also the
   mirror-averaged prediction that ``reconstruct`` uses (image + mirror, one batch of 2);
2. the whole reconstruction of the bundled example photo as ``facenormals reconstruct`` runs it
   (``reconstruct_photos``: read, detect, crop, the network on every detected face it needs,
   landmark decoding, pre-alignment, fit, writing every output file), not counting loading the
   model and the weights (``timings["load"]``), median over repeats.

    python benchmarks/bench_reconstruct.py [--repeats 7] [--model ict]
"""

from __future__ import annotations

import argparse
import platform
import statistics
import tempfile
import time
from pathlib import Path

import torch

from facenormals.models import load_model
from facenormals.nn import load_weights, mirror_averaged
from facenormals.reconstruct import reconstruct_photos

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "data" / "astronaut.jpg"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--model", default="ict")
    parser.add_argument("--image", default=str(EXAMPLE))
    args = parser.parse_args()
    print(f"machine: {platform.machine()} {platform.processor()}, torch {torch.__version__}, "
          f"{torch.get_num_threads()} threads")
    net = load_weights()
    model = load_model(args.model, dtype=torch.float32)

    x = torch.rand(1, 3, 128, 128)
    with torch.no_grad():
        for _ in range(5):
            net(x)
        times = []
        for _ in range(max(30, args.repeats)):
            t = time.perf_counter()
            net(x)
            times.append(time.perf_counter() - t)
    print(f"U-Net inference, 1 image 128x128: median {statistics.median(times) * 1e3:.1f} ms "
          f"(min {min(times) * 1e3:.1f}), target <= 30 ms")
    with torch.no_grad():
        times = []
        for _ in range(max(30, args.repeats)):
            t = time.perf_counter()
            mirror_averaged(net, x)
            times.append(time.perf_counter() - t)
    print(f"mirror-averaged inference (what reconstruct runs: the image and its mirror as one batch of 2): "
          f"median {statistics.median(times) * 1e3:.1f} ms (min {min(times) * 1e3:.1f}), "
          f"{statistics.median(times) / 2 * 1e3:.1f} ms per 128x128 image, target <= 30 ms per image")

    def once(out: str) -> dict[str, float]:
        timings = reconstruct_photos([args.image], out, model=model, log=lambda message: None).timings
        total = timings["total"] - timings["load"]
        glue = timings["reconstruct"] - timings["network"] - timings["fit"]  # dropping hidden detections, fit inputs
        return {"read+detect": timings["read_and_detect"], "network": timings["network"], "drop+glue": glue,
                "fit": timings["fit"], "write": total - timings["read_and_detect"] - timings["reconstruct"],
                "total": total}

    with tempfile.TemporaryDirectory() as out:
        once(out)  # warm-up
        runs = [once(out) for _ in range(args.repeats)]
    parts = {k: statistics.median(r[k] for r in runs) for k in runs[0]}
    print(f"reconstruct {Path(args.image).name} ({model.name}), median of {args.repeats}: "
          + ", ".join(f"{k} {v * 1e3:.0f} ms" for k, v in parts.items()) + "; target total <= 1000 ms")


if __name__ == "__main__":
    main()
