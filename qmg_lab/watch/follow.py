"""Following a run file from another process: the rows that arrived since the last look (no Bokeh here).

Each `RunFollower.poll()` opens the file read-only (qmg_lab.storage.runfile.open_run_file: SWMR while a writer
has it open; a damaged file is a `problem` in words, never a hang), reads what the writer has flushed since
the previous poll, and closes it again: a reopen costs about a millisecond and sees every flush, a killed
writer's file and a resumed one alike; nothing is ever written.

One data horizon for every group. Each poll takes every group up to the same instant, the horizon
    h = min over the groups with rows of their last time
(rows after h wait for the next poll), so no plot runs ahead of another: the writer hands /lockin and /truth over
in whole chunks (up to 9 s behind /table and /chamber on the twins), and without a common horizon the slow groups
would be drawn to a later time than the lock-in traces. Once the file is final (status completed or aborted, or
its writer died) the horizon is the end of every group: the last rows are all shown. Nothing caps the rows read
per poll, so a plot never falls behind the file (the slow groups are a few rows per second; the lock-in stream
is sampled, below): a finished file is drawn by its first poll.

A resume (`qmg-lab run --resume`) cuts every group back to a consistent instant before it appends again: a group
found shorter than the rows already read means the file was cut, and the poll says `reset` (start again).

Read per poll: /clsf (time, sf_change_estimate, gain_correction, rate_output_mean), /table, /chamber, from
/lockin the time, drive amplitude, drive (PLL) frequency and PLL lock flag (pll_locked; files written before it
existed lack it), from /truth (twins) the gyro temperature, which is row for row on the /lockin times
(docs/hdf5.md); /steps and /events whole (a few hundred rows), and the root attributes.

The lock-in stream (1800 rows per simulated second, hundreds of simulated seconds per wall second on the twins)
is sampled, so that following it costs the same whatever the campaign's speed: of the new rows, at most
SAMPLED_CHUNKS whole storage chunks are read per poll (evenly spaced, the newest always among them; a chunk is
what HDF5 decompresses anyway), FIRST_CHUNKS on a file's first poll (a finished file's replay). On the bench
(2048-row chunks, about one a second) that is every row; on the twins (16384-row chunks of 9 s) a poll after
300 simulated seconds reads 4 of its 33 chunks. The drive amplitude,
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

from qmg_lab.analysis.reductions import rate_pairs
from qmg_lab.clsf.moving_mean import SF_MEAN_WINDOW_S as MOVING_MEAN_S
from qmg_lab.clsf.moving_mean import window_mean
from qmg_lab.storage.layout import StorageError
from qmg_lab.storage.runfile import open_run_file

SAMPLED_CHUNKS = 4  # lock-in stream: whole chunks read per poll at most (module docstring)
FIRST_CHUNKS = 40  # ... and on a file's first poll: a finished file's replay shows its whole length, drawn in ~1 s
STREAM_GROUPS = ("lockin", "truth")
COLUMNS: dict[str, tuple[str, ...]] = {
    "clsf": ("time", "sf_change_estimate", "gain_correction", "rate_output_mean"),
    "table": ("time", "rate_command", "rate_measured"),
    "chamber": ("time", "setpoint", "temperature"),
    "lockin": ("time", "drive_amplitude", "drive_frequency", "pll_locked"),
    "truth": ("temperature",),  # row for row with /lockin
}
OPTIONAL = {("lockin", "pll_locked")}  # storage.layout.OPTIONAL_COLUMNS: older files lack it
PPM = 1e6


@dataclass
class Update:
    """What one poll found. groups: group -> column -> the new rows up to the horizon (truth's temperature
    carries /lockin's time as "time"); horizon: the common data horizon (s, module docstring; NaN before any
    row); final: the file's status is no longer "running" (every row shown); reset: the file was cut (a resume)
    and everything shown so far must go; ready: the file could be opened as a run file (False while a run is
    still creating it)."""

    ready: bool = False
    reset: bool = False
    final: bool = False
    horizon: float = float("nan")
    attrs: dict[str, Any] = field(default_factory=dict)
    groups: dict[str, dict[str, np.ndarray]] = field(default_factory=dict)
    steps: dict[str, np.ndarray] = field(default_factory=dict)
    events: dict[str, np.ndarray] = field(default_factory=dict)
    lost_samples: int = 0  # /lockin samples missing inside the stretches this poll read (missing_samples)
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


def _sampled(
    h5: h5py.File, group: str, cols: tuple[str, ...], a: int, b: int, chunks: int
) -> tuple[dict[str, np.ndarray], list[tuple[int, int]]]:
    """Rows [a, b) of a lock-in-rate group, read as at most `chunks` whole chunks (module docstring), and the
    row spans read; /truth's rows carry /lockin's time (row for row)."""
    ds = h5[group][cols[0]]
    size = int(ds.chunks[0]) if ds.chunks else b - a
    first, last = a // size, (b - 1) // size
    picked = np.unique(np.linspace(last, first, min(chunks, last - first + 1)).round().astype(np.int64))
    spans = [(max(a, int(k) * size), min(b, (int(k) + 1) * size)) for k in picked]
    out = {c: np.concatenate([h5[group][c][i:j] for i, j in spans]) for c in cols}
    if group == "truth":
        out["time"] = np.concatenate([h5["lockin/time"][i:j] for i, j in spans])
    return out, spans


def missing_samples(t: np.ndarray, spans: list[tuple[int, int]]) -> int:
    """Samples missing inside the spans read (t: their times end to end): a step dt_k > 1.5 dt_med between
    neighbours of one span (dt_med its median step) lacks round(dt_k / dt_med) - 1 samples."""
    lost, at = 0, 0
    for i, j in spans:
        dt = np.diff(t[at : at + j - i])
        at += j - i
        if dt.shape[0] < 2:
            continue
        med = float(np.median(dt))
        big = dt[dt > 1.5 * med]
        lost += int(np.sum(np.round(big / med) - 1)) if med > 0 else 0
    return lost


class RunFollower:
    """Reads a run file incrementally (see the module docstring); keeps the whole CLSF record (a few rows per
    second of run time) for its moving mean and the step pairs."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.read: dict[str, int] = dict.fromkeys(COLUMNS, 0)
        #: the newest row read of each group (column -> value): the page's "now" panel
        self.latest: dict[str, dict[str, float]] = {}
        self.clsf_t = np.zeros(0)
        self.clsf_s = np.zeros(0)
        self.clsf_out = np.zeros(0)
        self.probed = False  # open_run_file walked this file's structure (in a child) without fault

    def _restart(self) -> None:
        self.read = dict.fromkeys(COLUMNS, 0)
        self.latest = {}
        self.clsf_t, self.clsf_s, self.clsf_out = np.zeros(0), np.zeros(0), np.zeros(0)

    def attrs(self) -> dict[str, Any] | None:
        """The file's root attributes alone (status, writer), or None if it cannot be opened yet: the page's
        cheap check between polls (`open_run_file` without its child walk, which the polls make)."""
        try:
            with open_run_file(self.path, probe=False) as run:
                return dict(run.attrs)
        except StorageError:
            return None

    def poll(self, writer_gone: bool = False) -> Update:
        """What the writer flushed since the last poll, up to the common horizon (module docstring). writer_gone:
        the caller found the file's writer dead, so the file is final although its status says "running"."""
        up = Update()
        if not self.path.exists():
            up.problem = "waiting for the run file"
            return up
        try:
            self._read_new(up, writer_gone)
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

    def _read_new(self, up: Update, writer_gone: bool) -> None:
        """One poll's reading (`poll`): the file opened by `open_run_file` (its structure walked in a child
        process with a time limit at the first poll and after a failed one; SWMR while a writer has it open)."""
        with open_run_file(self.path, probe=not self.probed) as run:
            self.probed = True
            h5 = run.h5
            up.attrs = dict(run.attrs)
            up.final = writer_gone or up.attrs.get("status", "running") != "running"
            lengths, present = {}, {}
            for g, cols in COLUMNS.items():
                src = "lockin" if g == "truth" else g
                present[g] = tuple(c for c in cols if g in h5 and (c in h5[g] or (g, c) not in OPTIONAL))
                need = [(g, c) for c in present[g]] + ([("lockin", "time")] if g == "truth" else [])
                if g not in h5 or src not in h5 or any(c not in h5[gg] for gg, c in need):
                    lengths[g] = 0
                    continue
                lengths[g] = min(h5[gg][c].shape[0] for gg, c in need)
            first = all(n == 0 for n in self.read.values())
            if any(lengths[g] < self.read[g] for g in COLUMNS):
                self._restart()
                up.reset = True
            ends = _ends(h5, lengths)
            up.horizon = max(ends.values(), default=np.nan) if up.final else min(ends.values(), default=np.nan)
            for g in COLUMNS:
                a = self.read[g]
                b = _rows_to(h5, g, a, lengths[g], up.horizon) if g in ends else a
                if b <= a:
                    continue
                if g in STREAM_GROUPS:
                    rows, spans = _sampled(h5, g, present[g], a, b, FIRST_CHUNKS if first else SAMPLED_CHUNKS)
                    if g == "lockin":
                        up.lost_samples = missing_samples(rows["time"], spans)
                else:
                    rows = {c: h5[g][c][a:b] for c in present[g]}
                up.groups[g] = rows
                self.latest[g] = {c: float(v[-1]) for c, v in rows.items()}
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
        j = int(np.searchsorted(t, t[i0] - MOVING_MEAN_S, side="left"))
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
        for i in rate_pairs({i: (str(steps["kind"][k]), float(steps["table_rate"][k])) for i, k in rows.items()}):
            p, m = rows[i], rows[i + 1]
            rp, rm = float(steps["table_rate"][p]), float(steps["table_rate"][m])
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


def _ends(h5: h5py.File, lengths: dict[str, int]) -> dict[str, float]:
    """The last time of every group with rows (/truth: its /lockin time)."""
    return {g: float(h5["lockin" if g == "truth" else g]["time"][n - 1]) for g, n in lengths.items() if n > 0}


def _rows_to(h5: h5py.File, group: str, a: int, n: int, horizon: float) -> int:
    """The end (exclusive) of the group's rows at or before `horizon`, searched among rows [a, n): the horizon is
    at most one block before the group's end, so only the last stretch of a lock-in-rate time column is read."""
    if not np.isfinite(horizon) or n <= a:
        return a
    t = h5["lockin" if group == "truth" else group]["time"]
    lo = a
    if group in STREAM_GROUPS and t.chunks:
        lo = max(a, n - 2 * int(t.chunks[0]))
        while lo > a and float(t[lo]) > horizon:  # the horizon lies further back: widen the search
            lo = max(a, lo - 4 * int(t.chunks[0]))
    return lo + int(np.searchsorted(t[lo:n], horizon, side="right"))


def planned_kinds(attrs: dict[str, Any]) -> list[str]:
    try:
        return [str(k) for k in json.loads(str(attrs.get("planned_step_kinds", "[]")))]
    except ValueError:
        return []
