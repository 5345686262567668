"""Fetch ICT-FaceKit into the cache: ``facenormals models fetch ict [--from DIR]``.

The public repository (https://github.com/ICT-VGL/ICT-FaceKit, MIT licence) is downloaded as a zip,
or read from a local copy, and its ``FaceXModel/`` folder is converted into
``cache_dir()/ict/ict_face_head.npz``, where :func:`facenormals.models.find_ict_archive` finds it.
"""

from __future__ import annotations

import hashlib
import http.client
import urllib.error
import urllib.request
import warnings
import zipfile
from pathlib import Path, PurePosixPath
from typing import Callable
from urllib.parse import urlparse

import numpy as np

from facenormals.core.files import atomic_write
from facenormals.models.ict import ICT_FULL_EXPRESSIONS, ICT_FULL_IDENTITIES, ICT_KEYS, ict_npz_from_raw
from facenormals.models.morphable import NPZ_READ_ERRORS, ModelFileError, read_npz
from facenormals.models.registry import ICT_ARCHIVE, cache_dir

__all__ = ["ICT_URL", "FetchError", "fetch_ict", "ict_release_differences"]

#: The zip of the repository's default branch, as GitHub serves it. A branch, not a pinned commit,
#: so the converted arrays are compared with :data:`ICT_RELEASE_SHA256` after every conversion.
ICT_URL = "https://github.com/ICT-VGL/ICT-FaceKit/archive/refs/heads/master.zip"

#: SHA-256 of the converted arrays (their bytes as written by ``ict_npz_from_raw``) of the release
#: facenormals was built and measured with: the landmark vertices, the network's training data and the
#: accuracy tables depend on it. The bases are compared only when complete (100 and 53 modes).
ICT_RELEASE_SHA256 = {
    "mean": "1d320cada1f95df4a519624edab4e8597e50545b084484264ceddd7711e25b40",
    "faces": "e0c4c47a7dd1954ff06e101f5b9c7ca7a392e9ec2f38e798d6cc1f0edf0ded6a",
    "landmarks_ibug68": "56af14add570e48821553b669f10d250490f84b594bab0937aed7b7e1bcec0f6",
    "identity_basis": "dc0de2b6bd03b82d3a61d82d4cfac04a2acf12c21c1578857d32129005d15bf4",
    "expression_basis": "89629e8b199f81d21866925c5a4ab2c3c4c6b309fc1ea681f9b6cee0a9660334",
}
_COMPLETE_MODES = {"identity_basis": ICT_FULL_IDENTITIES, "expression_basis": ICT_FULL_EXPRESSIONS}
FROM_HINT = "facenormals models fetch ict --from DIR"
_CHUNK = 1 << 20


class FetchError(ModelFileError, OSError):
    """Downloading a model failed (no network, HTTP error, interrupted transfer). Both a
    :class:`ModelFileError` and an :class:`OSError`; the message says how to fetch from a local copy."""


def _zip_name(url: str) -> str:
    stem = PurePosixPath(urlparse(url).path).name or "download.zip"
    return stem if stem.startswith("ICT-FaceKit") else f"ICT-FaceKit-{stem}"


def _download(url: str, target: Path, timeout: float, progress: Callable[[str], object] | None) -> None:
    """Stream ``url`` into ``target`` through a temporary file in the same folder (renamed at the end)."""
    target.parent.mkdir(parents=True, exist_ok=True)
    try:
        with atomic_write(target) as part:
            with open(part, "wb") as handle:
                request = urllib.request.Request(url, headers={"User-Agent": "facenormals"})
                with urllib.request.urlopen(request, timeout=timeout) as response:
                    total = int(response.headers.get("Content-Length") or 0)
                    done, reported = 0, -1
                    while True:
                        chunk = response.read(_CHUNK)
                        if not chunk:
                            break
                        handle.write(chunk)
                        done += len(chunk)
                        step = done * 10 // total if total else done // (50 * _CHUNK)
                        if progress is not None and step != reported:
                            reported = step
                            size = f"{done / 1e6:.0f} / {total / 1e6:.0f} MB" if total else f"{done / 1e6:.0f} MB"
                            progress(f"  {size}")
                    if total and done < total:
                        raise http.client.IncompleteRead(b"", total - done)
            if not zipfile.is_zipfile(part):  # cut short by a server that sent no length
                raise ValueError(f"the download ({done} bytes) is not a complete zip archive")
    except (OSError, http.client.HTTPException, ValueError) as error:  # the temporary file is gone
        reason = getattr(error, "reason", None) or error
        raise FetchError(
            f"could not download ICT-FaceKit from {url} ({type(error).__name__}: {reason}); "
            f"download it elsewhere (the repository zip or a clone of https://github.com/ICT-VGL/ICT-FaceKit) "
            f"and run `{FROM_HINT}`"
        ) from error


def ict_release_differences(archive: str | Path) -> list[str]:
    """The arrays of a converted ICT-FaceKit archive that differ from the release facenormals uses.

    Compares the SHA-256 of ``mean``, ``faces`` and ``landmarks_ibug68`` and, when complete, of the
    identity and expression bases with :data:`ICT_RELEASE_SHA256`. An empty list means the archive
    holds that release (or a partial copy of it).

    Example:
        >>> ict_release_differences("ict_face_head.npz")  # doctest: +SKIP
        []
    """
    differences = []
    try:  # members read whole and CRC-checked: a damaged copy is an error, not "another release"
        arrays = read_npz(archive, list(ICT_RELEASE_SHA256))
    except NPZ_READ_ERRORS as error:  # missing, not an archive, truncated, damaged, pickled arrays
        raise ModelFileError(f"{archive}: cannot read ICT-FaceKit archive ({type(error).__name__}: {error})") from error
    missing = [key for key in ICT_RELEASE_SHA256 if key not in arrays]
    if missing:
        raise ModelFileError(f"{archive}: not an ICT-FaceKit archive, missing arrays {missing}")
    for key, digest in ICT_RELEASE_SHA256.items():
        array = np.ascontiguousarray(arrays[key])
        if key in _COMPLETE_MODES and array.shape[0] != _COMPLETE_MODES[key]:
            continue
        if hashlib.sha256(array.tobytes()).hexdigest() != digest:
            differences.append(key)
    return differences


def _archive_problem(archive: Path) -> str | None:
    """Why a cached archive cannot be used (an unreadable zip directory, e.g. a truncated copy, or
    missing arrays), or ``None``; reads the zip's directory only."""
    try:
        with zipfile.ZipFile(archive) as data:
            names = {name.removesuffix(".npy") for name in data.namelist()}
    except (zipfile.BadZipFile, OSError) as error:
        return f"{type(error).__name__}: {error}"
    missing = [key for key in ICT_KEYS if key not in names]
    return f"missing arrays {missing}" if missing else None


def _report(archive: Path, progress: Callable[[str], object] | None) -> None:
    """Say what was written, and warn when it is not the release the package was made with."""
    differences = ict_release_differences(archive)
    if differences:
        warnings.warn(
            f"{archive}: this ICT-FaceKit differs from the release facenormals was built with "
            f"({', '.join(differences)} changed): its landmark vertices, the shipped network and the "
            f"documented accuracy may not hold for it",
            stacklevel=3,
        )
    if progress is None:
        return
    with np.load(archive, allow_pickle=False) as data:
        identities, expressions = data["identity_basis"].shape[0], data["expression_basis"].shape[0]
    partial = (identities, expressions) != (ICT_FULL_IDENTITIES, ICT_FULL_EXPRESSIONS)
    note = f" (partial copy: the full model has {ICT_FULL_IDENTITIES} and {ICT_FULL_EXPRESSIONS})" if partial else ""
    release = "a different release" if differences else "the release facenormals was built with"
    progress(f"wrote {archive}: {identities} identity modes, {expressions} expressions{note}; {release}")


def fetch_ict(
    source: str | Path | None = None,
    cache: Path | None = None,
    url: str = ICT_URL,
    progress: Callable[[str], object] | None = print,
    force: bool = False,
    timeout: float = 30.0,
) -> Path:
    """Put the converted ICT-FaceKit archive into the cache and return its path.

    The archive is ``<cache>/ict/ict_face_head.npz`` (the layout of :func:`ict_npz_from_raw`), where
    :func:`facenormals.models.find_ict_archive` looks. If it is already there it is returned at once.

    Args:
        source: a local copy to convert instead of downloading (``--from DIR``): the repository folder
            containing ``FaceXModel/``, the ``FaceXModel`` folder itself, a folder holding one extracted
            repository, or the repository's ``.zip``. A partial copy is converted as far as it goes
            (identity modes ``identity000...`` up to the first missing one, the expressions present).
        cache: the cache root; default :func:`facenormals.models.registry.cache_dir`
            (``$FACENORMALS_HOME``, else ``~/.cache/facenormals``).
        url: the repository zip downloaded when ``source`` is ``None``; the zip is kept in
            ``<cache>/ict/`` and reused by later calls.
        progress: called with one line of text per step; ``None`` for silence.
        force: rebuild the archive (and re-download the zip) even if cached.
        timeout: socket timeout of the download, seconds.

    Warns:
        UserWarning: if the converted arrays differ from the release facenormals was built with
            (:func:`ict_release_differences`): the upstream repository changed its model.

    Raises:
        FetchError: if the download fails (no network, HTTP error, ...); the message names ``--from``.
            It is both a :class:`ModelFileError` and an :class:`OSError`.
        ModelFileError: if the source does not exist (checked even when the archive is cached), or it
            or the downloaded zip is not a readable ICT-FaceKit copy.
    """
    say = progress if progress is not None else (lambda _message: None)
    folder = Path(cache if cache is not None else cache_dir()) / "ict"
    archive = folder / ICT_ARCHIVE
    if source is not None and not Path(source).exists():
        raise ModelFileError(f"{source}: no such file or folder (--from expects a local ICT-FaceKit copy)")
    if archive.is_file() and not force:
        problem = _archive_problem(archive)
        if problem is None:
            say(f"ICT-FaceKit is already in {archive}" + ("" if source is None else
                                                          f"; {source} was not converted (--force converts it)"))
            return archive
        say(f"{archive} is damaged ({problem}); converting it again")
    if source is not None:
        say(f"converting ICT-FaceKit from {source}")
        ict_npz_from_raw(source, archive)
        _report(archive, progress)
        return archive
    zip_path = folder / _zip_name(url)
    if force or not zip_path.is_file():
        say(f"downloading ICT-FaceKit from {url}")
        _download(url, zip_path, timeout, progress)
    else:
        say(f"using the downloaded {zip_path}")
    say(f"converting {zip_path}")
    try:
        ict_npz_from_raw(zip_path, archive)
    except ModelFileError as error:
        raise ModelFileError(
            f"{error}; delete {zip_path} (or pass force=True / --force) to download it again, "
            f"or run `{FROM_HINT}` with a local copy"
        ) from error
    _report(archive, progress)
    return archive
