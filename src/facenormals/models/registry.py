"""Find and load a model by name: ``"ict"``, ``"builtin"`` or a path to a facenormals ``.npz``."""

from __future__ import annotations

import os
from pathlib import Path

import torch

from facenormals.models.builtin import builtin_head_model
from facenormals.models.ict import load_ict_npz
from facenormals.models.morphable import ModelFileError, MorphableModel

__all__ = ["cache_dir", "find_ict_archive", "load_model"]

ICT_ARCHIVE = "ict_face_head.npz"


def cache_dir() -> Path:
    """The cache folder: ``$FACENORMALS_HOME``, default ``~/.cache/facenormals``."""
    return Path(os.environ.get("FACENORMALS_HOME", Path.home() / ".cache" / "facenormals"))


def find_ict_archive() -> Path | None:
    """The ICT-FaceKit archive, looked up in ``$FACENORMALS_ICT``, the cache and ``shared/data``
    beside the working directory or the repository; ``None`` if absent."""
    candidates = []
    if os.environ.get("FACENORMALS_ICT"):
        candidates.append(Path(os.environ["FACENORMALS_ICT"]))
    candidates.append(cache_dir() / "ict" / ICT_ARCHIVE)
    repo_root = Path(__file__).resolve().parents[3]
    for base in (Path.cwd(), repo_root):
        candidates.append(base.parent / "shared" / "data" / "ict_facekit" / ICT_ARCHIVE)
        candidates.append(base / "shared" / "data" / "ict_facekit" / ICT_ARCHIVE)
    return next((c for c in candidates if c.is_file()), None)


def load_model(spec: str = "auto", dtype: torch.dtype = torch.float32) -> MorphableModel:
    """Load a model by name or path.

    Args:
        spec: ``"ict"`` (fails if the archive is not found), ``"builtin"``, ``"auto"`` (ICT when found,
            otherwise built-in) or a path to a model saved with :meth:`MorphableModel.save`.
        dtype: floating dtype of the model's buffers.

    Raises:
        ModelFileError: if ``"ict"`` is requested but not found, or the file cannot be read.
    """
    if spec in ("auto", "ict"):
        archive = find_ict_archive()
        if archive is not None:
            return load_ict_npz(archive, dtype=dtype)
        if spec == "ict":
            raise ModelFileError(
                f"ICT-FaceKit not found (looked in $FACENORMALS_ICT, {cache_dir() / 'ict'} and shared/data); "
                "run `facenormals models fetch ict` or pass --model builtin"
            )
        return builtin_head_model(dtype=dtype)
    if spec == "builtin":
        return builtin_head_model(dtype=dtype)
    return MorphableModel.load(spec, dtype=dtype)
