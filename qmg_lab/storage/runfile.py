"""Opening a run file for reading: `open_run_file`, the one way every reader of qmg-lab opens one.

`analyze`, `runs`, `salvage`'s scan, `watch`, `qmg_lab.open_run` and the read-only checks of `--resume` all
open run files here (a test holds `h5py.File(` to qmg_lab/storage/), so that each of them answers within
seconds, with words, whatever the file's bytes:

1. the path must be a regular file (a folder, a FIFO or a device is refused before anything reads it);
2. the superblock check (qmg_lab/storage/superblock.py): no HDF5 signature, a superblock cut off or with a bad
   checksum, or a file that ends before the end of file its superblock records is answered at once; a SWMR
   open of such a file retries its metadata reads for minutes;
3. the file's structure is walked once in a worker process with a time limit (qmg_lab/storage/probe.py: every
   group, attribute, dataset header and chunk index), without SWMR, through `ClearedView` (a writer's flags read
   as cleared, nothing written; bounded by the bytes on disk, nothing retried), tried again twice 0.2 s apart if
   it failed (a live writer's flush caught half-way is whole a moment later). HDF5 can loop inside its C code on
   damaged metadata, in a closed file too (a zeroed object header), and retries a failing SWMR read for minutes;
   no thread can interrupt either, the end of a process can. A walk that fails, crashes its worker or runs out of
   time (PROBE_TIMEOUT_S) makes the file damaged (DamagedFileError), and the worker is replaced. One worker
   serves a process's every file: its start (a Python start with h5py, about 0.4 s) is paid once per process,
   not per file, and is not counted in a file's time limit. A file is walked once per state (path, size,
   modification time) per process, and a state found damaged is answered at once the next time; a caller that
   reopens a live file again and again (the watch page) passes `probe=False` after its first open;
4. the file is opened here read-only: through SWMR if its flags are set (its writer is still writing, or was
   killed), else without;
5. the root attribute `format` must be one this version reads (READ_FORMATS): "qmg-lab/1" or "qmg-lab/2".

What the body of `with open_run_file(...)` raises from HDF5 (a chunk or a header that does not decode) comes out
as DamagedFileError naming the file (StorageError for a group or column the layout lacks).

Whole valid rows, one rule for every reader (`RunFile.rows`, `RunFile.read`): a group is cut to its shortest
column (a kill, or a reader between two column writes, may leave one column a block longer); in a data group
(one with a `time` column) the rows `valid_rows` takes as data, and of those, rows holding the fill value (NaN)
in any column read are dropped: rows allocated but never written (a kill, a full disk) are never data.
"""

from __future__ import annotations

import atexit
import json
import os
import queue
import subprocess
import sys
import threading
from collections.abc import Iterable, Iterator
from contextlib import contextmanager, suppress
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from qmg_lab.storage.h5clear import writer_flags_set
from qmg_lab.storage.layout import FORMAT, GROUP_UNITS, H5_ERRORS, READ_FORMATS, DamagedFileError, StorageError
from qmg_lab.storage.superblock import check_file_end
from qmg_lab.storage.view import ClearedView

#: the worker's time to walk one file's structure (step 3), s. The walk itself never retries (no SWMR) and takes
#: well under a second on an intact 12-hour file; the worker's start (a Python start with h5py) is not counted
#: in it, so a busy machine does not make a healthy file look damaged. Within the 5 s a reader has to answer.
PROBE_TIMEOUT_S = 4.0
#: the worker's start, up to its "ready" line, s: about 0.4 s on an idle machine, several seconds on one loaded
#: 5x over its cores (benchmarks/damaged_files.py)
WORKER_START_TIMEOUT_S = 60.0
#: how long a worker whose input is closed has to end by itself before it is killed, s
WORKER_STOP_S = 2.0


def attr_value(value: Any) -> Any:
    """An HDF5 attribute as a Python value: bytes decoded as UTF-8, numpy scalars as Python scalars."""
    if isinstance(value, bytes):
        return value.decode("utf-8", "replace")
    if isinstance(value, np.generic):
        return value.item()
    return value


SCAN_ROWS = 1 << 22  # time rows read at once by the valid-rows scan: 32 MiB of float64, 256 /lockin chunks


def valid_rows(t: np.ndarray, previous: float | None = None) -> int:
    """How many leading rows of a time column are data: the longest prefix that is finite and does not decrease,
    less a trailing run of exact 0.0 after the first row.

    Rows a killed writer (or a killed repair: shrinking a dataset writes fill values at once, its new extent only
    at the next flush) left allocated but unwritten hold the dataset's fill value: NaN (not finite) in files
    whose datasets declare it, 0.0 in the earliest files (a step back to 0.0, or 0.0 repeated after a first row
    at 0.0). A time of exactly 0.0 can only be a run's first row, so neither is ever taken as data.
    previous: the time of the row before t[0] when t continues rows already taken as data.
    """
    n = int(t.shape[0])
    if n == 0:
        return 0
    bad = ~np.isfinite(t)
    bad[1:] |= t[1:] < t[:-1]
    if previous is not None:
        bad[0] |= bool(t[0] < previous)
    k = int(np.argmax(bad)) if bad.any() else n
    first = 1 if previous is None else 0
    while k > first and t[k - 1] == 0.0:
        k -= 1
    return k


def _without_fill_rows(columns: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Rows of a group with a time column (equal-length `columns`) less those holding NaN, the fill value, in any
    float column: rows never written (a kill or a full disk) are not data."""
    if "time" not in columns:
        return columns
    fill = np.zeros(columns["time"].shape[0], dtype=bool)
    for v in columns.values():
        if v.dtype.kind == "f":
            fill |= np.isnan(v)
    return {c: v[~fill] for c, v in columns.items()} if fill.any() else columns


@dataclass
class RunFile:
    """A run file open for reading (`open_run_file`). h5: the open HDF5 file (read-only); format: its root
    attribute `format`; writer_open: its superblock says a writer has it open or was killed; attrs: the root
    attributes decoded (`attr_value`)."""

    path: Path
    h5: h5py.File
    format: str
    writer_open: bool
    attrs: dict[str, Any] = field(default_factory=dict)

    def columns(self, group: str) -> list[str]:
        """The 1-D datasets of /group, in file order (StorageError if there is no such group)."""
        if group not in self.h5:
            raise StorageError(f"{self.path}: has no /{group} group")
        grp = self.h5[group]
        return [c for c in grp if isinstance(grp[c], h5py.Dataset) and grp[c].ndim == 1]

    def rows(self, group: str, columns: Iterable[str] | None = None) -> int:
        """Whole rows of /group: its shortest column (of `columns`, default all), and in a data group (one of
        GROUP_UNITS: rows stamped with a sample or reading time) the leading rows `valid_rows` takes as data."""
        grp = self.h5[group]
        names = self.columns(group) if columns is None else list(columns)
        if self.writer_open:  # SWMR: see the writer's last flush
            for c in names:
                grp[c].refresh()
        n = min((int(grp[c].shape[0]) for c in names), default=0)
        if group not in GROUP_UNITS or "time" not in grp:
            return n
        n = min(n, int(grp["time"].shape[0]))
        done, previous = 0, None  # the rule over the whole column, SCAN_ROWS at a time: no memory on a long run
        while done < n:
            t = np.asarray(self._read(grp["time"], done, min(n, done + SCAN_ROWS)), dtype=float)
            k = valid_rows(t, previous=previous)
            if k < t.shape[0]:
                return done + k
            previous = float(t[-1])
            done += t.shape[0]
        return n

    def read(self, group: str, columns: Iterable[str] | None = None) -> dict[str, np.ndarray]:
        """Columns of /group (default every 1-D column; `time` always, when the group has one), whole rows only
        (module docstring): in a group with a time column, a row holding NaN (the fill value) in any float
        column read is a row never written, not data, and is dropped. Text columns stay bytes."""
        names = self.columns(group)
        if columns is not None:
            wanted = list(columns)
            unknown = sorted(set(wanted) - set(names))
            if unknown:
                raise StorageError(f"{self.path}: /{group} has no columns {unknown}")
            names = [c for c in names if c in wanted or c == "time"]
        grp = self.h5[group]
        n = self.rows(group, names)
        return _without_fill_rows({c: self._read(grp[c], 0, n) for c in names})

    def tail(self, group: str, columns: Iterable[str], rows: int) -> dict[str, np.ndarray]:
        """The last `rows` whole rows of /group's `columns` (and `time`), by the rule of `read` applied from the
        end: fill rows only ever follow a group's data (a kill or a full disk leaves them at its end), so the
        tail's time rows are checked continuing the row before it, and NaN rows dropped. Reads only the tail."""
        grp = self.h5[group]
        names = [c for c in self.columns(group) if c in set(columns) or c == "time"]
        n = min((int(grp[c].shape[0]) for c in names), default=0)
        if group in GROUP_UNITS and "time" in grp:
            i0 = max(0, n - rows)
            t = self._read(grp["time"], i0, n)
            before = float(self._read(grp["time"], i0 - 1, i0)[0]) if i0 else None
            k = valid_rows(t, previous=before)
            n = i0 + k if k or not i0 else self.rows(group, names)
        i0 = max(0, n - rows)
        return _without_fill_rows({c: self._read(grp[c], i0, n) for c in names})

    def _read(self, ds: h5py.Dataset, start: int, stop: int) -> np.ndarray:
        try:
            return np.asarray(ds[start:stop])
        except H5_ERRORS as exc:
            raise DamagedFileError(
                f"{self.path}: the dataset {ds.name} cannot be read (the file is damaged): {exc}"
            ) from None


@contextmanager
def open_run_file(
    path: str | Path, *, probe: bool = True, timeout_s: float = PROBE_TIMEOUT_S, damaged: bool = False
) -> Iterator[RunFile]:
    """`with open_run_file(path) as run:` a qmg-lab run file open read-only (module docstring, steps 1-5).

    Yields a RunFile (`run.h5` the h5py.File, `run.attrs`, `run.format`, `run.writer_open`, `run.read(group)`).
    Raises StorageError naming the file and what is wrong (DamagedFileError for damaged bytes), never an h5py
    exception. probe=False skips the worker's walk of the file's structure (step 3): only for a file this
    caller has already walked. damaged=True (salvage and its scan): a file cut short or left open
    by a writer is opened too, always through `ClearedView` without SWMR (bounded by the bytes on disk: nothing
    is retried), and root attributes that do not read are left out instead of refused.
    """
    p = Path(path)
    if not p.exists():
        raise StorageError(f"{p}: no such run file")
    if not p.is_file():
        raise StorageError(f"{p}: not a run file (a folder, a pipe or a device, not a regular file)")
    view: ClearedView | None = None
    if damaged:
        writer_open = False
        try:
            view = ClearedView(p)
            h5 = h5py.File(view, "r")
        except (*H5_ERRORS, StorageError) as exc:
            if view is not None:
                view.close()
            raise DamagedFileError(f"{p}: HDF5 cannot open it at all, nothing can be read: {exc}") from None
    else:
        check_file_end(p)
        writer_open = writer_flags_set(p)
        # every file's structure is walked once in a child with a time limit before this process reads it: HDF5
        # can loop inside its C code on damaged metadata (a zeroed object header, a flipped chunk-index byte),
        # closed file or not, and only a child process can be stopped there
        if probe:
            _probe_once(p, timeout_s)
        try:
            h5 = h5py.File(p, "r", swmr=writer_open, libver="latest")
        except H5_ERRORS as exc:
            raise DamagedFileError(f"{p}: HDF5 cannot open it: {exc}") from None
    try:
        with h5:
            attrs = _root_attrs(p, h5, tolerant=damaged)
            fmt = str(attrs.get("format", ""))
            if not (damaged and fmt == ""):
                check_format(p, fmt)
            yield RunFile(p, h5, fmt, writer_open, attrs)
    except StorageError:
        raise
    except KeyError as exc:
        if "doesn't exist" in str(exc) or "does not exist" in str(exc):
            raise StorageError(f"{p}: {exc.args[0] if exc.args else exc}") from None
        raise DamagedFileError(f"{p}: HDF5 cannot read it (the file is damaged): {exc}") from None
    except H5_ERRORS as exc:
        raise DamagedFileError(f"{p}: HDF5 cannot read it (the file is damaged): {exc}") from None
    finally:
        if view is not None:
            view.close()


def _root_attrs(p: Path, h5: h5py.File, *, tolerant: bool) -> dict[str, Any]:
    """The root attributes decoded; one that does not read is a DamagedFileError, or left out if tolerant."""
    try:
        names = list(h5.attrs)
    except H5_ERRORS as exc:
        if tolerant:
            return {}
        raise DamagedFileError(f"{p}: its root attributes do not read (the file is damaged): {exc}") from None
    attrs: dict[str, Any] = {}
    for k in names:
        try:
            attrs[k] = attr_value(h5.attrs[k])
        except H5_ERRORS as exc:
            if not tolerant:
                raise DamagedFileError(f"{p}: its root attribute {k!r} does not read (damaged): {exc}") from None
    return attrs


def check_structure(path: str | Path) -> None:
    """Open the file (`open_run_file`), whose worker walks every attribute, member, dataset header and chunk index
    of it (step 3), and close it. StorageError/DamagedFileError in words. For commands that want to answer for a
    damaged file before loading anything heavy (`analyze`, `watch`)."""
    with open_run_file(path):
        pass


def check_format(path: Path, fmt: str) -> None:
    """Refuse (StorageError, in words) a file whose root attribute `format` this version does not read."""
    if fmt in READ_FORMATS:
        return
    if fmt.startswith("qmg-lab/"):
        raise StorageError(
            f"{path}: written in the run-file format {fmt}, which this version of qmg-lab does not read (it reads "
            f"{' and '.join(READ_FORMATS)}); read it with the qmg-lab version that wrote it, or a newer one"
        )
    raise StorageError(
        f"{path}: not a qmg-lab run file: its root attribute format is {fmt!r}, not {FORMAT!r} "
        f"(nor any of {', '.join(READ_FORMATS)})"
    )


#: files whose structure the worker walked without fault, as (path, size, mtime ns): a file that has not changed
#: since is not walked again by this process (analyze opens the same killed file several times)
_PROBED: set[tuple[str, int, int]] = set()


#: file states a walk found damaged, with the time limit it had and what it said: the same bytes are answered
#: at once the next time this process opens them (a reader that opens a file several times, `runs` beside
#: `analyze`), unless the new limit is longer than the one that ran out
_DAMAGED: dict[tuple[str, int, int], tuple[float, str]] = {}


def _probe_once(path: Path, timeout_s: float) -> None:
    """The worker's walk of `path` (step 3), once per file state per process, a damaged state's answer kept."""
    key = _file_key(path)
    if key in _PROBED:
        return
    if key in _DAMAGED and timeout_s <= _DAMAGED[key][0]:
        raise DamagedFileError(_DAMAGED[key][1])
    try:
        _probe_in_child(path, timeout_s)
    except DamagedFileError as exc:
        _DAMAGED[key] = (timeout_s, str(exc))
        raise
    _PROBED.add(key)


def forget_walks() -> None:
    """Forget which file states this process walked (a benchmark that times each reader's first answer)."""
    _PROBED.clear()
    _DAMAGED.clear()


def _file_key(path: Path) -> tuple[str, int, int]:
    st = path.stat()
    return (str(path.resolve()), st.st_size, st.st_mtime_ns)


def child_env() -> dict[str, str]:
    """The environment of a child process that must import this qmg_lab (not another installed one)."""
    root = str(Path(__file__).resolve().parents[2])
    return {**os.environ, "PYTHONPATH": os.pathsep.join(x for x in (root, os.environ.get("PYTHONPATH", "")) if x)}


class _ProbeWorker:
    """One worker process of `python -m qmg_lab.storage.probe` (its protocol: qmg_lab/storage/probe.py) and the
    thread that reads its replies into a queue, so that the parent waits for each with a time limit on Linux and
    Windows alike (a pipe cannot be polled on Windows). The worker runs in its own process group: a Ctrl-C or a
    hang-up meant for the campaign does not end it."""

    def __init__(self, start_timeout_s: float) -> None:
        # Windows: a process group of its own (Ctrl+C is disabled in it: Python's subprocess documentation) and no
        # console window of its own (a notebook's kernel has no console to share); POSIX: a session of its own
        group = (
            {
                "creationflags": getattr(subprocess, "CREATE_NEW_PROCESS_GROUP", 0)
                | getattr(subprocess, "CREATE_NO_WINDOW", 0)
            }
            if os.name == "nt"
            else {"start_new_session": True}
        )
        argv = [sys.executable, "-m", "qmg_lab.storage.probe"]
        try:
            self.proc = subprocess.Popen(
                argv,
                stdin=subprocess.PIPE,
                stdout=subprocess.PIPE,
                stderr=subprocess.DEVNULL,
                encoding="utf-8",
                env=child_env(),
                **group,
            )
        except OSError as exc:
            raise StorageError(f"cannot start the process that checks run files' structure: {exc}") from None
        self.replies: queue.Queue[str | None] = queue.Queue()
        threading.Thread(target=self._read_replies, name="qmg-lab-probe-replies", daemon=True).start()
        try:
            ready = self.replies.get(timeout=start_timeout_s)
        except queue.Empty:
            ready = None
        if ready is None:
            self.proc.kill()
            self.stop()
            raise StorageError(
                f"the process that checks run files' structure did not start within {start_timeout_s:g} s "
                "(the machine may be overloaded): try again"
            )

    def _read_replies(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self.replies.put(line)
        self.replies.put(None)

    def walk(self, path: Path, timeout_s: float) -> None:
        """Have the worker walk `path`: DamagedFileError if the walk fails, the worker dies, or it does not answer
        within timeout_s (it is then killed: HDF5 may be looping in its C code). OSError if the worker had ended
        before the request reached it."""
        assert self.proc.stdin is not None
        self.proc.stdin.write(json.dumps({"path": str(path)}) + "\n")
        self.proc.stdin.flush()
        try:
            line = self.replies.get(timeout=timeout_s)
        except queue.Empty:
            self.proc.kill()
            self.stop()
            raise DamagedFileError(
                f"{path}: HDF5 did not finish reading the file's structure within {timeout_s:g} s (its metadata "
                "does not read: the file is damaged)"
            ) from None
        if line is None:
            self.stop()
            raise DamagedFileError(
                f"{path}: its structure does not read (the file is damaged): HDF5 ended the checking process "
                f"(exit {self.proc.returncode})"
            )
        problem = " ".join(str(json.loads(line).get("problem", "")).split())
        if problem:
            self.stop()  # a worker that met damaged metadata is not reused
            raise DamagedFileError(f"{path}: its structure does not read (the file is damaged): {problem}")

    def stop(self) -> None:
        """End the worker: close its input (it ends by itself) and kill it if it is still walking."""
        if self.proc.stdin is not None:
            with suppress(OSError):
                self.proc.stdin.close()
        try:
            self.proc.wait(timeout=WORKER_STOP_S)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()


class _ProbeService:
    """The process's one worker (started at its first file, kept for the next, replaced after a damaged file)."""

    def __init__(self) -> None:
        self.worker: _ProbeWorker | None = None
        self.lock = threading.Lock()

    def walk(self, path: Path, timeout_s: float) -> None:
        """`_ProbeWorker.walk` on the current worker. A worker found ended between two files (a signal meant for
        it, its watchdog) is replaced before the file is sent, so its end is never blamed on a file."""
        with self.lock:
            for attempt in (0, 1):
                if self.worker is None or self.worker.proc.poll() is not None:
                    self.worker = _ProbeWorker(WORKER_START_TIMEOUT_S)
                try:
                    self.worker.walk(path, timeout_s)
                    return
                except DamagedFileError:
                    self.worker = None
                    raise
                except OSError:  # the worker ended just before the request reached it
                    self.worker.stop()
                    self.worker = None
                    if attempt:
                        raise StorageError(f"{path}: the process that checks its structure ended twice") from None

    def start(self) -> None:
        """Start the worker if there is none (a start that fails is tried again, and said, at the next walk)."""
        with self.lock:
            if self.worker is None or self.worker.proc.poll() is not None:
                try:
                    self.worker = _ProbeWorker(WORKER_START_TIMEOUT_S)
                except StorageError:
                    self.worker = None

    def close(self) -> None:
        # at the process's exit: a worker still starting (start_structure_worker) is not waited for; it ends by
        # itself when this process's end closes its input
        if not self.lock.acquire(timeout=WORKER_STOP_S):
            return
        try:
            if self.worker is not None:
                self.worker.stop()
                self.worker = None
        finally:
            self.lock.release()

    def forget_inherited(self) -> None:
        """In a child made by fork(): the parent's worker and its pipes are the parent's, and the lock may have been
        held by one of the parent's threads at the fork; the child starts afresh (its first walk starts its own
        worker), so that replies never cross between the two processes."""
        self.worker = None
        self.lock = threading.Lock()


_PROBE_SERVICE = _ProbeService()
atexit.register(_PROBE_SERVICE.close)
if hasattr(os, "register_at_fork"):  # POSIX (multiprocessing's default start method on Linux is fork)
    os.register_at_fork(after_in_child=_PROBE_SERVICE.forget_inherited)


def start_structure_worker() -> None:
    """Start this process's structure worker in a background thread, if it has none: a caller that will open a
    run file later (a campaign reads its file back once it has closed it) pays the worker's start (a Python start
    with h5py) while it works, not after."""
    threading.Thread(target=_PROBE_SERVICE.start, name="qmg-lab-probe-start", daemon=True).start()


def _probe_in_child(path: Path, timeout_s: float) -> None:
    """Walk the file's structure in the worker process (module docstring, step 3); DamagedFileError if the walk
    fails, crashes its worker or is not done within timeout_s."""
    _PROBE_SERVICE.walk(path, timeout_s)
