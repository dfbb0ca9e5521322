"""The run file: a crash-safe, self-describing HDF5 file in the "qmg-lab/1" layout (docs/hdf5.md).

Protocol (docs/hdf5.md):

* `RunWriter.create` makes every group and every dataset up front — 1-D, chunked, unlimited `maxshape`, with a
  `units` and a `description` attribute — writes the root attributes, then switches the file to HDF5 SWMR
  (single-writer/multiple-reader) mode: `libver="latest"`, `file.swmr_mode = True`. From then on HDF5 orders its
  metadata writes so that the file on disk is always a consistent snapshot as of the last flush: a process
  killed at any instant leaves a file that h5py opens (with `swmr=True`; `read_run` does this), having lost only
  what was appended after the last flush.
* Appends go to a small per-group memory buffer. The buffers are handed to one writer thread
  (qmg_lab/storage/background.py), which writes them, compressing the chunks inside HDF5 while the campaign goes
  on: asynchronously, followed by a file flush, when `maybe_flush` finds that `flush_interval_s` of wall time has
  passed; synchronously (the call returns once they are written) on `flush`, on every `append_step` and
  `set_status`, and on `close`. A step row with status "completed" is therefore a checkpoint: every sample
  appended before it is in the file when the row is. Past BUFFER_ROWS_MAX buffered rows the buffers are handed
  over early (no file flush); at most two hand-overs wait for the thread, so memory does not grow with the data
  one flush interval carries.
* A kill can land between two datasets' resizes, so the columns of a group may differ in length by one block;
  `read_run` and `RunWriter.reopen` cut every group to its shortest column (rows are only valid when complete).
* Layout for the write pattern (qmg_lab/storage/layout.py, docs/hdf5.md): big chunks when the writer is faster
  than real time (twins), small ones when a flush carries a second of data (`realtime=True`, hardware); shuffle +
  the file's compression only on the columns that compress.
* Resume (`check_resumable`, then `reopen` once the station is connected): nothing changes in the file until every
  check passed (not completed, same configuration, writer gone, same twin/hardware instruments). HDF5 marks a
  file opened for (SWMR) writing in the superblock's consistency flags; after a crash these flags stay set and
  HDF5 refuses to open the file for writing ("may use h5clear"). `reopen` clears them itself
  (`qmg_lab.storage.h5clear.clear_superblock_flags`, the equivalent of `h5clear -s`), then cuts the file to one
  consistent instant and drops the checkpoints that end after it.

Why one module of this length: the writer's crash-safety rules (SWMR, chunk hand-over to the writer thread,
checkpoints, resume) depend on each other; the layout, reading, resume checks, records and the study level
are in their own modules of this package.
"""

from __future__ import annotations

import datetime as _dt
import errno
import json
import math
import os
import re
import secrets
import socket
import time as _time
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import Any

import h5py
import numpy as np
from h5py import h5s

from qmg_lab.instruments import INSTRUMENT_MODES, INSTRUMENT_NAMES
from qmg_lab.storage.background import BackgroundWrites
from qmg_lab.storage.deflate import shuffled_deflate
from qmg_lab.storage.h5clear import clear_superblock_flags, writer_flags_set
from qmg_lab.storage.holders import named_holders
from qmg_lab.storage.layout import (  # noqa: F401 - re-exported names are part of the API
    CHAMBER_UNITS,
    CHUNK_ROWS,
    CHUNK_ROWS_REALTIME,
    CLSF_UNITS,
    COMPRESSED_COLUMNS,
    COMPRESSED_COLUMNS_REALTIME,
    COMPRESSED_GROUPS,
    COMPRESSIONS,
    DESCRIPTIONS,
    FORMAT,
    GROUP_UNITS,
    GZIP_LEVEL,
    GZIP_LEVELS,
    KIND_BYTES,
    LOCKIN_UNITS,
    MODES,
    OPTIONAL_COLUMNS,
    STATUS_BYTES,
    STATUSES,
    STEPS_DTYPES,
    STEPS_UNITS,
    TABLE_UNITS,
    TRUTH_UNITS,
    StorageError,
    _text,
    column_dtype,
    whole_chunk_layout,
)
from qmg_lab.storage.lock import RunFileLock
from qmg_lab.storage.reader import RunData, read_run, read_window
from qmg_lab.storage.records import RunRecords, create_groups
from qmg_lab.storage.resume import (
    check_resumable,
    ends_short,
    file_instrument_modes,
    plan_repair,
    refuse_discarding_repair,
    repair_end,
    status_detail,
)
from qmg_lab.storage.superblock import read_superblock

#: the writer's chunk cache per dataset. HDF5 2.0 defaults to 8 MiB per open dataset, and the writer keeps ~30
#: datasets open: 1 MiB (8 fast-group chunks) holds every partial chunk until its flush; w0 = 1 evicts fully
#: written chunks first (an append-only pattern never comes back to them)
WRITER_CACHE: dict[str, Any] = {"rdcc_nbytes": 1 << 20, "rdcc_w0": 1.0}

#: rows buffered in memory (all groups) before they are handed to HDF5 without a file flush: about 12 MB of
#: buffers, so a writer's memory does not depend on how much data one wall-clock flush interval carries
BUFFER_ROWS_MAX = 131072

__all__ = [
    "CHAMBER_UNITS",
    "CLSF_UNITS",
    "FORMAT",
    "GROUP_UNITS",
    "LOCKIN_UNITS",
    "STEPS_UNITS",
    "TABLE_UNITS",
    "TRUTH_UNITS",
    "ResumeState",
    "RunData",
    "RunFileWriteError",
    "RunWriter",
    "StorageError",
    "file_instrument_modes",
    "read_run",
    "read_window",
    "status_detail",
    "writer_flags_set",
]


@dataclass(frozen=True)
class ResumeState:
    """What a run file says about the moment its writer stopped (for `--resume`)."""

    last_time: float | None  # None: no lock-in sample yet (the resumed run starts at t = 0)
    rho_ref: float | None
    gain_correction: float | None
    chamber_setpoint_c: float | None
    chamber_temperature_c: float | None
    gyro_temperature_c: float | None
    table_angle_deg: float | None = None  # the table's angle at last_time (its last position reading)

    def as_dict(self) -> dict[str, float | None]:
        return dict(self.__dict__)


class RunWriter:
    """Appends campaign data to a qmg-lab/1 run file in SWMR mode. Use `create` or `reopen`, not the constructor.

    Not thread-safe: one writer object, one thread. Usable as a context manager: an exception leaving the
    `with` block marks the run "aborted" with the exception as `abort_reason`, then closes the file.
    """

    def __init__(
        self,
        path: Path,
        h5: h5py.File,
        *,
        flush_interval_s: float,
        clock: Callable[[], float] = _time.monotonic,
        lock: RunFileLock | None = None,
    ) -> None:
        if not flush_interval_s > 0:
            raise StorageError(f"{path}: flush_interval_s must be > 0 s, got {flush_interval_s!r}")
        self._lock = lock  # the file's one-writer lock, released by close()
        self._failed = False  # a write failed (RunFileWriteError): nothing more is written
        self._write_error: RunFileWriteError | None = None
        self.path = path
        self._h5 = h5
        self.flush_interval_s = float(flush_interval_s)
        self._clock = clock
        self._last_flush = clock()
        self._groups = [g for g in GROUP_UNITS if g in h5]
        # dataset handles looked up once: an h5py lookup by name costs more than a small append
        self._ds: dict[str, list[tuple[str, h5py.Dataset]]] = {
            g: [(c, h5[g][c]) for c in GROUP_UNITS[g] if c in h5[g] or c not in OPTIONAL_COLUMNS.get(g, ())]
            for g in self._groups
        }
        # each column's stored dtype (layout.COLUMN_DTYPES): appended values are converted to it
        self._dtypes: dict[str, list[np.dtype[Any]]] = {g: [ds.dtype for _, ds in cols] for g, cols in self._ds.items()}
        # per group: blocks of rows appended as arrays (one array per column, in the group's column order, held by
        # reference until written), and single rows appended as numbers (append_row), joined into a block at the
        # next hand-over or array append of their group
        self._buffer: dict[str, list[tuple[np.ndarray, ...]]] = {g: [] for g in self._groups}
        self._rows: dict[str, list[tuple[float, ...]]] = {g: [] for g in self._groups}
        self._buffered_rows = 0
        self._last_time: dict[str, float] = {}
        for g in self._groups:
            t = h5[g]["time"]
            self._last_time[g] = float(t[t.shape[0] - 1]) if t.shape[0] else -np.inf
        steps = h5["steps"]
        self._completed: set[int] = {
            int(i) for i, s in zip(steps["index"][:], steps["status"][:], strict=True) if s == b"completed"
        }
        self._completed_in_file = set(self._completed)  # the "completed" rows in the file (the rest wait)
        # rows of each group handed to the writer thread (stored or on their way)
        self._handed: dict[str, int] = {g: int(h5[g]["time"].shape[0]) for g in self._groups}
        # the twins' layout (every /lockin column compressed): /lockin and /truth are handed over in whole chunks
        # only, so no flush leaves a dead copy of a compressed partial chunk behind (docs/hdf5.md); the rest waits
        # in memory for the next chunk, `flush(complete=True)`, `set_status` or `close`
        self._whole_chunk_rows: dict[str, int] = (
            {g: int(h5[g]["time"].chunks[0]) for g in ("lockin", "truth") if g in h5} if whole_chunk_layout(h5) else {}
        )
        # the shuffle + gzip columns of those groups: their chunks are compressed here (qmg_lab/storage/deflate.py)
        self._direct_chunk_rows: dict[tuple[str, str], int] = {
            (g, c): self._whole_chunk_rows.get(g, 0) if ds.compression == "gzip" and ds.shuffle else 0
            for g in self._groups
            for c, ds in self._ds[g]
        }
        # /steps rows waiting for their data: (row, rows of each whole-chunk group appended before the row)
        self._pending_steps: list[tuple[dict[str, Any], dict[str, int]]] = []
        self._closed = False
        # the HDF5 writes (and the chunk compression inside them) run on this thread, beside the campaign
        self._bg = BackgroundWrites(f"qmg-lab writer {path.name}")

    # ---- construction ---------------------------------------------------------------------------------------

    @classmethod
    def create(
        cls,
        path: str | Path,
        *,
        config_text: str,
        config_sha256: str,
        mode: str,
        software_version: str,
        t0_unix: float,
        flush_interval_s: float = 1.0,
        compression: str = "lzf",
        truth: bool,
        planned_steps: int = -1,
        planned_step_kinds: Iterable[str] = (),
        instrument_modes: Mapping[str, str] | None = None,
        realtime: bool = False,
        extra_attrs: Mapping[str, Any] | None = None,
        extra_layout: Callable[[h5py.File], None] | None = None,
        clock: Callable[[], float] = _time.monotonic,
    ) -> RunWriter:
        """Create a new run file (refuses to overwrite), lay out every group and dataset, start SWMR.

        instrument_modes: "twin" | "hardware" per instrument (root attribute instrument_modes, JSON), what
        --resume checks; default: every instrument as `mode` says. realtime: the data arrive in real time (a
        hardware lock-in), so each flush carries about a second of data: smaller chunks (CHUNK_ROWS_REALTIME).

        planned_steps / planned_step_kinds: the plan's length and its step kinds (root attributes
        `planned_steps`, `planned_step_kinds` as a JSON list); may also be set later with `set_plan`.
        extra_attrs: further root attributes (scalars or strings), written before SWMR starts.
        extra_layout: called with the open file before SWMR starts, to lay out further groups (SWMR cannot create
        objects later): the study storage level (qmg_lab/storage/study_level.py).
        """
        p = Path(path)
        if mode not in MODES:
            raise StorageError(f"{p}: mode must be one of {MODES}, got {mode!r}")
        if compression not in COMPRESSIONS:
            raise StorageError(f"{p}: compression must be one of {COMPRESSIONS}, got {compression!r}")
        modes = (
            dict(instrument_modes)
            if instrument_modes is not None
            else {n: ("twin" if mode == "sim" else "hardware") for n in INSTRUMENT_NAMES}
        )
        if set(modes) != set(INSTRUMENT_NAMES) or not set(modes.values()) <= set(INSTRUMENT_MODES):
            raise StorageError(
                f"{p}: instrument_modes must give each of {INSTRUMENT_NAMES} one of {INSTRUMENT_MODES}, got {modes!r}"
            )
        if not np.isfinite(t0_unix):
            raise StorageError(f"{p}: t0_unix must be a finite number of seconds, got {t0_unix!r}")
        if not p.parent.is_dir():
            raise StorageError(f"{p}: directory {p.parent} does not exist")
        lock = RunFileLock(p).acquire()  # one writer per file (qmg_lab/storage/lock.py); released by close()
        try:
            if p.exists():
                raise StorageError(f"{p}: already exists; choose another output file or resume it with --resume")
            h5 = cls._lay_out(
                p,
                lambda h5: cls._write_layout(
                    h5,
                    p,
                    config_text=config_text,
                    config_sha256=config_sha256,
                    mode=mode,
                    software_version=software_version,
                    t0_unix=t0_unix,
                    flush_interval_s=flush_interval_s,
                    compression=compression,
                    truth=truth,
                    planned_steps=planned_steps,
                    planned_step_kinds=planned_step_kinds,
                    modes=modes,
                    realtime=realtime,
                    extra_attrs=extra_attrs,
                    extra_layout=extra_layout,
                ),
            )
        except BaseException:
            lock.release()
            raise
        return cls(p, h5, flush_interval_s=flush_interval_s, clock=clock, lock=lock)

    @staticmethod
    def _lay_out(p: Path, write_layout: Callable[[h5py.File], None]) -> h5py.File:
        """Lay the file out under a hidden name unique to this process, close it, move it into place without
        replacing anything, then open it again and start SWMR. A process killed while laying it out leaves no
        half-made file at `p` (its hidden file is removed by the next writer of `p`, who holds the lock); and
        no file is renamed while open (Windows cannot)."""
        for stale in p.parent.glob(f".{p.name}.*.creating"):  # left by killed writers: never a run's data
            stale.unlink(missing_ok=True)
        tmp = p.with_name(f".{p.name}.{os.getpid()}-{secrets.token_hex(4)}.creating")
        try:
            h5 = h5py.File(tmp, "w-", libver="latest", **WRITER_CACHE)
        except OSError as exc:
            raise StorageError(f"{p}: cannot create the run file: {exc}") from None
        try:
            try:
                write_layout(h5)
            finally:
                h5.close()
            _move_into_place(tmp, p)
        except BaseException:
            tmp.unlink(missing_ok=True)
            raise
        h5 = _open_for_writing(p, "the new run file")
        try:
            h5.swmr_mode = True
        except OSError as exc:
            h5.close()
            raise StorageError(f"{p}: cannot start SWMR on the new run file: {exc}") from None
        return h5

    @staticmethod
    def _write_layout(
        h5: h5py.File,
        p: Path,
        *,
        config_text: str,
        config_sha256: str,
        mode: str,
        software_version: str,
        t0_unix: float,
        flush_interval_s: float,
        compression: str,
        truth: bool,
        planned_steps: int,
        planned_step_kinds: Iterable[str],
        modes: Mapping[str, str],
        realtime: bool,
        extra_attrs: Mapping[str, Any] | None,
        extra_layout: Callable[[h5py.File], None] | None,
    ) -> None:
        """The root attributes, every group and dataset (`create`), written before SWMR starts."""
        a = h5.attrs
        a["format"] = FORMAT
        a["created"] = _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds").replace("+00:00", "Z")
        a["t0_unix"] = float(t0_unix)
        a["software_version"] = software_version
        a["mode"] = mode
        a["config_toml"] = config_text
        a["config_sha256"] = config_sha256
        a["status"] = "running"
        a["abort_reason"] = ""
        a["completed_steps"] = 0
        a["resume_count"] = 0
        a["planned_steps"] = int(planned_steps)
        a["planned_step_kinds"] = json.dumps(list(planned_step_kinds))
        a["instrument_modes"] = json.dumps({n: modes[n] for n in INSTRUMENT_NAMES})
        a["compression"] = compression
        a["flush_interval_s"] = float(flush_interval_s)
        a["writer_pid"] = os.getpid()
        a["writer_host"] = socket.gethostname()
        a["clsf_reference"] = np.nan  # set by set_clsf_reference; created now: SWMR cannot add attributes safely
        for k, v in (extra_attrs or {}).items():
            if k in a:
                raise StorageError(f"{p}: extra attribute {k!r} clashes with a contract attribute")
            a[k] = v
        filt: dict[str, Any] = {}
        if compression == "gzip":
            filt = {"compression": "gzip", "compression_opts": GZIP_LEVEL, "shuffle": True}
        elif compression == "lzf":
            filt = {"compression": "lzf", "shuffle": True}
        rows = CHUNK_ROWS_REALTIME if realtime else CHUNK_ROWS
        compressed = COMPRESSED_COLUMNS_REALTIME if realtime else COMPRESSED_COLUMNS
        for g, units in GROUP_UNITS.items():
            if g == "truth" and not truth:
                continue
            grp = h5.create_group(g)
            for col, unit in units.items():
                dtype = column_dtype(g, col)
                ds = grp.create_dataset(
                    col,
                    shape=(0,),
                    maxshape=(None,),
                    dtype=dtype,
                    chunks=(rows[g],),
                    # rows allocated but never written are never data (resume.valid_rows reads the time column)
                    fillvalue=np.nan if np.dtype(dtype).kind == "f" else 0,
                    **(_filter(filt, col) if col in compressed.get(g, ()) else {}),
                )
                ds.attrs["units"] = unit
                ds.attrs["description"] = DESCRIPTIONS[f"{g}/{col}"]
        grp = h5.create_group("steps")
        for col, dtype in STEPS_DTYPES.items():
            fill = {"fillvalue": np.nan} if np.dtype(dtype).kind == "f" else {}
            ds = grp.create_dataset(col, shape=(0,), maxshape=(None,), dtype=dtype, chunks=(rows["steps"],), **fill)
            ds.attrs["units"] = STEPS_UNITS[col]
            ds.attrs["description"] = DESCRIPTIONS[f"steps/{col}"]
        create_groups(h5)  # /snapshots, /events (qmg_lab/storage/records.py): laid out before SWMR
        if extra_layout is not None:
            extra_layout(h5)

    @staticmethod
    def check_resumable(
        path: str | Path, *, config_sha256: str, instrument_modes: Mapping[str, str] | None = None
    ) -> RunData:
        """Read-only: can this file be resumed with this configuration and station? Changes nothing
        (qmg_lab.storage.resume.check_resumable: completed, configuration, live writer, instruments)."""
        return check_resumable(path, config_sha256=config_sha256, instrument_modes=instrument_modes)

    @classmethod
    def reopen(
        cls,
        path: str | Path,
        *,
        config_sha256: str,
        flush_interval_s: float = 1.0,
        instrument_modes: Mapping[str, str] | None = None,
        clock: Callable[[], float] = _time.monotonic,
    ) -> RunWriter:
        """Reopen a run file to resume it (after a crash or an abort). Call it once the station is connected:
        this is the first step that changes the file.

        First every check of `check_resumable` (nothing is changed if one fails). Then: clears the crash flags,
        restarts SWMR, and makes the file end on a consistent instant:
        1. every group is cut to its shortest column (whole rows only);
        2. the end instant is the last /lockin time, or the last /truth time if that is earlier (a kill can
           fall between the two groups' writes; /truth stays aligned sample for sample with /lockin) unless
           /truth has no rows at all; in the twins' layout (written in whole chunks) it moves back to the last
           /table or /chamber reading, the end of the last lock-in block whose readings are in; /lockin
           and /truth are cut to it and every other group to rows at or before it;
        3. /steps keeps only "completed" rows that end at or before that instant: a checkpoint whose data did
           not all reach the disk is not a checkpoint, and the step is run again after the resume point.
        Then status "running" (abort_reason ""), completed_steps recounted, resume_count incremented.
        """
        p = Path(path)
        lock = RunFileLock(p).acquire()  # one writer per file (qmg_lab/storage/lock.py); released by close()
        try:
            h5 = cls._reopen_repaired(p, config_sha256, instrument_modes)
        except BaseException:
            lock.release()
            raise
        return cls(p, h5, flush_interval_s=flush_interval_s, clock=clock, lock=lock)

    @classmethod
    def _reopen_repaired(cls, p: Path, config_sha256: str, instrument_modes: Mapping[str, str] | None) -> h5py.File:
        """`reopen`'s checks and repair, under the file's lock: the open, repaired file in SWMR mode."""
        short = ends_short(p)
        run = cls.check_resumable(p, config_sha256=config_sha256, instrument_modes=instrument_modes)
        if short:  # a write failed (a full disk, since freed): the space HDF5 had allocated, as zeros
            os.truncate(p, read_superblock(p).eof_address or 0)
        if run.writer_open or short:
            clear_superblock_flags(p)
        h5 = _open_for_writing(p, "the run file")
        try:
            plan = plan_repair(h5, thorough=short)  # where it can end; refused if that discards data
            refuse_discarding_repair(p, plan)
            create_groups(h5)  # files from before /snapshots and /events get them here, before SWMR
            h5.swmr_mode = True  # from here on a kill (even inside this repair) leaves a consistent file
            repair_end(h5, plan)
            steps = h5["steps"]
            h5.attrs["status"] = "running"
            h5.attrs["abort_reason"] = ""
            h5.attrs["completed_steps"] = int(np.unique(steps["index"][:]).shape[0])
            h5.attrs["resume_count"] = int(h5.attrs.get("resume_count", 0)) + 1
            h5.attrs["writer_pid"] = os.getpid()
            h5.attrs["writer_host"] = socket.gethostname()
            h5.flush()
        except BaseException:
            h5.close()
            raise
        return h5

    # ---- appending ------------------------------------------------------------------------------------------

    def append(self, group: str, **columns: np.ndarray) -> None:
        """Buffer rows for `group`: every column of the group, 1-D, same length; time finite and non-decreasing.

        The arrays are kept by reference until the writer thread has written them: the caller must not write into
        them afterwards (the campaign hands over fresh arrays every block)."""
        self._check_open()
        self._columns_of(group, columns, "append")
        expected = [c for c, _ in self._ds[group]]  # the file's columns (an older file may lack optional ones)
        arrays = [np.asarray(columns[c], dtype=d) for c, d in zip(expected, self._dtypes[group], strict=True)]
        for i, arr in enumerate(arrays):
            if arr.ndim == 0:
                arrays[i] = arr.reshape(1)
        t = arrays[0]
        n = t.shape[0]
        for c, arr in zip(expected, arrays, strict=True):
            if arr.ndim != 1 or arr.shape[0] != n:
                raise StorageError(
                    f"{self.path}: /{group}/{c} has shape {arr.shape}; every column of the append "
                    f"must be 1-D with {n} rows like /{group}/time"
                )
        if n == 0:
            return
        first, last = float(t[0]), float(t[-1])
        # finite ends and no step down in between: then every value is finite (a NaN fails >=, an infinity would
        # need an infinite end); only a failing block pays for finding out which rule it breaks
        ordered = math.isfinite(first) and math.isfinite(last) and (n == 1 or bool((t[1:] >= t[:-1]).all()))
        if not ordered and not np.all(np.isfinite(t)):
            raise StorageError(f"{self.path}: /{group}/time contains NaN or infinite values")
        if not ordered or first < self._last_time[group]:
            raise self._decreasing(group, first)
        self._last_time[group] = last
        if self._rows[group]:  # rows appended one by one before this block go first
            self._join_rows(group)
        self._buffer[group].append(tuple(arrays))
        self._buffered_rows += n
        if self._buffered_rows >= BUFFER_ROWS_MAX:  # bounded memory: hand the rows to HDF5 (no file flush)
            self._hand_over(flush_file=False)

    def append_row(self, group: str, **values: float) -> None:
        """Buffer one row of `group`: every column of the group as a number; time finite and not before the
        group's last. The same rows as `append` with one-element columns, without building an array per value
        (the table and chamber readings of every lock-in block)."""
        self._check_open()
        self._columns_of(group, values, "append_row")
        try:
            row = tuple([float(values[c]) for c, _ in self._ds[group]])
        except (TypeError, ValueError) as exc:
            raise StorageError(f"{self.path}: /{group} append_row needs a number for every column: {exc}") from None
        t = row[0]
        if not math.isfinite(t):
            raise StorageError(f"{self.path}: /{group}/time contains NaN or infinite values")
        if t < self._last_time[group]:
            raise self._decreasing(group, t)
        self._last_time[group] = t
        self._rows[group].append(row)
        self._buffered_rows += 1
        if self._buffered_rows >= BUFFER_ROWS_MAX:
            self._hand_over(flush_file=False)

    def _columns_of(self, group: str, columns: Mapping[str, object], method: str) -> dict[str, str]:
        """The group's columns (name -> units), once `group` and the given column names are checked."""
        expected = GROUP_UNITS.get(group)
        if expected is None:
            raise StorageError(
                f"{self.path}: unknown group {group!r}; groups: {', '.join(GROUP_UNITS)} "
                f"(steps are written with append_step)"
            )
        if group not in self._buffer:
            raise StorageError(f"{self.path}: this file has no /{group} group (created with truth=False)")
        if columns.keys() != expected.keys():
            missing = sorted(set(expected) - set(columns))
            extra = sorted(set(columns) - set(expected))
            raise StorageError(
                f"{self.path}: /{group} {method} needs exactly the columns {list(expected)}; "
                f"missing {missing}, unknown {extra}"
            )
        return expected

    def _decreasing(self, group: str, first: float) -> StorageError:
        return StorageError(
            f"{self.path}: /{group}/time must not decrease (last stored "
            f"{self._last_time[group]:.6f} s, this block starts at {first:.6f} s)"
        )

    def _join_rows(self, group: str) -> None:
        """The rows appended one by one (append_row) become one buffered block, column by column."""
        rows = self._rows[group]
        self._buffer[group].append(tuple(np.array(rows, dtype=np.float64).T.copy()))
        rows.clear()

    def _buffer_group(self, group: str, columns: Sequence[str]) -> None:
        """Buffer and hand over a further group of the file (laid out by `create`'s extra_layout) like the
        contract's groups, its rows given by `_buffer_block` / `_buffer_row` (no checks: the writer's own data)."""
        self._ds[group] = [(c, self._h5[group][c]) for c in columns]
        self._dtypes[group] = [ds.dtype for _, ds in self._ds[group]]
        self._buffer[group], self._rows[group] = [], []
        self._handed[group] = int(self._h5[group][columns[0]].shape[0])
        self._direct_chunk_rows.update({(group, c): 0 for c in columns})

    def _buffer_block(self, group: str, block: tuple[np.ndarray, ...]) -> None:
        """Buffer rows of a `_buffer_group` group: one 1-D float64 array per column, in its column order."""
        if self._rows[group]:
            self._join_rows(group)
        self._buffer[group].append(block)
        self._buffered_rows += block[0].shape[0]

    def _buffer_row(self, group: str, row: tuple[float, ...]) -> None:
        """Buffer one row of a `_buffer_group` group (its values in column order)."""
        self._rows[group].append(row)
        self._buffered_rows += 1

    def append_step(
        self,
        *,
        index: int,
        kind: str,
        t_start: float,
        t_end: float,
        table_rate: float,
        chamber_setpoint: float,
        status: str,
    ) -> None:
        """Append one /steps row: a "completed" row is a checkpoint for --resume, written (and the file flushed)
        right after every sample appended before it. The writer thread writes it (`drain` waits); in the twins'
        layout it goes with the chunk that holds the step's last sample (at most one chunk of simulated time
        later, or at `close`), never before its data."""
        self._check_open()
        kb, sb = kind.encode("utf-8"), status.encode("utf-8")
        if not kb or len(kb) > KIND_BYTES:
            raise StorageError(f"{self.path}: step kind must be 1..{KIND_BYTES} bytes, got {kind!r}")
        if not sb or len(sb) > STATUS_BYTES:
            raise StorageError(f"{self.path}: step status must be 1..{STATUS_BYTES} bytes, got {status!r}")
        if index < 0:
            raise StorageError(f"{self.path}: step index must be >= 0, got {index}")
        row: dict[str, Any] = {
            "index": int(index),
            "kind": kb,
            "t_start": float(t_start),
            "t_end": float(t_end),
            "table_rate": float(table_rate),
            "chamber_setpoint": float(chamber_setpoint),
            "status": sb,
        }
        need = {
            g: self._handed[g] + len(self._rows[g]) + sum(b[0].shape[0] for b in self._buffer[g])
            for g in self._whole_chunk_rows
        }
        self._pending_steps.append((row, need))
        if status == "completed":
            self._completed.add(int(index))
        self._hand_over(flush_file=True)
        self._last_flush = self._clock()

    # ---- queries --------------------------------------------------------------------------------------------

    def completed_steps(self) -> set[int]:
        """Indices of the steps with a "completed" row."""
        return set(self._completed)

    def last_time(self) -> float:
        """Last /lockin/time appended (buffered or stored), s; 0.0 if none: a resumed run continues after it."""
        t = self._last_time.get("lockin", -np.inf)
        return float(t) if np.isfinite(t) else 0.0

    def records(self) -> RunRecords:
        """The /snapshots and /events writer of this file (qmg_lab/storage/records.py)."""
        self._check_open()
        return RunRecords(self._h5, self.path)

    def set_clsf_reference(self, rho_ref: float) -> None:
        """Store the CLSF reference level rho_0 (root attr clsf_reference): a resumed run keeps its reference."""
        self._check_open()
        if self._h5.attrs.get("clsf_reference") != rho_ref:
            self._h5.attrs["clsf_reference"] = float(rho_ref)

    def resume_state(self) -> ResumeState:
        """Where a resumed run continues: last time, CLSF reference and gain, last chamber and truth readings, and
        the table's angle at the last time: its last /table position (deg) + its measured rate (deg/s) x the time
        from that reading to the last lock-in sample (on the twins both fall at the same block's end)."""
        self._check_open()
        self._flush_buffers()

        def last(group: str, col: str) -> float | None:
            if group not in self._h5:
                return None
            ds = self._h5[group][col]
            return float(ds[ds.shape[0] - 1]) if ds.shape[0] else None

        ref = self._h5.attrs.get("clsf_reference")
        has_data = bool(np.isfinite(self._last_time.get("lockin", -np.inf)))
        angle, table_t, table_rate = last("table", "position"), last("table", "time"), last("table", "rate_measured")
        if angle is not None and table_t is not None and table_rate is not None and has_data:
            angle += table_rate * (self.last_time() - table_t)
        return ResumeState(
            last_time=self.last_time() if has_data else None,
            rho_ref=float(ref) if ref is not None and np.isfinite(ref) else None,
            gain_correction=last("clsf", "gain_correction"),
            chamber_setpoint_c=last("chamber", "setpoint"),
            chamber_temperature_c=last("chamber", "temperature"),
            gyro_temperature_c=last("truth", "temperature"),
            table_angle_deg=angle if angle is not None and math.isfinite(angle) else None,
        )

    # ---- flushing and status --------------------------------------------------------------------------------

    def maybe_flush(self) -> None:
        """If `flush_interval_s` of wall time passed since the last flush: hand the buffers to the writer thread,
        which writes them and then flushes the file (asynchronous: `drain` waits for it)."""
        self._check_open()
        if self._clock() - self._last_flush >= self.flush_interval_s:
            self._hand_over(flush_file=True)
            self._last_flush = self._clock()

    def drain(self) -> None:
        """Wait until the writer thread has written (and, if asked, flushed) every row handed to it."""
        self._check_open()
        self._drain()

    def flush(self) -> None:
        """Write every buffered row (and every waiting /steps row) and flush the file to disk (SWMR readers see it
        from now on); returns once done. In the twins' layout this writes a partial chunk that a later write
        rewrites (a dead copy, docs/hdf5.md): the campaign leaves its flushes to `maybe_flush` and `append_step`."""
        self._check_open()
        self._flush_buffers()
        self._flush_file()

    def set_status(self, status: str, abort_reason: str = "") -> None:
        """Set the root status ("running" | "completed" | "aborted") and abort_reason; flushes."""
        self._check_open()
        if status not in STATUSES:
            raise StorageError(f"{self.path}: status must be one of {STATUSES}, got {status!r}")
        self._flush_buffers()
        try:
            self._h5.attrs["status"] = status
            self._h5.attrs["abort_reason"] = abort_reason
        except (OSError, RuntimeError) as exc:
            raise self._write_failed(exc) from exc
        self._flush_file()

    def set_plan(self, planned_steps: int, planned_step_kinds: Iterable[str]) -> None:
        """Store the plan's length and step kinds (root attrs planned_steps, planned_step_kinds as JSON)."""
        self._check_open()
        kinds = list(planned_step_kinds)
        if planned_steps < 0 or (kinds and len(kinds) != planned_steps):
            raise StorageError(
                f"{self.path}: planned_steps ({planned_steps}) must be >= 0 and match the "
                f"{len(kinds)} planned step kinds"
            )
        self._h5.attrs["planned_steps"] = int(planned_steps)
        self._h5.attrs["planned_step_kinds"] = json.dumps(kinds)
        self._flush_file()

    def close(self) -> None:
        """Flush and close (idempotent). Closing clears the superblock's writer flags: a clean file."""
        if self._closed:
            return
        try:
            if not self._failed:
                self._flush_buffers()
        finally:
            self._closed = True
            try:
                self._bg.close()
                self._close_file()
            finally:
                if self._lock is not None:
                    self._lock.release()

    def _close_file(self) -> None:
        """Close the HDF5 file. After a failed write (a full disk) HDF5's close fails too (it cannot extend the
        file to its allocated end): that is not raised again, the file keeps what its last successful flush wrote
        (docs/reliability.md: it resumes once space is freed)."""
        try:
            self._h5.close()
        except (OSError, RuntimeError):
            if not self._failed:
                raise

    @property
    def closed(self) -> bool:
        return self._closed

    @property
    def write_error(self) -> RunFileWriteError | None:
        """The write that failed (a full disk), or None: after one, nothing more was written and the file keeps
        what its last successful flush wrote."""
        return self._write_error

    def __enter__(self) -> RunWriter:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        if exc_type is not None and not self._closed:
            try:
                if _text(self._h5.attrs["status"]) == "running":
                    reason = "interrupted" if issubclass(exc_type, KeyboardInterrupt) else f"{exc_type.__name__}: {exc}"
                    self.set_status("aborted", reason)
            finally:
                self.close()
        else:
            self.close()

    # ---- internals ------------------------------------------------------------------------------------------

    def _check_open(self) -> None:
        if self._closed:
            raise StorageError(f"{self.path}: the run file is closed")

    def _flush_buffers(self, *, complete: bool = True) -> None:
        """Every buffered row (`complete`; else: up to the last whole chunk in the twins' layout) and every /steps
        row whose data are in written to HDF5 (not flushed) when this returns."""
        self._hand_over(flush_file=False, complete=complete)
        self._drain()

    def _drain(self) -> None:
        try:
            self._bg.drain()
        except Exception as exc:
            raise self._write_failed(exc) from exc

    def _write_failed(self, exc: BaseException) -> RunFileWriteError:
        """The StorageError of a failed write; the writer writes nothing more (`close` then only closes)."""
        self._failed = True
        error = RunFileWriteError(self.path, exc)
        if self._write_error is None:
            self._write_error = error
        return error

    def _hand_over(self, *, flush_file: bool, complete: bool = False) -> None:
        """Give the buffered rows to the writer thread: one job writes every group's columns, then the /steps rows
        whose data are all in, then flushes the file if asked (or if it wrote a step row). In the twins' layout
        /lockin and /truth are handed over up to their last whole chunk unless `complete`. The job gets each
        column as the pieces it was appended in (views, no copy here): it joins them itself, or, for a chunk
        compressed here, inside the chunk's byte shuffle (qmg_lab/storage/deflate.py)."""
        batch: list[tuple[h5py.Dataset, list[np.ndarray], int]] = []
        kept = 0
        for g, blocks in self._buffer.items():
            if self._rows[g]:
                self._join_rows(g)
            if not blocks:
                continue
            n = sum(b[0].shape[0] for b in blocks)
            chunk = self._whole_chunk_rows.get(g, 0)
            keep = 0 if complete or not chunk else (self._handed[g] + n) % chunk
            written = _split_blocks(blocks, n - keep)  # `blocks` keeps the last `keep` rows
            kept += keep
            if n > keep:
                # time first: a partial write leaves time the column to be cut
                for i, (c, ds) in enumerate(self._ds[g]):
                    batch.append((ds, [b[i] for b in written], self._direct_chunk_rows[g, c]))
                self._handed[g] += n - keep
        self._buffered_rows = kept
        rows: list[dict[str, Any]] = []
        while self._pending_steps and all(self._handed[g] >= k for g, k in self._pending_steps[0][1].items()):
            rows.append(self._pending_steps.pop(0)[0])  # in order: a row never overtakes an earlier one
        self._completed_in_file |= {int(r["index"]) for r in rows if r["status"] == b"completed"}
        if not batch and not rows and not flush_file:
            return
        h5, completed = self._h5, len(self._completed_in_file)

        def write() -> None:
            for ds, pieces, direct_rows in batch:
                _append_pieces(ds, pieces, direct_rows)
            if rows:
                steps = h5["steps"]
                n = steps["index"].shape[0]
                for c, dtype in STEPS_DTYPES.items():
                    steps[c].resize((n + len(rows),))
                    steps[c][n:] = np.array([r[c] for r in rows], dtype=dtype)
                h5.attrs["completed_steps"] = completed
            if flush_file or rows:
                h5.flush()

        try:
            self._bg.submit(write)
        except Exception as exc:
            raise self._write_failed(exc) from exc

    def _flush_file(self) -> None:
        try:
            self._h5.flush()
        except (OSError, RuntimeError) as exc:
            raise self._write_failed(exc) from exc
        self._last_flush = self._clock()


class RunFileWriteError(StorageError):
    """Writing the run file failed (the campaign aborts to its safe state). `out_of_space`: the disk is full, the
    user's quota or the process's file size limit is reached (ENOSPC, EDQUOT, EFBIG: HDF5 reports the errno in
    its message, h5py as OSError.errno)."""

    def __init__(self, path: Path, cause: BaseException) -> None:
        super().__init__(f"{path}: writing the run file failed: {type(cause).__name__}: {cause}")
        numbers = {getattr(cause, "errno", None)} | {int(n) for n in re.findall(r"errno = (\d+)", str(cause))}
        self.out_of_space = bool(numbers & OUT_OF_SPACE_ERRNOS)
        self.size_limit = errno.EFBIG in numbers


OUT_OF_SPACE_ERRNOS = frozenset({errno.ENOSPC, errno.EFBIG} | ({errno.EDQUOT} if hasattr(errno, "EDQUOT") else set()))


#: how long the writer retries opening a file a reader holds (HDF5's own file lock, errno 11), s: a reader that
#: polls the file (the watch page, `runs`, a test waiting for a checkpoint) holds it for milliseconds at a time
READER_WAIT_S = 3.0


def _open_for_writing(p: Path, what: str) -> h5py.File:
    """Open `p` for writing (not yet SWMR). HDF5 locks a file for each open; a reader that has it open (not as a
    SWMR reader of a SWMR-writing file) makes the open fail with "unable to lock file": retried for READER_WAIT_S,
    then refused with words saying a reader holds it, naming the process where the OS shows it (storage/holders.py)."""
    deadline = _time.monotonic() + READER_WAIT_S
    while True:
        try:
            return h5py.File(p, "r+", libver="latest", **WRITER_CACHE)
        except OSError as exc:
            held = "unable to lock file" in str(exc)
            if held and _time.monotonic() < deadline:
                _time.sleep(0.05)
                continue
            if held:
                who = (
                    named_holders(p) or " (a `qmg-lab analyze`, `watch` or `runs`, or a program using h5py or HDFView)"
                )
                raise StorageError(
                    f"{p}: another process holds {what} open for reading{who}: close it, then run the command again"
                ) from None
            raise StorageError(f"{p}: cannot open {what} for writing: {exc}") from None


def _move_into_place(tmp: Path, p: Path) -> None:
    """Give the closed file `tmp` the name `p`, never replacing a file at `p` (StorageError if one appeared): a hard
    link then the hidden name's removal, or where the file system has no hard links a rename (which on Windows
    refuses an existing target; on POSIX the caller's lock keeps other qmg-lab writers away)."""
    try:
        os.link(tmp, p)
    except FileExistsError:
        raise StorageError(f"{p}: already exists; choose another output file or resume it with --resume") from None
    except OSError:
        if p.exists():
            raise StorageError(f"{p}: already exists; choose another output file") from None
        os.rename(tmp, p)
        return
    tmp.unlink()


def _split_blocks(blocks: list[tuple[np.ndarray, ...]], rows: int) -> list[tuple[np.ndarray, ...]]:
    """Take the first `rows` rows out of `blocks` (buffered blocks, column arrays of equal length): returns them as
    blocks and leaves the rest in `blocks` (a block cut in two is split into views)."""
    taken: list[tuple[np.ndarray, ...]] = []
    left: list[tuple[np.ndarray, ...]] = []
    start = 0
    for b in blocks:
        m = b[0].shape[0]
        if start + m <= rows:
            taken.append(b)
        elif start >= rows:
            left.append(b)
        else:
            cut = rows - start
            taken.append(tuple(c[:cut] for c in b))
            left.append(tuple(c[cut:] for c in b))
        start += m
    blocks[:] = left
    return taken


def _rows_of(pieces: Sequence[np.ndarray], start: int, stop: int) -> list[np.ndarray]:
    """Views of rows [start, stop) of `pieces` taken end to end."""
    out: list[np.ndarray] = []
    first = 0
    for p in pieces:
        end = first + p.shape[0]
        if end > start and first < stop:
            out.append(p[max(start - first, 0) : min(stop, end) - first])
        if end >= stop:
            break
        first = end
    return out


def _joined(pieces: Sequence[np.ndarray]) -> np.ndarray:
    """The pieces as one C-contiguous array (a single contiguous piece is not copied)."""
    return np.ascontiguousarray(pieces[0]) if len(pieces) == 1 else np.concatenate(pieces)


def _append_pieces(ds: h5py.Dataset, pieces: Sequence[np.ndarray], direct_chunk_rows: int = 0) -> None:
    """Extend a 1-D dataset by the rows of `pieces` (float64 arrays, taken end to end) with the HDF5 calls
    themselves: h5py's `ds.resize` + `ds[n:] = data` spend more time building the selection in Python than small
    writes take.

    direct_chunk_rows (a shuffle + gzip column of the twins' layout, whose chunks are written whole): the chunks
    that start at or after the old end are compressed by `shuffled_deflate` straight from the pieces and written
    as stored chunks; only rows that fill an already stored partial chunk (the first append after a resume) go
    through HDF5's filters.
    """
    dsid = ds.id
    n, m = dsid.shape[0], sum(p.shape[0] for p in pieces)
    if m == 0:
        return
    dsid.set_extent((n + m,))
    head = m if not direct_chunk_rows else min(m, -n % direct_chunk_rows)
    if head:
        fspace = dsid.get_space()
        fspace.select_hyperslab((n,), (head,))
        dsid.write(h5s.create_simple((head,)), fspace, _joined(_rows_of(pieces, 0, head)))
    for i in range(head, m, direct_chunk_rows or 1):
        rows = _rows_of(pieces, i, min(i + direct_chunk_rows, m))
        dsid.write_direct_chunk((n + i,), shuffled_deflate(rows, direct_chunk_rows))


def _filter(filt: dict[str, Any], col: str) -> dict[str, Any]:
    """The dataset filter arguments of column `col`: gzip at its own level (GZIP_LEVELS), other filters as given."""
    if filt.get("compression") == "gzip":
        return {**filt, "compression_opts": GZIP_LEVELS.get(col, GZIP_LEVEL)}
    return filt
