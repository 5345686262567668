"""``--threads`` for the benchmarks that compare with SciPy: torch's threads *and* the BLAS/OpenMP
pools, pinned before numpy, scipy and torch load (a helper module, not a benchmark)."""

from __future__ import annotations

import argparse
import os


def add_threads_argument(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--threads", type=int, default=None,
                        help="torch and BLAS threads (default: the libraries' choice)")


def pin_threads(args: argparse.Namespace) -> None:
    """Set the thread pools' sizes from ``args.threads``; call it before importing numpy, scipy or torch."""
    if args.threads:
        for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
            os.environ[var] = str(args.threads)
