"""Differentiable image sampling (OpenCV-compatible bicubic interpolation)."""

from facenormals.sampling.bicubic import BicubicSampler, sample_bicubic, sample_bicubic_with_gradient

__all__ = ["BicubicSampler", "sample_bicubic", "sample_bicubic_with_gradient"]
