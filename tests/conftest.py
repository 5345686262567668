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


def ict_archive_or_skip() -> Path:
    """The ICT-FaceKit archive where the library finds it (``$FACENORMALS_ICT``, the cache, then
    ``../shared/data``, see :func:`facenormals.models.find_ict_archive`); skips where there is none."""
    from facenormals.models import find_ict_archive

    found = find_ict_archive()
    if found is None:
        pytest.skip(f"ICT-FaceKit not found ($FACENORMALS_ICT, the cache, or {ICT_NPZ})")
    return found


@pytest.fixture
def ict_npz() -> Path:
    """Path to the ICT-FaceKit archive (:func:`ict_archive_or_skip`)."""
    return ict_archive_or_skip()


def headless_gl_or_skip() -> None:
    """Skip the test where no headless OpenGL (EGL or OSMesa) is available."""
    from facenormals.data import HeadlessGLError, select_gl_platform

    try:
        select_gl_platform()
    except HeadlessGLError as error:
        pytest.skip(f"no headless OpenGL: {error}")


def damage_deflate_stream(path: Path, member: str) -> None:
    """Make ``member`` of the zip (or ``.npz``) ``path``, stored deflated, undecompressable: its first
    deflate block becomes one of the reserved type 3, so reading it raises ``zlib.error`` ("invalid
    block type"), not ``BadZipFile``."""
    import struct
    import zipfile

    with zipfile.ZipFile(path) as archive:
        info = archive.getinfo(member)
    assert info.compress_type == zipfile.ZIP_DEFLATED, f"{member} is not deflated"
    data = bytearray(path.read_bytes())
    name_length, extra_length = struct.unpack_from("<HH", data, info.header_offset + 26)  # the local header's
    data[info.header_offset + 30 + name_length + extra_length] = 0b111  # final block, reserved type 3
    path.write_bytes(bytes(data))
