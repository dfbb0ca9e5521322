"""Following a run file from another process: the rows that arrived since the last look (no Bokeh here).

Each `RunFollower.poll()` opens the file read-only (qmg_lab.storage.runfile.open_run_file: SWMR while a writer
has it open; a damaged file is a `problem` in words, never a hang), reads what the writer has flushed since
the previous poll, and closes it again: a reopen costs about a millisecond and sees every flush, a killed
writer's file and a resumed one alike; nothing is ever written. Per poll at most `max_rows` rows of a group are
read (the first polls of a long finished file replay it in pieces, so the page answers meanwhile).

A resume (`qmg-lab run --resume`) cuts every group back to a consistent instant before it appends again: a group
found shorter than the rows already read means the file was cut, and the poll says `reset` (start again).

Read per poll: /clsf (time, sf_change_estimate, gain_correction, rate_output_mean), /table, /chamber, from
/lockin the time, drive amplitude and drive (PLL) frequency, from /truth (twins) the gyro temperature, which is
row for row on the /lockin times (docs/hdf5.md); /steps and /events whole (a few hundred rows), and the root
attributes.

The lock-in stream (1800 rows per simulated second, hundreds of simulated seconds per wall second on the twins)
is sampled, so that following it costs the same whatever the campaign's speed: of the new rows, at most
SAMPLED_CHUNKS whole storage chunks are read per poll (evenly spaced, the newest always among them; a chunk is
what HDF5 decompresses anyway). On the bench (2048-row chunks, about one a second) that is every row; on the
twins (16384-row chunks of 9 s) a poll after 300 simulated seconds reads 4 of its 33 chunks. The drive amplitude,
PLL frequency and gyro temperature traces are therefore exact within each chunk read and may miss a glitch in a
chunk skipped; faults and lost locks are also in the events.

The true SF of a completed +rate/-rate step pair, as the page shows it while the run goes on:
    SF_k = (m+ - m-) / (r+ - r-)
where m+- is the mean of /clsf/rate_output_mean (each dither period's dither-free rate output) over the periods
that end inside the step's window [t_start + settle_s, t_end], and r+- the steps' table rates; its change is
referred to the first pair, in ppm: (SF_k / SF_0 - 1) 1e6. `qmg-lab analyze` takes whole periods of the raw
stream instead: the two agree to the noise of the periods at a window's edges.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from qmg_lab.data.run import MOVING_MEAN_S, window_mean
from qmg_lab.storage.layout import StorageError
from qmg_lab.storage.runfile import open_run_file

MAX_ROWS = 2_000_000
SAMPLED_CHUNKS = 4  # lock-in stream: whole chunks read per poll at most (module docstring)
STREAM_GROUPS = ("lockin", "truth")
COLUMNS: dict[str, tuple[str, ...]] = {
    "clsf": ("time", "sf_change_estimate", "gain_correction", "rate_output_mean"),
    "table": ("time", "rate_command", "rate_measured"),
    "chamber": ("time", "setpoint", "temperature"),
    "lockin": ("time", "drive_amplitude", "drive_frequency"),
    "truth": ("temperature",),  # row for row with /lockin
}
PPM = 1e6


@dataclass
class Update:
    """What one poll found. groups: group -> column -> the new rows (truth's temperature carries /lockin's
    time as "time"); reset: the file was cut (a resume) and everything shown so far must go; ready: the
    file could be opened as a run file (False while a run is still creating it)."""

    ready: bool = False
    reset: bool = False
    attrs: dict[str, Any] = field(default_factory=dict)
    groups: dict[str, dict[str, np.ndarray]] = field(default_factory=dict)
    steps: dict[str, np.ndarray] = field(default_factory=dict)
    events: dict[str, np.ndarray] = field(default_factory=dict)
    pending: bool = False  # rows remain beyond max_rows: poll again soon
    problem: str = ""


def _decode(a: np.ndarray) -> np.ndarray:
    return np.array([v.decode("utf-8", "replace") for v in a], dtype=str) if a.dtype.kind == "S" else a


def _whole(h5: h5py.File, group: str) -> dict[str, np.ndarray]:
    if group not in h5:
        return {}
    g = h5[group]
    cols = [c for c in g if isinstance(g[c], h5py.Dataset) and g[c].ndim == 1]
    n = min((g[c].shape[0] for c in cols), default=0)
    return {c: _decode(g[c][:n]) for c in cols}


def _sampled(h5: h5py.File, group: str, cols: tuple[str, ...], a: int, b: int) -> dict[str, np.ndarray]:
    """Rows [a, b) of a lock-in-rate group, read as at most SAMPLED_CHUNKS whole chunks (module docstring);
    /truth's rows carry /lockin's time (row for row)."""
    ds = h5[group][cols[0]]
    size = int(ds.chunks[0]) if ds.chunks else b - a
    first, last = a // size, (b - 1) // size
    picked = np.unique(np.linspace(last, first, min(SAMPLED_CHUNKS, last - first + 1)).round().astype(np.int64))
    spans = [(max(a, int(k) * size), min(b, (int(k) + 1) * size)) for k in picked]
    out = {c: np.concatenate([h5[group][c][i:j] for i, j in spans]) for c in cols}
    if group == "truth":
        out["time"] = np.concatenate([h5["lockin/time"][i:j] for i, j in spans])
    return out


class RunFollower:
    """Reads a run file incrementally (see the module docstring); keeps the whole CLSF record (a few rows per
    second of run time) for its moving mean and the step pairs."""

    def __init__(self, path: Path, max_rows: int = MAX_ROWS) -> None:
        self.path = path
        self.max_rows = max_rows
        self.read: dict[str, int] = dict.fromkeys(COLUMNS, 0)
        self.clsf_t = np.zeros(0)
        self.clsf_s = np.zeros(0)
        self.clsf_out = np.zeros(0)
        self.probed = False  # open_run_file walked this file's structure (in a child) without fault

    def _restart(self) -> None:
        self.read = dict.fromkeys(COLUMNS, 0)
        self.clsf_t, self.clsf_s, self.clsf_out = np.zeros(0), np.zeros(0), np.zeros(0)

    def poll(self) -> Update:
        up = Update()
        if not self.path.exists():
            up.problem = "waiting for the run file"
            return up
        try:
            self._read_new(up)
        except StorageError as exc:  # open_run_file: not (yet) a readable run file, or damaged; said in words
            self.probed = False  # walked again, in a child process with a time limit, at the next poll
            up.problem = f"cannot read it yet ({exc})"
            return up
        clsf = up.groups.get("clsf")
        if clsf is not None:
            self.clsf_t = np.concatenate((self.clsf_t, clsf["time"]))
            self.clsf_s = np.concatenate((self.clsf_s, clsf["sf_change_estimate"]))
            self.clsf_out = np.concatenate((self.clsf_out, clsf["rate_output_mean"]))
        up.ready = True
        return up

    def _read_new(self, up: Update) -> None:
        """One poll's reading (`poll`): the file opened by `open_run_file` (its structure walked in a child
        process with a time limit at the first poll and after a failed one; SWMR while a writer has it open)."""
        with open_run_file(self.path, probe=not self.probed) as run:
            self.probed = True
            h5 = run.h5
            up.attrs = dict(run.attrs)
            lengths = {}
            for g, cols in COLUMNS.items():
                src = "lockin" if g == "truth" else g
                need = [(g, c) for c in cols] + ([("lockin", "time")] if g == "truth" else [])
                if g not in h5 or src not in h5 or any(c not in h5[gg] for gg, c in need):
                    lengths[g] = 0
                    continue
                lengths[g] = min(h5[gg][c].shape[0] for gg, c in need)
            if any(lengths[g] < self.read[g] for g in COLUMNS):
                self._restart()
                up.reset = True
            for g, cols in COLUMNS.items():
                a = self.read[g]
                b = min(lengths[g], a + self.max_rows)
                up.pending = up.pending or b < lengths[g]
                if b <= a:
                    continue
                rows = _sampled(h5, g, cols, a, b) if g in STREAM_GROUPS else {c: h5[g][c][a:b] for c in cols}
                up.groups[g] = rows
                self.read[g] = b
            up.steps = _whole(h5, "steps")
            up.events = _whole(h5, "events")

    def moving_mean_of_new(self, new_rows: int) -> np.ndarray:
        """The trailing MOVING_MEAN_S mean of the CLSF estimate at its newest `new_rows` rows (from the kept
        record: each window reaches back into earlier polls' rows)."""
        t, s = self.clsf_t, self.clsf_s
        if new_rows == 0:
            return np.zeros(0)
        i0 = t.shape[0] - new_rows
        j = int(np.searchsorted(t, t[i0] - MOVING_MEAN_S, side="right"))
        tt, ss = t[j:], s[j:]
        return window_mean(tt, ss, tt - MOVING_MEAN_S, tt)[i0 - j :]

    def pair_changes(self, steps: dict[str, np.ndarray], settle_s: float) -> tuple[np.ndarray, np.ndarray]:
        """(middle time, SF change vs the first pair in ppm) of every completed +rate/-rate pair (module
        docstring)."""
        if not steps or "index" not in steps:
            return np.zeros(0), np.zeros(0)
        done = steps["status"] == "completed"
        rows = {int(i): k for k, i in enumerate(steps["index"]) if done[k]}
        mids, sfs = [], []
        for i in sorted(rows):
            p, m = rows[i], rows.get(i + 1)
            if m is None or steps["kind"][p] != "rate" or steps["kind"][m] != "rate":
                continue
            rp, rm = float(steps["table_rate"][p]), float(steps["table_rate"][m])
            if not rp > 0 > rm:
                continue
            means = []
            for k in (p, m):
                a, b = float(steps["t_start"][k]) + settle_s, float(steps["t_end"][k])
                inside = (self.clsf_t > a) & (self.clsf_t <= b)
                means.append(float(np.mean(self.clsf_out[inside])) if inside.any() else np.nan)
            if np.all(np.isfinite(means)):
                mids.append(0.5 * (float(steps["t_start"][p]) + float(steps["t_end"][m])))
                sfs.append((means[0] - means[1]) / (rp - rm))
        if not sfs:
            return np.zeros(0), np.zeros(0)
        sf = np.array(sfs)
        return np.array(mids), (sf / sf[0] - 1.0) * PPM


def planned_kinds(attrs: dict[str, Any]) -> list[str]:
    try:
        return [str(k) for k in json.loads(str(attrs.get("planned_step_kinds", "[]")))]
    except ValueError:
        return []
