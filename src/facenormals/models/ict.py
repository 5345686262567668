"""ICT-FaceKit, the MIT-licensed full-head model (face, head, neck and ears)."""

from __future__ import annotations

import zipfile
from pathlib import Path

import numpy as np
import torch

from facenormals.models.morphable import ModelFileError, MorphableModel

__all__ = ["load_ict_npz", "opengl_to_model_frame"]

ICT_KEYS = ("mean", "faces", "identity_basis", "expression_basis", "expression_names", "landmarks_ibug68")


def opengl_to_model_frame(points: np.ndarray, scale: float) -> np.ndarray:
    """Convert ``(..., 3)`` points from an OpenGL-style frame (+y up, +z out of the face) to the
    library's model frame (y down, face along −z) and multiply by ``scale`` (to mm)."""
    return points * np.array([scale, -scale, -scale], dtype=points.dtype)


def load_ict_npz(path: str | Path, num_shape: int = 100, dtype: torch.dtype = torch.float32) -> MorphableModel:
    """Load the converted ICT-FaceKit archive (``ict_face_head.npz``, see ``shared/data/README.md``).

    The archive is in centimetres in an OpenGL-style frame; the model is returned in millimetres in the
    library's model frame. Identity coefficients have unit variance (``shape_std = 1``). The 68 iBUG
    landmarks are attached as ``ibug_00`` ... ``ibug_67``.

    Args:
        path: the ``.npz`` file.
        num_shape: how many of the 100 identity components to keep.
        dtype: floating dtype of the model's buffers.

    Raises:
        ModelFileError: if the file is missing, corrupt or lacks the expected arrays.
    """
    path = Path(path)
    if not path.exists():
        raise ModelFileError(f"{path}: ICT-FaceKit archive not found")
    try:
        with np.load(path, allow_pickle=False) as data:
            missing = [k for k in ICT_KEYS if k not in data.files]
            if missing:
                raise ModelFileError(f"{path}: not an ICT-FaceKit archive, missing arrays {missing}")
            units = str(data["units"]) if "units" in data.files else "cm"
            arrays = {k: data[k] for k in ICT_KEYS}
    except ModelFileError:
        raise
    except (OSError, ValueError, zipfile.BadZipFile, EOFError) as error:
        raise ModelFileError(f"{path}: cannot read ICT-FaceKit archive ({type(error).__name__}: {error})") from error
    scale = {"cm": 10.0, "mm": 1.0, "m": 1000.0}.get(units)
    if scale is None:
        raise ModelFileError(f"{path}: unknown units {units!r}, expected 'cm', 'mm' or 'm'")
    if not 1 <= num_shape <= arrays["identity_basis"].shape[0]:
        raise ValueError(f"num_shape: expected 1..{arrays['identity_basis'].shape[0]}, got {num_shape}")
    landmarks = {f"ibug_{i:02d}": int(v) for i, v in enumerate(arrays["landmarks_ibug68"])}
    return MorphableModel(
        torch.from_numpy(opengl_to_model_frame(arrays["mean"], scale)).to(dtype),
        torch.from_numpy(opengl_to_model_frame(arrays["identity_basis"][:num_shape], scale)).to(dtype),
        torch.from_numpy(arrays["faces"].astype(np.int64)),
        expression_basis=torch.from_numpy(opengl_to_model_frame(arrays["expression_basis"], scale)).to(dtype),
        landmarks=landmarks,
        expression_names=[str(n) for n in arrays["expression_names"]],
        name="ict",
        metadata={"source": "ICT-FaceKit (USC ICT), face + head-and-neck regions", "license": "MIT",
                  "file": str(path)},
    )
