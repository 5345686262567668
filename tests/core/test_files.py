"""Atomic, durable writes: the target holds the old or the new content, never a part."""

import os
import stat

import pytest

from facenormals.core.files import PART, atomic_write, publish, publish_together, temporary_beside


def test_atomic_write_publishes_and_leaves_no_temporary(tmp_path):
    target = tmp_path / "table.csv"
    with atomic_write(target) as part:
        assert part.parent == tmp_path and part != target and part.name.endswith(PART + ".csv")
        part.write_text("a,b\n")
        assert not target.exists()  # nothing visible before the block ends
    assert target.read_text() == "a,b\n"
    assert [p.name for p in tmp_path.iterdir()] == ["table.csv"]


@pytest.mark.parametrize("error", [OSError("disk full"), KeyboardInterrupt()])
def test_a_failed_write_keeps_the_old_file(tmp_path, error):
    target = tmp_path / "last.pt"
    target.write_bytes(b"old checkpoint")
    with pytest.raises(type(error)):
        with atomic_write(target) as part:
            part.write_bytes(b"half of a new one")
            raise error
    assert target.read_bytes() == b"old checkpoint"
    assert [p.name for p in tmp_path.iterdir()] == ["last.pt"]


def test_temporaries_are_unique_and_hidden(tmp_path):
    names = {temporary_beside(tmp_path / "shard_00000.npz").name for _ in range(20)}
    assert len(names) == 20
    assert all(n.startswith(".shard_00000.npz.") and n.endswith(".part.npz") for n in names)


def test_published_files_get_umask_permissions_and_are_flushed(tmp_path, monkeypatch):
    synced = []
    real_fsync = os.fsync
    monkeypatch.setattr(os, "fsync", lambda fd: (synced.append(fd), real_fsync(fd)))
    umask = os.umask(0o027)
    try:
        part = temporary_beside(tmp_path / "w.pt")
        assert stat.S_IMODE(part.stat().st_mode) == 0o600  # as mkstemp creates it
        part.write_bytes(b"x")
        publish(part, tmp_path / "w.pt")
    finally:
        os.umask(umask)
    assert stat.S_IMODE((tmp_path / "w.pt").stat().st_mode) == 0o640
    assert len(synced) == (2 if hasattr(os, "O_DIRECTORY") else 1)  # the file, then its folder entry
    synced.clear()
    part = temporary_beside(tmp_path / "v.pt")
    publish(part, tmp_path / "v.pt", durable=False)
    assert synced == [] and (tmp_path / "v.pt").exists()


def test_errors_name_the_target_and_long_names_fit(tmp_path):
    with pytest.raises(FileNotFoundError) as caught:
        with atomic_write(tmp_path / "missing" / "model.npz") as part:
            part.write_text("x")
    assert caught.value.filename == str(tmp_path / "missing" / "model.npz")
    with pytest.raises(IsADirectoryError) as caught:
        with atomic_write(tmp_path / "model.npz") as part:
            open(part.parent, "w")  # an OSError about another file keeps its own name
    assert caught.value.filename == str(tmp_path)
    long = tmp_path / ("a" * 240 + ".ply")
    with atomic_write(long) as part:
        part.write_text("ply")
    assert long.read_text() == "ply"


def _staged(folder, names):
    pairs = [(temporary_beside(folder / n), folder / n) for n in names]
    for part, target in pairs:
        part.write_text("new " + target.name)
    return pairs


@pytest.mark.parametrize("after", [False, True])
@pytest.mark.parametrize("fail_at", [1, 2, 3, 4, 5])
@pytest.mark.parametrize("error", [OSError("EIO"), KeyboardInterrupt()])
def test_publish_together_is_all_or_nothing(tmp_path, monkeypatch, fail_at, error, after):
    """Published one by one, an error or Ctrl-C at the k-th file left the first k-1 new and the rest
    old (seen: head.ply of an ICT fit beside params.json of a built-in one)."""
    (tmp_path / "a.txt").write_text("old a")
    (tmp_path / "b.txt").write_text("old b")
    pairs = _staged(tmp_path, ["a.txt", "b.txt", "c.txt"])  # c is new
    calls = []
    real = os.replace

    def failing(src, dst):  # ``after``: Ctrl-C arriving once the rename is done (an old file's backup was deleted)
        calls.append(1)
        if len(calls) == fail_at:
            if after:
                real(src, dst)
            raise error
        return real(src, dst)

    monkeypatch.setattr(os, "replace", failing)
    with pytest.raises(type(error)):
        publish_together(pairs)
    monkeypatch.setattr(os, "replace", real)
    assert (tmp_path / "a.txt").read_text() == "old a" and (tmp_path / "b.txt").read_text() == "old b"
    assert not (tmp_path / "c.txt").exists()
    # what is left besides a and b: unpublished temporaries (the caller deletes them), no backup of an old file
    left = [p for p in tmp_path.iterdir() if p.name not in ("a.txt", "b.txt")]
    assert all(p.name.startswith(".") and p.read_text().startswith("new ") for p in left)


def test_publish_together_replaces_every_file_and_leaves_no_backup(tmp_path):
    (tmp_path / "a.txt").write_text("old a")
    assert publish_together(_staged(tmp_path, ["a.txt", "b.txt"])) == [tmp_path / "a.txt", tmp_path / "b.txt"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.txt", "b.txt"]
    assert (tmp_path / "a.txt").read_text() == "new a.txt" and (tmp_path / "b.txt").read_text() == "new b.txt"


def test_a_published_file_is_flushed_before_it_loses_its_write_permission(tmp_path, monkeypatch):
    """Under a umask without the owner's write bit, chmod came first and the flush's opening for
    writing then failed (for users other than root)."""
    order = []
    real_chmod, real_open = os.chmod, os.open
    monkeypatch.setattr(os, "chmod", lambda *a, **k: (order.append("chmod"), real_chmod(*a, **k))[1])
    monkeypatch.setattr(os, "open", lambda path, flags, *a: (order.append("open" if flags & os.O_RDWR else "other"),
                                                            real_open(path, flags, *a))[1])
    part = temporary_beside(tmp_path / "r.json")
    publish(part, tmp_path / "r.json")
    assert order.index("open") < order.index("chmod")


_HOLDER = """
import sys, time
from facenormals.core.files import hold_locks
with hold_locks(sys.argv[1], [int(s) for s in sys.argv[2:]], "held"):
    print("held", flush=True)
    time.sleep(60)
"""


@pytest.mark.skipif(os.name != "posix", reason="advisory locks are POSIX")
def test_locks_held_by_another_process_are_refused_until_it_dies(tmp_path):
    import signal
    import subprocess
    import sys

    from facenormals.core.files import FolderInUseError, hold_locks

    lock = tmp_path / ".synth.lock"
    holder = subprocess.Popen([sys.executable, "-c", _HOLDER, str(lock), "1", "3"], stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        with hold_locks(lock, [0, 2, 4], "other slots"):  # other bytes of the same file: no conflict
            pass
        for slots in ([3], [0, 1]):
            with pytest.raises(FolderInUseError, match=rf"shards: another process is writing it \(it holds the lock "
                                                       rf"{lock}\)"):
                with hold_locks(lock, slots, "shards"):
                    pytest.fail("entered a held lock")
    finally:
        holder.send_signal(signal.SIGKILL)  # as a killed run: the system releases its locks
        holder.wait()
    with hold_locks(lock, [1, 3], "shards"):
        pass


def test_publish_together_refuses_a_target_named_twice_and_staged_removal_of_a_folder(tmp_path):
    """Written and removed in one call, a file ended up removed but was reported as written (and the
    other order kept it): the order of the entries decided. A folder to remove failed the commit
    with an error naming its backup."""
    from facenormals.core.files import StagedFiles, publish_together, temporary_beside

    target = tmp_path / "a.txt"
    part = temporary_beside(target)
    part.write_text("new")
    with pytest.raises(ValueError, match=r"pairs: .*a.txt is named twice"):
        publish_together([(part, target), (None, tmp_path / "." / "a.txt")])
    assert not target.exists() and part.exists()
    (tmp_path / "folder").mkdir()
    with pytest.raises(OSError, match=r"folder: is a folder, not a file to remove"):
        StagedFiles().remove(tmp_path / "folder")
