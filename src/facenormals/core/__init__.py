"""Shared infrastructure: input checks and atomic file writes."""

from facenormals.core.check import (
    check_finite,
    check_floating,
    check_nonnegative,
    check_same_dims,
    check_shape,
    check_tensor,
)
from facenormals.core.files import atomic_write

__all__ = [
    "atomic_write",
    "check_finite",
    "check_floating",
    "check_nonnegative",
    "check_same_dims",
    "check_shape",
    "check_tensor",
]
