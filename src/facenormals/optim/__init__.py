"""Batched non-linear least-squares solvers."""

from facenormals.optim.lm import LMResult, LMStatus, levenberg_marquardt
from facenormals.optim.normal_equations import normal_equations

__all__ = ["LMResult", "LMStatus", "levenberg_marquardt", "normal_equations"]
