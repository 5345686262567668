"""Morphable models and their loaders."""

from facenormals.models.ict import load_ict_npz
from facenormals.models.morphable import ModelFileError, MorphableModel

__all__ = ["ModelFileError", "MorphableModel", "load_ict_npz"]
