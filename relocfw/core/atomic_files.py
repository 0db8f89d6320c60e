"""Files written all or nothing: a temporary beside the target, renamed over it.

A run killed mid-write leaves the previous file intact, never a truncated one.
Checkpoints and model files (relocfw.model.checkpoints), results, tables and
figures are all written through here.

Folders of files are written the same way: into a staging folder beside their place
(`staging_folder`, locked while written) and renamed into place when complete
(`publish_folder`); `remove_stale_folders` clears the ones killed writers left.
Writers that publish in turn hold `file_lock` on a lock file beside their target.

Several runs may share one cache folder. A writer holds an exclusive advisory lock
(flock) on its temporary for as long as the temporary exists, so
`remove_stale_temporaries` can tell a live writer's temporary (locked) from a killed
writer's (the kernel drops a dead process's locks) and removes only the latter.

A written file gets the mode `open()` gives a new file, 0o666 without the umask's
bits (0o644 under umask 022), not mkstemp's owner-only 0o600; a file that replaces
another gets that usual mode too, not the old file's (the rename makes a new file,
and files that an older relocfw wrote owner-only get the usual mode when rewritten).
"""

from __future__ import annotations

import contextlib
import os
import shutil
import tempfile
import time
from collections.abc import Iterator
from contextlib import contextmanager, suppress
from pathlib import Path
from typing import IO

try:
    import fcntl
except ImportError:  # Windows: no flock; clean-up goes by age alone
    fcntl = None

# With locks: a temporary younger than this is kept even when unlocked, which covers
# the instant between mkstemp creating it and its writer locking it.
LOCKED_GRACE_SECONDS = 60.0
# Without locks only the age tells: a temporary untouched this long has no writer.
UNLOCKED_GRACE_SECONDS = 24 * 3600.0
# open()'s mode for a new file, before the umask.
USUAL_MODE = 0o666


def temporary_prefix(path: Path) -> str:
    """The name every temporary of `path` starts with (hidden, beside it)."""
    return f".{Path(path).name}."


def current_umask() -> int:
    """The process's umask, read without changing it where the system allows.

    Linux reports it in /proc/self/status; elsewhere it is set and restored, which
    another thread creating a file in that instant could see.
    """
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("Umask:"):
                return int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    mask = os.umask(0o077)
    os.umask(mask)
    return mask


def usual_file_mode() -> int:
    """The mode `open()` gives a new file: 0o666 without the umask's bits."""
    return USUAL_MODE & ~current_umask()


def hold_exclusive_lock(handle: int) -> None:
    """Lock the open file `handle` for this writer until it is closed (no-op without
    flock); `remove_stale_temporaries` never removes a locked temporary.

    A file system that refuses flock (some network mounts) leaves the temporary
    unlocked: the write goes on, and a cleaner there cannot lock it either, which
    `remove_if_abandoned` takes as a live writer.
    """
    if fcntl is None:
        return
    # ENOLCK, EOPNOTSUPP: no flock on this file system.
    with suppress(OSError):
        fcntl.flock(handle, fcntl.LOCK_EX)


def give_usual_mode(handle: int, temporary: str) -> None:
    """Give the temporary `usual_file_mode` instead of mkstemp's 0o600."""
    mode = usual_file_mode()
    # Some file systems (exFAT, vfat) refuse a change of mode; the mode is a courtesy,
    # the data is what must land, so such a file keeps the mode it was given.
    with contextlib.suppress(PermissionError, NotImplementedError):
        if hasattr(os, "fchmod"):
            os.fchmod(handle, mode)
        else:
            os.chmod(temporary, mode)


@contextmanager
def atomic_write(path: Path, mode: str = "wb") -> Iterator[IO]:
    """A stream to a temporary file beside `path`, renamed over it when the block ends.

    The data is flushed to disk before the rename; an exception (or an interrupt)
    removes the temporary and leaves `path` as it was. Text modes write newlines as
    given (no translation). The parent folder is created if needed. The temporary is
    locked while it exists (see the module's note), and the file gets the usual mode
    of a new file (0o666 without the umask's bits).
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    handle, temporary = tempfile.mkstemp(prefix=temporary_prefix(path), dir=path.parent)
    try:
        with os.fdopen(handle, mode, **({} if "b" in mode else {"newline": ""})) as stream:
            hold_exclusive_lock(stream.fileno())
            give_usual_mode(stream.fileno(), temporary)
            yield stream
            stream.flush()
            os.fsync(stream.fileno())
            if fcntl is not None:
                # Renamed while still open and locked: closed first, a cleaner could
                # lock and remove it in between. (POSIX renames open files freely.)
                os.replace(temporary, path)
        if fcntl is None:
            # Windows cannot rename a file it holds open.
            os.replace(temporary, path)
    except BaseException:
        Path(temporary).unlink(missing_ok=True)
        raise


def publish_folder(staging: Path, folder: Path, marker: str) -> None:
    """Rename a finished `staging` folder to `folder`, all or nothing.

    Folders of files (a rendered scene, a bag's extraction) are written beside their
    place and renamed into it once complete, so a killed writer never leaves half a
    folder under the real name. Where another process published the same folder
    first (its `marker` file is there), that one is kept and this call returns; the
    caller removes its own staging folder.
    """
    try:
        os.replace(staging, folder)
    except OSError:
        if not (Path(folder) / marker).is_file():  # not a concurrent writer that won
            raise


def staging_folder(parent: Path, prefix: str) -> tuple[Path, int]:
    """A new hidden folder in `parent` (named `prefix` + a random part) to write files
    into before they are published, and an open handle of it holding an exclusive lock
    (as `atomic_write` holds its temporary's) until `release_folder`: so
    `remove_stale_folders` tells a live writer's folder from a killed one's. Without
    flock (Windows, where a folder cannot be opened either) the handle is -1 and
    clean-up goes by age alone."""
    parent.mkdir(parents=True, exist_ok=True)
    folder = Path(tempfile.mkdtemp(prefix=prefix, dir=parent))
    if fcntl is None:
        return folder, -1
    handle = os.open(folder, os.O_RDONLY)
    hold_exclusive_lock(handle)
    return folder, handle


def release_folder(handle: int) -> None:
    """Close a `staging_folder`'s handle (its lock goes with it)."""
    if handle < 0:
        return
    with suppress(OSError):
        os.close(handle)


def remove_stale_folders(parent: Path, prefix: str) -> list[Path]:
    """Delete the staging folders named `prefix`* in `parent` that killed writers left
    (a bag extraction, a compact map), and say which.

    As `remove_if_abandoned` does for files: a folder is removed only when it is older
    than LOCKED_GRACE_SECONDS (UNLOCKED_GRACE_SECONDS without flock) and no writer
    holds its lock, taken here for the removal so no writer can take it up meanwhile.
    """
    removed = []
    now = time.time()
    grace = LOCKED_GRACE_SECONDS if fcntl is not None else UNLOCKED_GRACE_SECONDS
    for folder in sorted(Path(parent).glob(f"{prefix}*")):
        try:
            if not folder.is_dir() or folder.is_symlink():
                continue
            if now - folder.stat().st_mtime < grace:
                continue
            # Without flock the age alone tells (and a folder cannot be opened there).
            handle = -1 if fcntl is None else os.open(folder, os.O_RDONLY)
        except OSError:  # gone already (its writer published it) or unreadable
            continue
        try:
            if fcntl is not None:
                try:
                    fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
                except OSError:  # a live writer holds it
                    continue
            shutil.rmtree(folder, ignore_errors=True)
            removed.append(folder)
        finally:
            release_folder(handle)
    return removed


@contextmanager
def file_lock(path: Path) -> Iterator[None]:
    """An exclusive lock on the file `path` (created if missing, and left in place: a
    lock file removed while another process waits on it would let a third in) for
    the block, so writers take turns.

    Only a courtesy: without flock (Windows), where the lock file cannot be opened for
    writing, or where flock does nothing (some network mounts) the block runs
    unlocked, so what it does must be safe without the lock.
    """
    if fcntl is None:
        yield
        return
    try:
        # Read-write: over NFS an exclusive flock needs a descriptor open for writing.
        handle = os.open(path, os.O_RDWR | os.O_CREAT, USUAL_MODE)
    except OSError:
        handle = -1
    try:
        if handle >= 0:
            hold_exclusive_lock(handle)
        yield
    finally:
        if handle >= 0:
            os.close(handle)


def write_text_atomic(text: str, path: Path) -> None:
    """Write `text` to `path` all or nothing (results files, tables, notes)."""
    with atomic_write(path, "w") as stream:
        stream.write(text)


def remove_if_abandoned(temporary: Path, now: float) -> bool:
    """Remove `temporary` if no writer holds it; whether it was removed.

    With flock: only when it is older than LOCKED_GRACE_SECONDS and its lock can be
    taken without waiting (its writer has finished or died), and it is removed while
    that lock is held, so no writer can take it up in between. Without flock: only
    when it is older than UNLOCKED_GRACE_SECONDS.
    """
    grace = LOCKED_GRACE_SECONDS if fcntl is not None else UNLOCKED_GRACE_SECONDS
    try:
        if now - temporary.stat().st_mtime < grace:
            return False
    except OSError:  # gone already (its writer renamed it) or unreadable
        return False
    if fcntl is None:
        temporary.unlink(missing_ok=True)
        return True
    try:
        # Read-write: over NFS an exclusive flock needs a descriptor open for writing.
        handle = os.open(temporary, os.O_RDWR)
    except OSError:
        return False
    try:
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:  # a live writer holds it (or no flock here: keep it, to be safe)
            return False
        # The name may have been renamed away (the writer finished) between the stat
        # and the open; remove it only if it still names the file now locked.
        try:
            same = os.path.samestat(os.fstat(handle), temporary.stat())
        except OSError:
            return False
        if same:
            temporary.unlink(missing_ok=True)
        return same
    finally:
        os.close(handle)


def remove_stale_temporaries(path: Path) -> None:
    """Delete temporary files a killed writer of `path` left behind.

    A SIGKILL during `atomic_write` cannot clean up; `path` itself is intact (it is
    only ever replaced whole), but the temporaries would pile up. Safe while other
    processes write `path`: a temporary is removed only when no writer holds its lock
    and it is older than a short grace age (see `remove_if_abandoned`); without flock
    (Windows) only when it is a day old.
    """
    path = Path(path)
    now = time.time()
    for temporary in path.parent.glob(f"{temporary_prefix(path)}*"):
        remove_if_abandoned(temporary, now)
