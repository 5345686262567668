"""Differentiable image sampling (OpenCV-compatible bicubic interpolation)."""

from facenormals.sampling.bicubic import sample_bicubic, sample_bicubic_with_gradient

__all__ = ["sample_bicubic", "sample_bicubic_with_gradient"]
