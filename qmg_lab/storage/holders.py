"""Which other processes have a file open: the readers a writer names when HDF5 refuses it a run file.

HDF5 (1.10 on) locks a file for each open: a read-only open takes a shared lock and keeps it until the file is
closed, an open for writing needs the exclusive lock, so a writer (`qmg-lab run --resume`) is refused ("unable to
lock file") while any reader holds the file open: `flock(2)` on Linux, `LockFileEx` on Windows (the HDF Group's
"File Locking in HDF5", doc/file-locking.md in the HDF5 sources: read-only opens lock shared, writing opens
exclusive, the lock lasts until the descriptor closes; Windows locks from 1.10.8 and 1.12.1). HDF5 does not say
who holds the lock; the operating system says who has the file open, as far as it lets this user see:
`psutil.Process.open_files()` (Linux: /proc/PID/fd, processes of this user; Windows: the handles of processes
this user may inspect, which psutil documents as not guaranteed complete).
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass
from pathlib import Path

import psutil

#: at most this long is spent looking (s): the answer names readers, it must not delay the refusal much
SEARCH_LIMIT_S = 2.0


@dataclass(frozen=True)
class Holder:
    """A process that has the file open: its id, its name and its command line (as the OS reports them)."""

    pid: int
    name: str
    cmdline: str

    def __str__(self) -> str:
        cmd = self.cmdline if len(self.cmdline) <= 80 else self.cmdline[:77] + "..."
        return f"process {self.pid} ({cmd or self.name})"


def holders(path: str | Path, limit_s: float = SEARCH_LIMIT_S) -> list[Holder]:
    """The other processes that have `path` open, as far as this user can see within `limit_s` (module doc)."""
    wanted = os.path.normcase(str(Path(path).resolve()))  # Windows: paths compare without case
    me = os.getpid()
    deadline = time.monotonic() + limit_s
    found: list[Holder] = []
    for proc in psutil.process_iter(["pid", "name"]):
        if time.monotonic() > deadline:
            break
        if proc.pid == me:
            continue
        try:
            files = proc.open_files()
            if any(os.path.normcase(f.path) == wanted for f in files):
                found.append(Holder(proc.pid, str(proc.info["name"] or ""), " ".join(proc.cmdline())))
        except (psutil.Error, OSError):  # gone, or not ours to inspect
            continue
    return found


def named_holders(path: str | Path) -> str:
    """The readers of `path` for a message: " (process 4242 (python -m ipykernel ...))", or "" if none is seen."""
    found = holders(path)
    return f" ({', '.join(map(str, found))})" if found else ""
