"""Recover a random synthetic head from its exact normal map and landmarks (the synthetic demo, ``facenormals demo``).

    python examples/demo_synthetic_fit.py [--model auto|ict|builtin|PATH] [--seed 0] [--out out/demo]
"""

import argparse

from facenormals.demo import run_demo
from facenormals.models import load_model

parser = argparse.ArgumentParser(description=__doc__)
parser.add_argument("--model", default="auto")
parser.add_argument("--seed", type=int, default=0)
parser.add_argument("--out", default="out/demo")
args = parser.parse_args()

report = run_demo(load_model(args.model), seed=args.seed, out_dir=args.out)
print(report)
