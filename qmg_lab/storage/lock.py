"""One writer per run file, and the one answer to "is its writer still alive?": the run file's lock.

The lock is `filelock.FileLock` (flock on POSIX, LockFileEx on Windows) on a separate small file next to the run
file, `.NAME.lock`, held from the CLI's first check (before `--overwrite` may delete anything) to the run file's
close. The operating system releases it however the process dies (kill -9 included).

Why a separate lock file, not the run file itself: the lock must exist before the run file does (a new run is laid
out under a hidden name and moved into place) and across its replacement (`--overwrite`); and HDF5 owns the run
file's descriptors (a POSIX record lock on another descriptor of the same file would be dropped by HDF5's own
close). The lock file stays after release (filelock leaves it so that waiters share one inode): a stale one is
harmless, it only ever records who held it last.

What filelock lacks here, in one line: it does not say who holds a lock, so once held this wrapper writes
"process PID on HOST" into the lock file for the refusal message (unreadable while held on Windows, where the
message then says the holder is not recorded).

Liveness (`writer_state`): a run file's writer is alive exactly while its lock is held. A free lock means the
writer is gone, whatever its recorded process id now names (a reused PID is not a writer). No process is signalled
to find out: `os.kill` with signal 0 sends Ctrl-C on Windows (signal 0 is CTRL_C_EVENT).

Within one process the lock is re-entrant (counted): the CLI takes it, and `RunWriter.create` / `reopen`, which
always take it too, share it. A writer waits up to ACQUIRE_WAIT_S for a lock that another process holds: a
`writer_state` probe from a reader (`status`, the watch page) holds it for microseconds and must not refuse a run.
"""

from __future__ import annotations

import contextlib
import os
import socket
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import Literal

from filelock import FileLock, Timeout

from qmg_lab.storage.layout import StorageError

#: how long a writer waits for a lock held elsewhere before it refuses, s: longer than a liveness probe holds it
ACQUIRE_WAIT_S = 1.0


@dataclass
class _Held:
    lock: FileLock
    count: int


#: locks this process holds, by lock file path
_HELD: dict[str, _Held] = {}

WriterState = Literal["writing", "gone", "unknown"]


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
            held.count += 1
            self._held = True
            return self
        lock = FileLock(self.lock_file, thread_local=False)
        try:
            lock.acquire(timeout=ACQUIRE_WAIT_S)
        except Timeout:
            raise StorageError(
                f"{self.path}: is being written by another qmg-lab process ({_read_holder(self.lock_file)}); a run "
                f"file has one writer: wait for it to end or stop it, or write to another -o"
            ) from None
        except OSError as exc:  # a read-only folder, no space for an empty file, a path that is not a folder
            raise StorageError(f"{self.path}: cannot create its lock file {self.lock_file}: {_words(exc)}") from None
        _write_holder(self.lock_file)
        _HELD[self._key] = _Held(lock, 1)
        self._held = True
        return self

    def release(self) -> None:
        if not self._held:
            return
        self._held = False
        held = _HELD[self._key]
        held.count -= 1
        if held.count > 0:
            return
        del _HELD[self._key]
        held.lock.release()

    def __enter__(self) -> RunFileLock:
        return self.acquire()

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.release()


def writer_state(path: str | Path) -> WriterState:
    """Whether a process writes the run file `path`, from its lock alone: "writing" (the lock is held, by another
    process or by this one: `held_here` tells which), "gone" (the lock is free, or there is no lock file: no writer
    ever locked it from this folder's view), "unknown" (the lock file cannot be opened to probe it). A free lock
    taken by the probe is released at once."""
    if held_here(path):
        return "writing"
    lock_file = lock_path(path)
    if not lock_file.exists():
        return "gone"
    probe = FileLock(lock_file, thread_local=False)
    try:
        probe.acquire(timeout=0)
    except Timeout:
        return "writing"
    except (OSError, RuntimeError):
        return "unknown"
    probe.release()
    return "gone"


def held_here(path: str | Path) -> bool:
    """This process holds the lock of run file `path` (it is, or is about to be, its writer)."""
    return os.path.abspath(lock_path(path)) in _HELD


def holder(path: str | Path) -> str:
    """Who holds (or last held) the lock of run file `path`, as its lock file says ("process PID on HOST")."""
    return _read_holder(lock_path(path))


def _write_holder(lock_file: Path) -> None:
    """Record the holder in the held lock file; a write that fails (a full disk) only loses the record."""
    with contextlib.suppress(OSError), open(lock_file, "r+b") as f:
        f.truncate(0)
        f.write(f"process {os.getpid()} on {socket.gethostname()}\n".encode())


def _read_holder(lock_file: Path) -> str:
    try:
        text = lock_file.read_bytes()[:200].decode("utf-8", "replace").strip()
    except OSError:
        text = ""
    return text or "its process is not recorded"


def _words(exc: OSError) -> str:
    """An OSError as words without the traceback's class name: its strerror and file name."""
    return f"{exc.strerror or exc}" + (f" ({exc.filename})" if exc.filename else "")
