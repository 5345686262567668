"""Morphable models and their loaders."""

from facenormals.models.builtin import BUILTIN_PARAMETERS, builtin_head_model
from facenormals.models.ict import load_ict_npz
from facenormals.models.landmarks import LANDMARK_NAMES, LANDMARK_PAIRS
from facenormals.models.morphable import ModelFileError, MorphableModel
from facenormals.models.registry import find_ict_archive, load_model

__all__ = [
    "BUILTIN_PARAMETERS",
    "LANDMARK_NAMES",
    "LANDMARK_PAIRS",
    "ModelFileError",
    "MorphableModel",
    "builtin_head_model",
    "find_ict_archive",
    "load_ict_npz",
    "load_model",
]
