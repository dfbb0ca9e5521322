"""One writer per run file: an exclusive lock that the operating system releases when the process dies.

The lock is a small file next to the run file, `.NAME.lock`, held open and locked for as long as a writer may
change `NAME`: from the CLI's first check (before `--overwrite` may delete anything) to the run file's close.
`fcntl.flock(LOCK_EX | LOCK_NB)` where the system has fcntl (POSIX), else `msvcrt.locking(LK_NBLCK)` on one byte
far past the end (Windows; so the holder's pid, written at the start, stays readable); each module is imported
only where it exists. Both
locks belong to the open file and end with the process, however it dies (kill -9 included): a stale lock file
is harmless, the next writer locks it again.

Within one process the lock is re-entrant (counted): the CLI takes it, and `RunWriter.create` / `reopen`, which
always take it too, share it.

POSIX: the holder deletes the lock file on release, still holding it; a process that opened the old file in the
meantime finds, once it has the lock, that the path names another file (or none) and starts over. Windows does
not delete a file another process holds open: the delete is tried and skipped if refused.
"""

from __future__ import annotations

import contextlib
import importlib
import os
import socket
import sys
from pathlib import Path
from types import TracebackType
from typing import Any

from qmg_lab.storage.layout import StorageError


def _posix_flock() -> Any:
    """fcntl where the system has it (POSIX), else None (Windows)."""
    try:
        import fcntl
    except ImportError:
        return None
    return fcntl


_FCNTL = _posix_flock()
_WIN_LOCK_OFFSET = 1 << 30  # msvcrt's locked byte: past any pid text, so readers can read the holder


def _try_lock(fd: int) -> None:
    """Lock `fd` without waiting; OSError (BlockingIOError on POSIX) if another process holds it."""
    if _FCNTL is not None:
        _FCNTL.flock(fd, _FCNTL.LOCK_EX | _FCNTL.LOCK_NB)
        return
    msvcrt: Any = importlib.import_module("msvcrt")  # Windows: a byte-range lock on one byte far past the end
    os.lseek(fd, _WIN_LOCK_OFFSET, os.SEEK_SET)
    msvcrt.locking(fd, msvcrt.LK_NBLCK, 1)
    os.lseek(fd, 0, os.SEEK_SET)


def _unlock(fd: int) -> None:
    if _FCNTL is not None:
        _FCNTL.flock(fd, _FCNTL.LOCK_UN)
        return
    msvcrt: Any = importlib.import_module("msvcrt")
    os.lseek(fd, _WIN_LOCK_OFFSET, os.SEEK_SET)
    msvcrt.locking(fd, msvcrt.LK_UNLCK, 1)


#: locks this process holds: lock file path -> [file descriptor, count]
_HELD: dict[str, list[int]] = {}


def lock_path(path: str | Path) -> Path:
    """The lock file of a run file: `.NAME.lock` in the same directory."""
    p = Path(path)
    return p.with_name(f".{p.name}.lock")


class RunFileLock:
    """`with RunFileLock(path):` — the exclusive right to write `path` (StorageError if another process has it)."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.lock_file = lock_path(self.path)
        self._key = os.path.abspath(self.lock_file)
        self._held = False

    def acquire(self) -> RunFileLock:
        if self._held:
            return self
        held = _HELD.get(self._key)
        if held is not None:
            held[1] += 1
            self._held = True
            return self
        while True:
            try:
                fd = os.open(self.lock_file, os.O_RDWR | os.O_CREAT, 0o644)
            except OSError as exc:
                raise StorageError(f"{self.path}: cannot create its lock file {self.lock_file}: {exc}") from None
            try:
                _try_lock(fd)
            except OSError:
                holder = _read_holder(fd)
                os.close(fd)
                raise StorageError(
                    f"{self.path}: is being written by another qmg-lab process ({holder}); a run file has one "
                    f"writer: wait for it to end or stop it, or write to another -o"
                ) from None
            if sys.platform != "win32" and not _same_file(fd, self.lock_file):
                os.close(fd)  # its holder deleted it on release after we opened it: lock the new one
                continue
            os.ftruncate(fd, 0)
            os.write(fd, f"process {os.getpid()} on {socket.gethostname()}\n".encode())
            _HELD[self._key] = [fd, 1]
            self._held = True
            return self

    def release(self) -> None:
        if not self._held:
            return
        self._held = False
        held = _HELD[self._key]
        held[1] -= 1
        if held[1] > 0:
            return
        del _HELD[self._key]
        fd = held[0]
        try:
            if sys.platform != "win32":
                self.lock_file.unlink(missing_ok=True)  # still held: see the module docstring
            _unlock(fd)
        finally:
            os.close(fd)
        if sys.platform == "win32":
            with contextlib.suppress(OSError):  # another process has it open (and will lock it)
                self.lock_file.unlink(missing_ok=True)

    def __enter__(self) -> RunFileLock:
        return self.acquire()

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.release()


def _same_file(fd: int, path: Path) -> bool:
    try:
        return os.path.samestat(os.fstat(fd), os.stat(path))
    except FileNotFoundError:
        return False


def _read_holder(fd: int) -> str:
    try:
        os.lseek(fd, 0, os.SEEK_SET)
        text = os.read(fd, 200).decode("utf-8", "replace").strip()
    except OSError:
        text = ""
    return text or "its process is not recorded"
