"""Find and load a model by name: ``"ict"``, ``"builtin"`` or a path to a model file (a facenormals
``.npz``, LYHM or BFM 2009 ``.mat``, BFM 2017/2019 ``.h5``, FLAME ``.pkl``)."""

from __future__ import annotations

import os
import warnings
from pathlib import Path

import torch

from facenormals.core.check import MILLIMETRE_SPAN, outside_millimetre_span
from facenormals.models.builtin import builtin_head_model
from facenormals.models.ict import ICT_FULL_EXPRESSIONS, ICT_FULL_IDENTITIES, load_ict_npz, load_ict_raw
from facenormals.models.morphable import ModelFileError, MorphableModel, check_model_dtype

__all__ = ["cache_dir", "find_ict_archive", "load_model"]

ICT_ARCHIVE = "ict_face_head.npz"


def cache_dir() -> Path:
    """The cache folder: ``$FACENORMALS_HOME``, default ``~/.cache/facenormals``."""
    return Path(os.environ.get("FACENORMALS_HOME") or Path.home() / ".cache" / "facenormals")  # empty: unset


def find_ict_archive() -> Path | None:
    """The ICT-FaceKit archive, looked up in ``$FACENORMALS_ICT``, the cache and, for a source
    checkout, ``../shared/data`` beside the repository; ``None`` if absent. Not beside the working
    directory: the model a command uses must not depend on where it is run."""
    candidates = []
    if os.environ.get("FACENORMALS_ICT"):
        named = Path(os.environ["FACENORMALS_ICT"])
        if not named.is_file():
            what = ("a folder; it must name the converted archive (a repository is converted once with "
                    f"`facenormals models fetch ict --from {named}`)" if named.is_dir() else "a file that does not exist")
            raise ModelFileError(f"{named}: FACENORMALS_ICT names {what}; fix or unset it")
        candidates.append(named)
    candidates.append(cache_dir() / "ict" / ICT_ARCHIVE)
    repo_root = Path(__file__).resolve().parents[3]  # src/facenormals/models/registry.py in a checkout
    if (repo_root / "pyproject.toml").is_file() and (repo_root / "src" / "facenormals").is_dir():
        candidates.append(repo_root.parent / "shared" / "data" / "ict_facekit" / ICT_ARCHIVE)
    return next((c for c in candidates if c.is_file()), None)


def _load_path(path: Path, dtype: torch.dtype) -> MorphableModel:
    """Dispatch a model file to its loader by extension (and, for ``.mat``/``.npz``, by its keys)."""
    from facenormals.models import formats

    if path.is_dir() and any((folder / "generic_neutral_mesh.obj").is_file() for folder in (path, path / "FaceXModel")):
        return load_ict_raw(path, dtype=dtype)  # the FaceXModel folder or the repository's root
    if path.is_dir():
        raise ModelFileError(f"{path}: a folder, not a model file (an ICT-FaceKit repository folder holds "
                             "FaceXModel/generic_neutral_mesh.obj)")
    if not path.is_file():
        hint = "" if path.suffix or len(path.parts) > 1 else ' (model names: "ict", "builtin", "auto")'
        raise ModelFileError(f"{path}: model file not found{hint}")
    suffix = path.suffix.lower()
    if suffix == ".zip":
        raise ModelFileError(f"{path}: a repository archive is converted once with "
                             f"`facenormals models fetch ict --from {path}`; then use --model ict")
    if suffix == ".npz":
        import zipfile

        try:
            with zipfile.ZipFile(path) as archive:
                names = {n.removesuffix(".npy") for n in archive.namelist()}
        except (zipfile.BadZipFile, OSError) as error:
            raise ModelFileError(f"{path}: cannot read model file ({type(error).__name__}: {error})") from error
        if "identity_basis" in names and "format" not in names:
            return load_ict_npz(path, dtype=dtype)
        return MorphableModel.load(path, dtype=dtype)
    if suffix == ".mat":  # BFM 2009 or LYHM, told apart by their variables
        return formats._load_matlab_model(path, dtype=dtype)
    if suffix in (".h5", ".hdf5"):
        return formats.load_bfm2017(path, dtype=dtype)
    if suffix in (".pkl", ".pickle"):
        return formats.load_flame(path, dtype=dtype)
    raise ModelFileError(
        f"{path}: unknown model format {suffix!r}; expected .npz (facenormals or ICT archive), "
        ".mat (LYHM, BFM 2009), .h5 (BFM 2017) or .pkl (FLAME)"
    )


def load_model(spec: str | Path = "auto", dtype: torch.dtype = torch.float32) -> MorphableModel:
    """Load a model by name or path: bring your own model in one call.

    Args:
        spec: ``"ict"`` (fails if the archive is not found), ``"builtin"``, ``"auto"`` (ICT when found,
            otherwise built-in) or a path: a facenormals ``.npz`` (:meth:`MorphableModel.save`), the
            ICT-FaceKit archive, LYHM or BFM 2009 ``.mat``, BFM 2017 ``.h5`` or FLAME ``.pkl``.
        dtype: floating dtype of the model's buffers.

    Raises:
        ModelFileError: if ``"ict"`` is requested but not found, or the file cannot be read.
    """
    check_model_dtype(dtype)
    if not isinstance(spec, (str, Path)):
        raise ValueError(f"spec: expected a model name ('ict', 'builtin', 'auto') or a path, got {spec!r}")
    if isinstance(spec, Path):
        return _in_millimetres(_load_path(spec, dtype), spec)
    if spec in ("auto", "ict"):
        archive = find_ict_archive()
        if archive is not None:
            try:
                model = load_ict_npz(archive, dtype=dtype)
            except ModelFileError as error:
                remedy = ("`facenormals models fetch ict --force` rebuilds it" if archive == cache_dir() / "ict" / ICT_ARCHIVE
                          else "replace it, or name a good copy with $FACENORMALS_ICT")
                raise ModelFileError(f"{error}; {remedy}") from error
            if model.num_shape < ICT_FULL_IDENTITIES or model.num_expressions < ICT_FULL_EXPRESSIONS:  # a subset's
                warnings.warn(f"{archive}: a partial ICT-FaceKit ({model.num_shape} identity components and "
                              f"{model.num_expressions} expressions of {ICT_FULL_IDENTITIES} and "
                              f"{ICT_FULL_EXPRESSIONS}); replace it with "
                              "`facenormals models fetch ict --force`", stacklevel=2)
            return model
        if spec == "ict":
            raise ModelFileError(
                f"ICT-FaceKit not found (looked in $FACENORMALS_ICT, {cache_dir() / 'ict'} and shared/data); "
                "run `facenormals models fetch ict` or pass --model builtin"
            )
        return builtin_head_model(dtype=dtype)
    if spec == "builtin":
        return builtin_head_model(dtype=dtype)
    return _in_millimetres(_load_path(Path(spec), dtype), Path(spec))


def _in_millimetres(model: MorphableModel, path: Path) -> MorphableModel:
    """``model``, unless its mean is not head-sized in mm after its loader's unit conversion (e.g. a BFM
    file already converted to mm, divided again): a ``ModelFileError`` naming the file then."""
    span = outside_millimetre_span(model.mean)
    if span is not None:
        low, high = MILLIMETRE_SPAN
        raise ModelFileError(f"{path}: the loaded mean spans {span:.3g} mm across, not the {low:g}-{high:g} of a face "
                             "or head: the file is not in the units its format uses (docs/models.md)")
    return model
