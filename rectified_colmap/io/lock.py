"""Output files: checked writable before anything is written, one writer at a time.

:func:`check_writable` says in one line why an output cannot be written (missing or
read-only folder, read-only file) before a run creates or changes anything.

One writer per output: an exclusive advisory lock held while a writer is open.

``OutputLock(path)`` locks ``<path>.lock`` (``flock``, released by the kernel when the
process dies, so a kill -9 never leaves a stale lock behind). A second process that wants
the same output logs once which process holds it (the pid is written into the lock file)
and waits; when it gets the lock, the first writer has closed its files and the second
sees everything the first wrote (and skips it on resume).

Within one process the lock is re-entrant: opening a second writer (or a reader through
the same class) on a path this process already holds shares the lock instead of
dead-locking.

The lock file is removed on release. Removing a lock file is racy unless acquiring checks
that the locked file is still the one at the path: :meth:`OutputLock.acquire` does (the
usual inode check), so two processes can never both believe they hold the lock.
"""

from __future__ import annotations

import logging
import os
import tempfile
import time
from pathlib import Path

try:
    import fcntl
except ImportError:  # pragma: no cover - not POSIX: no inter-process lock
    fcntl = None

logger = logging.getLogger(__name__)

_HELD: dict[Path, list] = {}
"""Locks this process holds: resolved lock path -> [fd, reference count, pid]. Entries
inherited through fork() belong to the parent and are ignored by the child."""


def check_writable(path: Path | str, what: str = "output") -> None:
    """Raise PermissionError naming ``path`` when it cannot be created or changed.

    The folder must be writable too: SQLite puts its journal beside the database and the
    hloc writer stages and atomically replaces files there."""
    path = Path(path)
    folder = path.absolute().parent
    existing = folder
    while not existing.exists():
        existing = existing.parent
    if not existing.is_dir():
        raise NotADirectoryError(f"{path}: cannot create the {what}: {existing} is not a folder")
    if not os.access(existing, os.W_OK | os.X_OK):
        raise PermissionError(
            f"{path}: cannot write the {what}: folder {existing} is not "
            "writable (journal and staging files are made beside it)"
        )
    if path.exists():
        if path.is_dir():
            raise IsADirectoryError(f"{path}: the {what} path is a folder")
        if not os.access(path, os.R_OK | os.W_OK):
            raise PermissionError(f"{path}: the {what} file is read-only")
    # os.access trusts permission bits (always yes for root): a file made and removed
    # there is the real test (read-only mounts, /proc, full quotas)
    try:
        fd, probe = tempfile.mkstemp(dir=existing, prefix=".rectified-colmap-probe-")
    except OSError as e:
        raise PermissionError(
            f"{path}: cannot write the {what}: folder {existing} does not accept new files "
            f"({e.strerror})"
        ) from None
    os.close(fd)
    os.unlink(probe)


def lock_path(path: Path | str) -> Path:
    """The lock file of an output: ``<path>.lock`` beside it (folder symlinks resolved, so
    every spelling of the path shares one lock)."""
    path = Path(path).absolute()
    return path.parent.resolve() / (path.name + ".lock")


class OutputLock:
    """Exclusive lock on an output file for this process (see the module docstring).

    ``with OutputLock(path): ...`` or :meth:`acquire` / :meth:`release`."""

    def __init__(self, path: Path | str, poll_seconds: float = 0.2):
        self.path = Path(path)
        self.file = lock_path(self.path)
        self.poll_seconds = poll_seconds
        self._held = False

    def __enter__(self) -> "OutputLock":
        self.acquire()
        return self

    def __exit__(self, *exc) -> None:
        self.release()

    def acquire(self) -> None:
        if self._held:
            return
        if fcntl is None:  # pragma: no cover
            self._held = True
            return
        held = _HELD.get(self.file)
        if held is not None and held[2] == os.getpid():
            held[1] += 1
            self._held = True
            return
        told = False
        while True:
            try:
                fd = os.open(self.file, os.O_RDWR | os.O_CREAT, 0o644)
            except OSError as e:
                raise PermissionError(
                    f"{self.path}: cannot lock it for writing: its lock file {self.file.name} "
                    f"cannot be made beside it ({e.strerror})"
                ) from None
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                if not told:
                    logger.warning(
                        "%s is being written by process %s; waiting for it to finish",
                        self.path,
                        _read_pid(fd) or "?",
                    )
                    told = True
                os.close(fd)
                time.sleep(self.poll_seconds)
                continue
            except BaseException:
                os.close(fd)
                raise
            # The holder may have removed the file just before we locked it: then our lock
            # is on an orphan inode and means nothing. Start again on the current file.
            try:
                same = os.stat(self.file).st_ino == os.fstat(fd).st_ino
            except FileNotFoundError:
                same = False
            if not same:
                os.close(fd)
                continue
            os.ftruncate(fd, 0)
            os.write(fd, f"{os.getpid()}\n".encode())
            _HELD[self.file] = [fd, 1, os.getpid()]
            self._held = True
            if told:
                logger.info("%s: got the lock, going on", self.path)
            return

    def release(self) -> None:
        if not self._held:
            return
        self._held = False
        if fcntl is None:  # pragma: no cover
            return
        held = _HELD[self.file]
        held[1] -= 1
        if held[1] > 0:
            return
        del _HELD[self.file]
        try:
            self.file.unlink()  # while still locked: see the module docstring
        except FileNotFoundError:
            pass
        os.close(held[0])


def _read_pid(fd: int) -> str | None:
    try:
        text = os.pread(fd, 32, 0).decode(errors="replace").strip()
    except OSError:
        return None
    return text if text.isdigit() else None
