"""Resuming a run file: the read-only checks before anything changes, the repair of a killed file's end, and how
to read a file's status (`qmg_lab.storage.writer.RunWriter.reopen` and the CLI use these; docs/hdf5.md,
docs/reliability.md).
"""

from __future__ import annotations

import json
import os
import socket
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from qmg_lab.storage.layout import GROUP_UNITS, INSTRUMENTS, StorageError, whole_chunk_layout
from qmg_lab.storage.reader import RunData, read_run


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
    run = read_run(p, select=("steps",))
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
    if run.writer_open:
        pid, host = int(run.attrs.get("writer_pid", -1)), run.attrs.get("writer_host", "")
        if host == socket.gethostname() and pid > 0 and pid != os.getpid() and _pid_alive(pid):
            raise StorageError(f"{p}: is still open for writing by process {pid} on {host}; stop it first")
    if instrument_modes is not None:
        _check_modes(p, file_instrument_modes(run.attrs), dict(instrument_modes))
    return run


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def file_instrument_modes(attrs: Mapping[str, Any]) -> dict[str, str]:
    """ "twin" | "hardware" per instrument as the file records them (root attribute instrument_modes; files
    without it: every instrument as the root attribute mode says)."""
    raw = attrs.get("instrument_modes")
    if raw:
        try:
            modes = json.loads(raw)
            if isinstance(modes, dict) and set(modes) == set(INSTRUMENTS):
                return {n: str(modes[n]) for n in INSTRUMENTS}
        except (TypeError, ValueError):
            pass
    return {n: ("twin" if attrs.get("mode") == "sim" else "hardware") for n in INSTRUMENTS}


def status_detail(run: RunData) -> str:
    """The file's status as the operator should read it. "running" is what the file says while its writer
    works, and also what a killed writer leaves behind: a "running" file whose writer process is gone (same
    host, pid not alive) is "interrupted (process died)"; one written on another host cannot be checked."""
    if run.status != "running":
        return run.status
    pid, host = int(run.attrs.get("writer_pid", -1)), str(run.attrs.get("writer_host", ""))
    if host and host != socket.gethostname():
        return f"running, or interrupted (written on host {host}; its process cannot be checked from here)"
    if run.writer_open and pid > 0 and pid != os.getpid() and _pid_alive(pid):
        return f"running (process {pid} is writing it)"
    return "interrupted (process died)"


def _check_modes(path: Path, recorded: dict[str, str], now: dict[str, str]) -> None:
    """Refuse a station whose instruments are not twin/hardware as the file's were, saying how to match it."""
    diff = [n for n in INSTRUMENTS if recorded.get(n) != now.get(n)]
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
            + ", ".join(n for n in INSTRUMENTS if recorded.get(n) == "twin")
            + ") and do not pass --sim"
        )
    raise StorageError(
        f"{path}: the station does not match the run's instruments ({what}); a run continues "
        f"on the instruments it started on: {hint}"
    )


def _last(ds: h5py.Dataset) -> float:
    return float(ds[ds.shape[0] - 1]) if ds.shape[0] else -np.inf


def _cut(grp: h5py.Group, n: int) -> None:
    for c in grp:
        if grp[c].shape[0] > n:
            grp[c].resize((n,))


def repair_end(h5: h5py.File) -> None:
    """Make a reopened file end on one consistent instant (RunWriter.reopen steps 1-3)."""
    for g in [g for g in (*GROUP_UNITS, "steps") if g in h5]:
        _cut(h5[g], min(h5[g][c].shape[0] for c in h5[g]))
    t_end = _last(h5["lockin"]["time"])
    if "truth" in h5 and h5["truth"]["time"].shape[0]:  # a writer that never logs truth keeps its lock-in
        t_end = min(t_end, _last(h5["truth"]["time"]))
    if whole_chunk_layout(h5):
        # written in whole chunks: the file may end inside a lock-in block whose /table and /chamber readings
        # (stamped with the block's last sample) were cut. End on the last block that has its readings, so the
        # resumed file keeps one reading per block across the resume point
        ends = []
        for g in ("table", "chamber"):
            t = h5[g]["time"][:] if g in h5 else np.empty(0)
            k = int(np.searchsorted(t, t_end, side="right"))
            if k:
                ends.append(float(t[k - 1]))
        if ends:
            t_end = max(ends)
    for g in [g for g in GROUP_UNITS if g in h5]:
        t = h5[g]["time"][:]
        _cut(h5[g], int(np.searchsorted(t, t_end, side="right")))
    steps = h5["steps"]
    keep = (steps["status"][:] == b"completed") & (steps["t_end"][:] <= t_end)
    if not keep.all():
        for c in steps:
            kept = steps[c][:][keep]
            steps[c].resize((kept.shape[0],))
            if kept.shape[0]:
                steps[c][:] = kept
