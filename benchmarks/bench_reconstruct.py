"""Speed of the product path on CPU: U-Net inference and `facenormals reconstruct` end to end.

1. U-Net inference on one 128x128 image (batch 1), eval mode, median over repeats; also the
   mirror-averaged prediction that ``reconstruct`` uses (image + mirror, one batch of 2);
2. the whole reconstruction of the bundled example photo (read, detect, crop, network, landmark
   decoding, pre-alignment, fit, writing every output file), not counting loading the model and
   the weights, median over repeats.

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
from facenormals.reconstruct import prepare_view, reconstruct_views, write_reconstruction
from facenormals.reconstruct.pipeline import Reconstruction

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
          f"median {statistics.median(times) * 1e3:.1f} ms (min {min(times) * 1e3:.1f}), target <= 30 ms")

    def once(out: str) -> dict[str, float]:
        t0 = time.perf_counter()
        view = prepare_view(args.image)
        t1 = time.perf_counter()
        crops = torch.from_numpy(view.crop).permute(2, 0, 1)[None].float() / 255.0
        maps, fit = reconstruct_views(crops, net, model)
        t2 = time.perf_counter()
        write_reconstruction(Reconstruction([view], maps, fit, model), out)
        t3 = time.perf_counter()
        return {"read+detect": t1 - t0, "network": maps.seconds, "fit": fit.timings.get("total_s", float("nan")),
                "write": t3 - t2, "total": t3 - t0}

    with tempfile.TemporaryDirectory() as out:
        once(out)  # warm-up
        runs = [once(out) for _ in range(args.repeats)]
    parts = {k: statistics.median(r[k] for r in runs) for k in runs[0]}
    print(f"reconstruct {Path(args.image).name} ({model.name}), median of {args.repeats}: "
          + ", ".join(f"{k} {v * 1e3:.0f} ms" for k, v in parts.items()) + "; target total <= 1000 ms")


if __name__ == "__main__":
    main()
