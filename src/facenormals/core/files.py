"""Atomic, durable file writes.

A file is written under a unique temporary name in its target's folder, flushed to disk and renamed
over the target. Readers, and a crash, Ctrl-C or a full disk midway, see the old file or the new
one, never a part of it; two writers of one target never share a temporary file.
"""

from __future__ import annotations

import os
import tempfile
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

__all__ = ["atomic_write", "publish", "temporary_beside"]

#: Suffix of the temporary files (before the target's own suffix, which some writers need).
PART = ".part"


def _current_umask() -> int:
    """The process umask. Reading it means setting it, which is not thread-safe (another thread's new
    file could get mode 0666 in between); where the kernel reports it, it is read from there."""
    try:
        with open("/proc/self/status") as status:
            for line in status:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except OSError:
        pass
    umask = os.umask(0)
    os.umask(umask)
    return umask


def temporary_beside(path: str | Path) -> Path:
    """Create an empty file with a unique name beside ``path`` (``.NAME.XXXX.part.SUFFIX``, hidden,
    ending in ``path``'s suffix so that writers choosing a format by extension still can).

    Example:
        >>> import tempfile
        >>> target = Path(tempfile.mkdtemp()) / "head.ply"
        >>> part = temporary_beside(target)
        >>> part.parent == target.parent, part.name.startswith(".head.ply."), part.name.endswith(".part.ply")
        (True, True, True)
    """
    path = Path(path)
    try:  # the name is cut so that a long target name still leaves room for the temporary one
        handle, name = tempfile.mkstemp(prefix=f".{path.name[:100]}.", suffix=PART + path.suffix, dir=path.parent)
    except OSError as error:
        raise type(error)(error.errno, error.strerror, str(path)) from None
    os.close(handle)
    return Path(name)


def publish(temporary: str | Path, path: str | Path, durable: bool = True) -> Path:
    """Rename the finished ``temporary`` over ``path`` atomically, with the permissions a new file
    gets under the current umask (``mkstemp`` creates it 0600).

    Args:
        temporary: a file in ``path``'s folder (see :func:`temporary_beside`).
        path: the target.
        durable: flush the file's data to disk before the rename and the folder entry after it, so
            that a machine that goes down right after this returns still holds the new file (else
            a crash may leave an empty or a missing one on some file systems).

    Returns:
        ``path``.
    """
    temporary, path = Path(temporary), Path(path)
    os.chmod(temporary, 0o666 & ~_current_umask())
    if durable:
        handle = os.open(temporary, os.O_RDWR)  # Windows flushes only handles open for writing
        try:
            os.fsync(handle)
        finally:
            os.close(handle)
    os.replace(temporary, path)
    if durable and hasattr(os, "O_DIRECTORY"):  # POSIX: make the rename itself durable
        try:
            folder = os.open(path.parent, os.O_RDONLY | os.O_DIRECTORY)
            try:
                os.fsync(folder)
            finally:
                os.close(folder)
        except OSError:  # some network and FUSE file systems cannot sync a folder; the file is in place
            pass
    return path


@contextmanager
def atomic_write(path: str | Path, durable: bool = True) -> Iterator[Path]:
    """Yield a temporary path to write ``path``'s content to; publish it over ``path`` when the block
    ends normally (:func:`publish`), delete it when the block raises (``path`` keeps its old content).

    Example:
        >>> import tempfile
        >>> target = Path(tempfile.mkdtemp()) / "log.csv"
        >>> with atomic_write(target) as part:
        ...     _ = part.write_text("step,loss\\n")
        >>> target.read_text()
        'step,loss\\n'
        >>> try:
        ...     with atomic_write(target) as part:
        ...         _ = part.write_text("half a")
        ...         raise KeyboardInterrupt
        ... except KeyboardInterrupt:
        ...     pass
        >>> target.read_text(), sorted(p.name for p in target.parent.iterdir())
        ('step,loss\\n', ['log.csv'])
    """
    temporary = temporary_beside(path)
    try:
        yield temporary
        publish(temporary, path, durable=durable)
    except OSError as error:
        temporary.unlink(missing_ok=True)
        if error.filename == str(temporary):  # name the file the caller asked for, not the temporary one
            raise type(error)(error.errno, error.strerror, str(path)) from None
        raise
    except BaseException:
        temporary.unlink(missing_ok=True)
        raise
