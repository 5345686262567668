"""Morphable models and their loaders."""

from facenormals.models.builtin import BUILTIN_PARAMETERS, builtin_head_model
from facenormals.models.fetch import fetch_ict, ict_release_differences
from facenormals.models.formats import load_bfm2009, load_bfm2017, load_flame, load_lyhm
from facenormals.models.ict import load_ict_npz, load_ict_raw
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
    "fetch_ict",
    "find_ict_archive",
    "ict_release_differences",
    "load_bfm2009",
    "load_bfm2017",
    "load_flame",
    "load_ict_npz",
    "load_ict_raw",
    "load_lyhm",
    "load_model",
]
