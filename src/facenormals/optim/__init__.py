"""Batched non-linear least-squares solvers."""

from facenormals.optim.lm import LMResult, LMStatus, levenberg_marquardt

__all__ = ["LMResult", "LMStatus", "levenberg_marquardt"]
