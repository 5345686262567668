"""Shared infrastructure: input checks."""

from facenormals.core.check import (
    check_finite,
    check_floating,
    check_nonnegative,
    check_same_dims,
    check_shape,
    check_tensor,
)

__all__ = [
    "check_finite",
    "check_floating",
    "check_nonnegative",
    "check_same_dims",
    "check_shape",
    "check_tensor",
]
