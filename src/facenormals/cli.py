"""The ``facenormals`` command line."""

from __future__ import annotations

import argparse
import sys
from typing import Sequence

__all__ = ["main"]


def _cmd_demo(args: argparse.Namespace) -> int:
    import torch

    from facenormals.demo import run_demo
    from facenormals.models import load_model

    torch.set_num_threads(max(1, torch.get_num_threads()))
    model = load_model(args.model)
    if model.name == "builtin" and args.model == "auto":
        print("ICT-FaceKit not found: using the built-in procedural head (see docs/installation.md)")
    report = run_demo(model, seed=args.seed, out_dir=args.out)
    print()
    print(f"model                           {report.model}")
    print(f"visible-vertex RMSE, mean head  {report.mean_head_rmse_mm:7.2f} mm")
    print(f"visible-vertex RMSE, fitted     {report.fitted_rmse_mm:7.2f} mm")
    print(f"landmark error                  {report.landmark_error_px:7.2f} px")
    print(f"normal error (visible)          {report.normal_error_deg:7.2f} deg")
    print(f"yaw error                       {report.yaw_error_deg:7.2f} deg")
    print(f"time                            {report.seconds:7.1f} s")
    if report.mesh_path is not None:
        print(f"wrote {report.mesh_path}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="facenormals", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)
    demo = sub.add_parser("demo", help="recover a random synthetic head from its normal map and landmarks")
    demo.add_argument("--model", default="auto", help="ict, builtin, auto (default) or a model .npz path")
    demo.add_argument("--seed", type=int, default=0)
    demo.add_argument("--out", default="out/demo", help="output folder for demo_fit.ply")
    demo.set_defaults(func=_cmd_demo)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args))
    except (ValueError, OSError) as error:
        print(f"facenormals {args.command}: error: {error}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    raise SystemExit(main())
