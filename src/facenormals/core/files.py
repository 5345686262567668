"""Atomic, durable file writes.

A file is written under a unique temporary name in its target's folder, flushed to disk and renamed
over the target. Readers, and a crash, Ctrl-C or a full disk midway, see the old file or the new
one, never a part of it; two writers of one target never share a temporary file.
"""

from __future__ import annotations

import errno
import os
import tempfile
from contextlib import contextmanager
from pathlib import Path
from typing import Callable, Iterator, Sequence

try:
    import fcntl
except ImportError:  # Windows: no advisory locks, see hold_locks
    fcntl = None

__all__ = ["FolderInUseError", "StagedFiles", "atomic_write", "hold_locks", "publish", "publish_together",
           "temporary_beside"]

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
    _finish(temporary, _current_umask(), durable)
    os.replace(temporary, path)
    if durable:
        _sync_folder(path.parent)
    return path


def _finish(temporary: Path, umask: int, durable: bool) -> None:
    """If ``durable``, flush ``temporary``'s data to disk; then give it a new file's permissions (in
    this order: a umask without the owner's write bit would forbid the flush's opening for writing)."""
    if durable:
        handle = os.open(temporary, os.O_RDWR)  # Windows flushes only handles open for writing
        try:
            os.fsync(handle)
        finally:
            os.close(handle)
    os.chmod(temporary, 0o666 & ~umask)


def _sync_folder(folder: Path) -> None:
    """POSIX: make the renames in ``folder`` durable."""
    if not hasattr(os, "O_DIRECTORY"):
        return
    try:
        handle = os.open(folder, os.O_RDONLY | os.O_DIRECTORY)
        try:
            os.fsync(handle)
        finally:
            os.close(handle)
    except OSError:  # some network and FUSE file systems cannot sync a folder; the files are in place
        pass


def publish_together(pairs: list[tuple[Path | None, Path]], durable: bool = True) -> list[Path]:
    """Rename finished temporaries over their targets, and remove targets, all together or not at all.

    Every temporary is flushed to disk first (where a full disk or an I/O error usually shows); then
    each existing target is moved to a backup name and its temporary renamed into place. An error or
    Ctrl-C during the renames puts back every target already replaced or removed (and removes those
    that are new), so the folder keeps its old set of files, never a mix of old and new ones.

    Args:
        pairs: ``(temporary, target)`` pairs, each temporary in its target's folder
            (:func:`temporary_beside`); a temporary ``None`` removes its target (if it exists).
        durable: as :func:`publish`.

    Returns:
        The targets.

    Example:
        >>> import tempfile
        >>> folder = Path(tempfile.mkdtemp())
        >>> _ = (folder / "a.txt").write_text("old a")
        >>> pairs = [(temporary_beside(folder / n), folder / n) for n in ("a.txt", "b.txt")]
        >>> for part, target in pairs:
        ...     _ = part.write_text("new " + target.stem)
        >>> [p.name for p in publish_together(pairs)], (folder / "a.txt").read_text()
        (['a.txt', 'b.txt'], 'new a')
    """
    pairs = [(None if t is None else Path(t), Path(p)) for t, p in pairs]
    targets = [os.path.abspath(p) for _, p in pairs]
    if len(set(targets)) != len(targets):  # which of two entries would win would depend on their order
        twice = next(t for t in targets if targets.count(t) > 1)
        raise ValueError(f"pairs: {twice} is named twice; expected each target once")
    umask = _current_umask()
    for temporary, _ in pairs:
        if temporary is not None:
            _finish(temporary, umask, durable)
    done: list[tuple[Path, Path | None]] = []  # (target, its backup or None for a new file)
    try:
        for temporary, path in pairs:
            backup = None
            if os.path.lexists(path):  # a symbolic link too, even a broken one: it is put back as it was
                backup = temporary_beside(path)
                try:
                    os.replace(path, backup)
                except BaseException:  # e.g. Ctrl-C, which may arrive after the rename
                    if os.path.lexists(path):
                        backup.unlink(missing_ok=True)
                    else:
                        os.replace(backup, path)
                    raise
            done.append((path, backup))
            if temporary is not None:
                os.replace(temporary, path)
    except BaseException:
        for path, backup in reversed(done):
            if backup is not None:
                os.replace(backup, path)
            else:
                path.unlink(missing_ok=True)
        raise
    for _, backup in done:
        if backup is not None:
            backup.unlink(missing_ok=True)
    if durable:
        for folder in dict.fromkeys(path.parent for _, path in pairs):
            _sync_folder(folder)
    return [path for temporary, path in pairs if temporary is not None]


class StagedFiles:
    """Files written under unique temporary names in their folders, renamed into place together by
    :meth:`commit` (:func:`publish_together`): a failure before or during it (an error, a full disk,
    Ctrl-C) leaves every earlier file as it was, and two runs into one folder never rename each
    other's half-written files. Call :meth:`discard` when done (e.g. in ``finally``): it removes the
    temporaries of files not committed.

    Example:
        >>> import tempfile
        >>> folder = Path(tempfile.mkdtemp())
        >>> staged = StagedFiles()
        >>> try:
        ...     _ = staged.write(folder / "a.txt", lambda part: part.write_text("a"))
        ...     _ = staged.write(folder / "b.txt", lambda part: part.write_text("b"))
        ...     [p.name for p in staged.commit()]
        ... finally:
        ...     staged.discard()
        ['a.txt', 'b.txt']
    """

    def __init__(self) -> None:
        self.files: list[tuple[Path | None, Path]] = []

    def write(self, path: Path, write: Callable[[Path], object]) -> Path:
        """Call ``write(temporary)`` for ``path``'s content; ``path`` is published by :meth:`commit`."""
        if path.is_dir():  # found now, not when renaming after other files were replaced
            raise OSError(f"{path}: is a folder, cannot write the file there")
        part = temporary_beside(path)
        self.files.append((part, path))
        write(part)
        return path

    def remove(self, path: Path) -> None:
        """Remove the file ``path`` (if it exists) in :meth:`commit`, together with publishing the
        written files; a folder is refused (found now, not when the commit renames it)."""
        if path.is_dir() and not path.is_symlink():
            raise OSError(f"{path}: is a folder, not a file to remove")
        self.files.append((None, path))

    def commit(self) -> list[Path]:
        """Publish every written file and make every removal, all together or none
        (:func:`publish_together`); returns the written files."""
        done = publish_together(self.files)
        self.files = []
        return done

    def discard(self) -> None:
        """Remove the temporaries of the files not committed."""
        for tmp, _ in self.files:
            if tmp is not None:
                tmp.unlink(missing_ok=True)
        self.files = []


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


class FolderInUseError(ValueError):
    """Another process holds a lock of :func:`hold_locks` (it is writing the same files)."""


@contextmanager
def hold_locks(path: str | Path, slots: Sequence[int], what: str) -> Iterator[None]:
    """Hold exclusive advisory locks on ``slots`` (byte ``k`` of the file ``path`` for slot ``k``) for
    the duration of the block, or raise :class:`FolderInUseError` naming ``what`` where another
    process holds one: two writers of the same files (a run started twice, a second ``synth`` into
    a folder) would otherwise delete each other's temporaries or interleave their logs.

    The locks are POSIX record locks: the system releases them when the process ends, however it
    ends, so a killed run leaves none behind (the small lock file stays). Processes on other
    machines see them where the file system supports them (NFS with its lock daemon). Without
    ``fcntl`` (Windows) nothing is locked. Record locks belong to the process: a second
    ``hold_locks`` on the same file in the same process does not conflict, and its end releases the
    first's locks too; each writer here takes one file for the whole of its work.

    Example:
        >>> import tempfile
        >>> lock = Path(tempfile.mkdtemp()) / ".synth.lock"
        >>> with hold_locks(lock, [0, 3], "shards 0 and 3"):
        ...     pass
    """
    slots = list(slots)
    if fcntl is None or not slots:
        yield
        return
    handle = os.open(path, os.O_RDWR | os.O_CREAT, 0o666)
    try:
        for slot in slots:
            try:
                fcntl.lockf(handle, fcntl.LOCK_EX | fcntl.LOCK_NB, 1, slot)
            except OSError as error:  # EACCES or EAGAIN: held by another process
                if error.errno not in (errno.EACCES, errno.EAGAIN):
                    raise
                raise FolderInUseError(f"{what}: another process is writing it (it holds the lock {path}); wait "
                                       "for that run to end, or choose another folder") from None
        yield
    finally:
        os.close(handle)  # releases every lock this process holds on the file
