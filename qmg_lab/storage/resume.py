"""Resuming a run file: the read-only checks before anything changes, the repair of a killed file's end, and how
to read a file's status (`qmg_lab.storage.writer.RunWriter.reopen` and the CLI use these; docs/hdf5.md,
docs/reliability.md).
"""

from __future__ import annotations

import json
import os
import socket
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from qmg_lab.instruments import INSTRUMENT_NAMES
from qmg_lab.storage.h5clear import clear_superblock_flags, left_open_without_swmr
from qmg_lab.storage.layout import GROUP_UNITS, DamagedFileError, StorageError, whole_chunk_layout
from qmg_lab.storage.lock import held_here, holder, lock_path, writer_state
from qmg_lab.storage.reader import RunData, read_run, valid_rows
from qmg_lab.storage.runfile import open_run_file
from qmg_lab.storage.salvage import H5_ERRORS, padded_copy, readable_rows
from qmg_lab.storage.superblock import read_superblock

#: the way out when a file cannot be resumed
SALVAGE = "copy what still reads into a new file with `qmg-lab salvage {path} -o NEW.h5` and analyse that"


def check_resumable(
    path: str | Path, *, config_sha256: str, instrument_modes: Mapping[str, str] | None = None
) -> RunData:
    """Read-only: can this file be resumed with this configuration and station? Changes nothing.

    Refuses (StorageError naming what is wrong): a missing or unreadable file; a completed run ("already
    completed"); a file of another configuration (both fingerprints); a file whose writer process is still
    alive; a station whose instruments are not twin/hardware as the file's were (`instrument_modes`,
    "twin" | "hardware" per instrument; files without that attribute: every instrument as `mode` says).
    Returns the file's /steps and root attributes.
    """
    p = Path(path)
    if not p.is_file():
        raise StorageError(f"{p}: no such run file to resume")
    if not ends_short(p):
        return _check_resumable(p, p, config_sha256, instrument_modes, thorough=False)
    # shorter than its superblock's end of file: a write that failed (a full disk) or an incomplete copy. Checked
    # on a copy padded with zeros to that end (nothing here changes the file); the repair plan then reads every
    # column, and refuses if what does not read is more than a kill loses
    tmp = p.with_name(f".{p.name}.{os.getpid()}.check")
    try:
        padded_copy(p, tmp)
        try:  # first without SWMR: metadata lost with the missing bytes fails at once instead of being retried
            with h5py.File(tmp, "r") as h5:
                plan_repair(h5, thorough=True)
        except H5_ERRORS as exc:
            raise DamagedFileError(
                f"{p}: ends before the end of file its superblock records, and what is left cannot be resumed "
                f"({exc}); nothing was changed: {SALVAGE.format(path=p)}"
            ) from None
        return _check_resumable(p, tmp, config_sha256, instrument_modes, thorough=True)
    finally:
        tmp.unlink(missing_ok=True)


def heal_interrupted_open(path: Path) -> bool:
    """A writer killed between opening the file for writing and switching it to SWMR (the first moments of a new
    file's or a resume's write, before any data is written) leaves the superblock marked "open for writing, not
    SWMR", which no reader can open. Once the lock says that writer is gone (the caller holds it), the marks are
    cleared (what `h5clear -s` does; qmg_lab/storage/h5clear.py): the only change made to a file before every
    resume check passed, and it changes no data. True if it cleared them. StorageError: no HDF5 file."""
    if (not held_here(path) and writer_state(path) == "writing") or not left_open_without_swmr(path):
        return False
    clear_superblock_flags(path)
    return True


def ends_short(path: Path) -> bool:
    """The file ends before the end-of-file address its superblock records (superblock.py); StorageError if
    there is no such file or it is no HDF5 file."""
    if not Path(path).is_file():
        raise StorageError(f"{path}: no such run file to resume")
    sb = read_superblock(path)
    return sb.eof_address is not None and os.path.getsize(path) < sb.eof_address


def _check_resumable(
    p: Path, readable: Path, config_sha256: str, instrument_modes: Mapping[str, str] | None, *, thorough: bool
) -> RunData:
    """check_resumable's checks of the run file `p`, read from `readable` (p itself or its padded copy)."""
    run = read_run(readable, select=("steps",))
    if run.status == "completed":
        done, planned = run.attrs.get("completed_steps", "?"), run.attrs.get("planned_steps", "?")
        raise StorageError(
            f"{p}: the run is already completed ({done} of {planned} steps); there is nothing "
            f"to resume: analyse it with `qmg-lab analyze {p}`, or start a new run with -o"
        )
    stored = run.attrs.get("config_sha256", "")
    if stored != config_sha256:
        raise StorageError(
            f"{p}: was written with configuration {stored}, not with this configuration "
            f"{config_sha256}; resume with the configuration the run was started with"
        )
    if not held_here(p) and writer_state(p) == "writing":  # the lock, not the recorded pid (maybe reused)
        raise StorageError(f"{p}: is still being written by another process ({holder(p)}); stop it first")
    if instrument_modes is not None:
        _check_modes(p, file_instrument_modes(run.attrs), dict(instrument_modes))
    with open_run_file(readable) as opened:  # the readers' guarded open: bounded, StorageError in words
        plan = plan_repair(opened.h5, thorough=thorough)
    refuse_discarding_repair(p, plan)
    return run


def file_instrument_modes(attrs: Mapping[str, Any]) -> dict[str, str]:
    """ "twin" | "hardware" per instrument as the file records them (root attribute instrument_modes; files
    without it: every instrument as the root attribute mode says)."""
    raw = attrs.get("instrument_modes")
    if raw:
        try:
            modes = json.loads(raw)
            if isinstance(modes, dict) and set(modes) == set(INSTRUMENT_NAMES):
                return {n: str(modes[n]) for n in INSTRUMENT_NAMES}
        except (TypeError, ValueError):
            pass
    return {n: ("twin" if attrs.get("mode") == "sim" else "hardware") for n in INSTRUMENT_NAMES}


def status_detail(run: RunData) -> str:
    """The file's status as the operator should read it. "running" is what the file says while its writer
    works, and also what a killed writer leaves behind: a "running" file whose lock is free (its writer is gone,
    qmg_lab.storage.lock.writer_state) is "interrupted (process died)"; one written on another host cannot be
    checked (a lock on a network file system does not reliably reach this host)."""
    if run.status != "running":
        return run.status
    pid, host = int(run.attrs.get("writer_pid", -1)), str(run.attrs.get("writer_host", ""))
    if host and host != socket.gethostname():
        return f"running, or interrupted (written on host {host}; its process cannot be checked from here)"
    state = writer_state(run.path)
    if state == "writing":
        return f"running (process {pid} is writing it)"
    if state == "unknown":
        return f"running, or interrupted (its lock file {lock_path(run.path)} cannot be read to check)"
    return "interrupted (process died)"


def _check_modes(path: Path, recorded: dict[str, str], now: dict[str, str]) -> None:
    """Refuse a station whose instruments are not twin/hardware as the file's were, saying how to match it."""
    diff = [n for n in INSTRUMENT_NAMES if recorded.get(n) != now.get(n)]
    if not diff:
        return
    what = ", ".join(f"{n} was {recorded.get(n)}, now {now.get(n)}" for n in diff)
    if all(v == "twin" for v in recorded.values()):
        hint = "the run was made on the twins: resume it with --sim"
    elif all(v == "hardware" for v in recorded.values()):
        hint = "the run was made on the bench: resume it without --sim, every instrument with sim = false"
    else:
        hint = (
            "set sim = true for exactly the instruments that were twins ("
            + ", ".join(n for n in INSTRUMENT_NAMES if recorded.get(n) == "twin")
            + ") and do not pass --sim"
        )
    raise StorageError(
        f"{path}: the station does not match the run's instruments ({what}); a run continues "
        f"on the instruments it started on: {hint}"
    )


#: a repair may cut at most what a kill loses: the data of the last flush (on the twins /truth is handed over in
#: whole chunks behind /lockin, 16384 samples = 9.1 s at 1800 Sa/s; on the bench a flush carries about a second)
#: plus the last lock-in block whose /table and /chamber readings were not in. The bound is two /lockin chunks of
#: time, two /table reading intervals and this margin (s); a repair that would cut more is not repairing a kill:
#: the file's end is damaged, and the resume refuses instead of discarding what the file holds
REPAIR_CUT_MARGIN_S = 5.0


@dataclass(frozen=True)
class RepairPlan:
    """Where a reopened file will end (`plan_repair`): rows kept per group, /steps rows kept (a prefix), the end
    instant, and what the cut drops."""

    rows: dict[str, int]
    steps_rows: int
    t_end: float
    #: the latest time the file shows as recorded: its last valid /lockin time, or the end of its latest
    #: "completed" step if later (a step's row is written only after its data), s (-inf: none)
    t_recorded: float
    dropped_steps: list[int]
    max_cut_s: float  # what a kill can lose in this file's layout (REPAIR_CUT_MARGIN_S)

    @property
    def cut_s(self) -> float:
        """Recorded time the repair cuts, s."""
        if not np.isfinite(self.t_recorded):
            return 0.0
        return self.t_recorded - (self.t_end if np.isfinite(self.t_end) else 0.0)


def plan_repair(h5: h5py.File, *, thorough: bool = False) -> RepairPlan:
    """Read-only: where a killed file can end on one consistent instant (RunWriter.reopen steps 1-3).

    1. every group keeps its whole rows that are data: its shortest column, no row at or after a fill value (NaN)
       in any of its columns (the last FILL_CHECK_ROWS; every row when thorough), and of its time column only the
       rows `valid_rows` accepts (rows a kill left allocated but unwritten hold the fill value, NaN in qmg-lab/2 files
       and the later /1 ones, 0.0 in the earliest: never data);
    2. the end instant is the last /lockin time, or the last /truth time if earlier (unless /truth has no rows);
       in the twins' whole-chunk layout it moves back to the last /table or /chamber reading at or before it;
    3. /steps keeps its leading rows that are "completed" and end at or before that instant.

    thorough (a file that ended short and was padded with zeros: a write failed, e.g. on a full disk): every
    column is read, and each group keeps only the rows every one of its columns can read.
    """
    rows: dict[str, int] = {}
    times: dict[str, np.ndarray] = {}
    for g in [g for g in GROUP_UNITS if g in h5]:
        n = min(h5[g][c].shape[0] for c in h5[g])
        if thorough:
            n = min(readable_rows(h5[g][c], n) for c in h5[g])
        n = min(_written_rows(h5[g][c], n, 0 if thorough else max(n - FILL_CHECK_ROWS, 0)) for c in h5[g])
        t = h5[g]["time"][:n]
        n = valid_rows(t)
        rows[g], times[g] = n, t[:n]
    t_data_end = float(times["lockin"][-1]) if rows.get("lockin") else -np.inf
    t_end = t_data_end
    if rows.get("truth"):  # a writer that never logs truth keeps its lock-in
        t_end = min(t_end, float(times["truth"][-1]))
    if whole_chunk_layout(h5):
        # written in whole chunks: the file may end inside a lock-in block whose /table and /chamber readings
        # (stamped with the block's last sample) were cut. End on the last block that has its readings, so the
        # resumed file keeps one reading per block across the resume point
        ends = []
        for g in ("table", "chamber"):
            t = times.get(g, np.empty(0))
            k = int(np.searchsorted(t, t_end, side="right"))
            if k:
                ends.append(float(t[k - 1]))
        if ends:
            t_end = max(ends)
    for g, t in times.items():
        rows[g] = int(np.searchsorted(t, t_end, side="right"))
    steps = h5["steps"]
    n = min(steps[c].shape[0] for c in steps)
    status, t_ends, index = steps["status"][:n], steps["t_end"][:n], steps["index"][:n]
    ok = (status == b"completed") & (t_ends <= t_end)
    keep = int(np.argmin(ok)) if not ok.all() else n
    dropped = [int(i) for i, s in zip(index[keep:], status[keep:], strict=True) if s == b"completed"]
    done = t_ends[(status == b"completed") & np.isfinite(t_ends)]
    t_recorded = max(t_data_end, float(done.max())) if done.shape[0] else t_data_end
    return RepairPlan(
        rows=rows,
        steps_rows=keep,
        t_end=t_end,
        t_recorded=t_recorded,
        dropped_steps=dropped,
        max_cut_s=_max_cut_s(h5, times),
    )


#: rows at the end of every column a repair reads for fill values (NaN: allocated, never written): twice what the
#: writer's chunk cache holds per dataset (1 MiB of float64, qmg_lab.storage.writer.WRITER_CACHE), the most a
#: failed flush (a full disk) can leave unwritten behind rows whose time did reach the disk
FILL_CHECK_ROWS = 1 << 18


def _written_rows(ds: h5py.Dataset, n: int, start: int) -> int:
    """Rows of `ds` before its first fill value (NaN) at or after row `start`, at most n. A full disk can leave a
    column's chunk unwritten while the group's time reached the disk: those rows hold the fill value and are never
    data (the campaign writes no NaN)."""
    if n <= start:
        return n
    bad = np.flatnonzero(np.isnan(ds[start:n]))
    return start + int(bad[0]) if bad.size else n


def _max_cut_s(h5: h5py.File, times: dict[str, np.ndarray]) -> float:
    """What a kill can lose at the end of this file, s: two /lockin chunks of samples, two /table intervals and
    REPAIR_CUT_MARGIN_S (the spacings from the file's own last rows)."""

    def spacing(t: np.ndarray) -> float:
        return float(t[-1] - t[-2]) if t.shape[0] >= 2 else 0.0

    lockin = times.get("lockin", np.empty(0))
    chunk = h5["lockin"]["time"].chunks
    chunk_s = spacing(lockin) * (chunk[0] if chunk else 1)
    return 2.0 * chunk_s + 2.0 * spacing(times.get("table", np.empty(0))) + REPAIR_CUT_MARGIN_S


def refuse_discarding_repair(path: Path, plan: RepairPlan) -> None:
    """A resume never discards recorded data beyond what a kill loses: refuse (StorageError, nothing changed) a
    repair that would cut more recorded time (the later of the last valid /lockin time and the end of the last
    completed step) than a kill loses (`max_cut_s`)."""
    cut = plan.cut_s
    kept_end = plan.t_end if np.isfinite(plan.t_end) else 0.0
    if cut > plan.max_cut_s:
        raise StorageError(
            f"{path}: resuming would discard {cut:.1f} s of recorded data (the file records data up to "
            f"{plan.t_recorded:.1f} s, its groups only agree up to {kept_end:.1f} s) and the completed "
            f"steps {plan.dropped_steps}: the file's end is damaged beyond what a killed process leaves "
            f"(at most {plan.max_cut_s:.1f} s here). Nothing was changed; analyse it as it is "
            f"(qmg-lab analyze {path}), or {SALVAGE.format(path=path)}"
        )


def _cut(ds: h5py.Dataset, n: int) -> None:
    if ds.shape[0] > n:
        ds.resize((n,))


def repair_end(h5: h5py.File, plan: RepairPlan | None = None) -> RepairPlan:
    """Make a reopened (SWMR-writing) file end on one consistent instant, in an order that a kill at any point
    of it leaves a file the next repair finishes correctly.

    Shrinking a chunked dataset makes HDF5 write fill values into the part of its last partial chunk beyond the
    new end at once, while the new extent reaches the file only at the next flush: a kill in between leaves the
    old row count with fill values at the end. So every time column is cut first, each followed by a flush (its
    new extent is on disk before any other column of its group changes); then the other columns. Fill values a
    kill leaves in a time column are not data to `valid_rows`, and those in the other columns lie beyond their
    group's time, so the next `plan_repair` never takes them as data. /steps likewise: its status column first
    (a fill value is not "completed"), flushed, then the others.
    """
    plan = plan or plan_repair(h5)
    groups = [g for g in GROUP_UNITS if g in h5]
    for g in groups:
        if h5[g]["time"].shape[0] > plan.rows[g]:
            _cut(h5[g]["time"], plan.rows[g])
            h5.flush()
    for g in groups:
        for c in h5[g]:
            _cut(h5[g][c], plan.rows[g])
    steps = h5["steps"]
    if steps["status"].shape[0] > plan.steps_rows:
        _cut(steps["status"], plan.steps_rows)
        h5.flush()
    for c in steps:
        _cut(steps[c], plan.steps_rows)
    h5.flush()
    return plan


def kept_checkpoints(path: Path) -> dict[int, tuple[float, float]]:
    """Read-only: the checkpoints a plain resume of the file keeps (its repair plan: the leading "completed" /steps
    rows whose data are in), index -> (t_start, t_end), s. A file a full disk left short is read from a copy padded
    to its recorded end, as its resume reads it."""
    short = ends_short(path)
    source = path.with_name(f".{path.name}.{os.getpid()}.padded") if short else path
    if short:
        padded_copy(path, source)
    try:
        with h5py.File(source, "r", swmr=True, libver="latest") as h5:
            n = plan_repair(h5, thorough=short).steps_rows
            cols = [h5["steps"][c][:n] for c in ("index", "t_start", "t_end")]
    finally:
        if short:
            source.unlink()
    return {int(i): (float(a), float(b)) for i, a, b in zip(*cols, strict=True)}
