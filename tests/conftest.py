"""Shared fixtures: dtype and device parametrisation, dtype-aware tolerances."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

SHARED_DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
ICT_NPZ = SHARED_DATA / "ict_facekit" / "ict_face_head.npz"

DEVICES = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])


@pytest.fixture(params=DEVICES)
def device(request) -> torch.device:
    # an indexed device: tensors report "cuda:0", and torch.device("cuda") != torch.device("cuda:0")
    if request.param == "cuda":
        return torch.device("cuda", torch.cuda.current_device())
    return torch.device(request.param)


@pytest.fixture(params=[torch.float32, torch.float64], ids=["f32", "f64"])
def dtype(request) -> torch.dtype:
    return request.param


def tolerances(dtype: torch.dtype) -> dict[str, float]:
    """rtol/atol used by :func:`assert_close` for a dtype."""
    if dtype == torch.float64:
        return {"rtol": 1e-9, "atol": 1e-9}
    return {"rtol": 1e-4, "atol": 1e-5}


def assert_close(actual, expected, *, rtol: float | None = None, atol: float | None = None) -> None:
    """``torch.testing.assert_close`` with tolerances chosen from the dtype of ``actual``."""
    expected = torch.as_tensor(expected, dtype=actual.dtype, device=actual.device)
    tol = tolerances(actual.dtype)
    torch.testing.assert_close(
        actual,
        expected,
        rtol=tol["rtol"] if rtol is None else rtol,
        atol=tol["atol"] if atol is None else atol,
    )


@pytest.fixture
def ict_npz() -> Path:
    """Path to the shared ICT-FaceKit archive; skips where ../shared is absent."""
    if not ICT_NPZ.exists():
        pytest.skip(f"shared data not found at {ICT_NPZ}")
    return ICT_NPZ
