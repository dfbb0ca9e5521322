"""The study storage level: a run file that keeps only what `qmg-lab analyze` needs (docs/hdf5.md).

A design study runs hundreds of campaigns; their raw lock-in streams (/lockin and /truth at the lock-in rate,
about 250 MB per campaign hour) are what costs disk and time, and the analysis reads them only through a few
reductions. At `[storage] level = "study"` the writer computes those reductions while the campaign runs and
stores them instead of the streams:

* /edges, one row per rising edge of the recorded dither: the edge time, located by the analysis's own edge
  tracker (qmg_lab/clsf/dither_edges.py) on the same chunks of EDGE_CHUNK_SAMPLES samples the analysis uses, and
  I(t_e) = ∫_0^t_e rate_output dt, the trapezoid integral of the rate output from the first sample, linearly
  interpolated at the edge (the analysis's running integral). A step's rate-output mean over whole dither periods
  is then (I(e_last) - I(e_first)) / (e_last - e_first), as the analysis computes it from a full file.
* /windows, one row per completed step: its analysis window [t_start + settle, t_end] (settle =
  max(plan.settle_s, 5 / (2 π rate_bandwidth_hz)), `analysis_settle_s`), and on the twins the number of samples
  in it and the mean of the true scale factor and the true gyro temperature over them (the analysis's truth check).
* /lockin holds only the samples of the one step the settling-time figure uses (the first table move from rest,
  `settling_step_index`), from 2.5 s before it starts to its end; /truth is not written.

/clsf, /table, /chamber, /steps, /events and /snapshots are written as at the full level. The file carries the
root attribute storage_level = "study". A study-level file cannot be resumed (the running integral and the edge
tracker live in the writer's memory): a study reruns a campaign that did not finish.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from qmg_lab.campaign.plan import Step, dither_amplitude_vpp
from qmg_lab.clsf.dither_edges import EdgeTracker
from qmg_lab.config.schema import Config
from qmg_lab.storage.writer import RunWriter, StorageError

#: the analysis hands the recorded dither to its edge tracker in chunks of this many samples (the tracker's level
#: estimate is updated per chunk): the study writer uses the same chunks, so it finds the same edges
EDGE_CHUNK_SAMPLES = 36000

#: lock-in rows kept before the settling step: the settling analysis reads from 1 s plus one dither period before
TAIL_S = 2.5

LEVEL_ATTR = "storage_level"
WINDOWS_UNITS = {
    "index": "1",
    "window_start": "s",
    "window_end": "s",
    "truth_samples": "1",
    "truth_scale_factor": "V/(deg/s)",
    "truth_temperature": "degC",
}
EDGES_UNITS = {"time": "s", "rate_integral": "V s"}
SUMMARY_DESCRIPTIONS = {
    "windows/index": "step number in the plan (completed steps only)",
    "windows/window_start": "analysis window start: the step's t_start + settle, s since t0_unix",
    "windows/window_end": "analysis window end: the step's t_end, s since t0_unix",
    "windows/truth_samples": "lock-in samples in the window (twins; 0 on hardware)",
    "windows/truth_scale_factor": "mean true FTR scale factor over the window's samples (twins), V per deg/s",
    "windows/truth_temperature": "mean true gyro temperature over the window's samples (twins), degC",
    "edges/time": "rising edge of the recorded dither, s since t0_unix (the analysis's edge tracker)",
    "edges/rate_integral": "trapezoid integral of the rate output from the first sample to the edge, V s",
}
SUMMARY_CHUNK_ROWS = 4096
#: lock-in samples kept from the previous chunk: a smoothed edge may lie a sample or two before its chunk
_INTERP_HISTORY = 16


def analysis_settle_s(cfg: Config) -> float:
    """Start of a step excluded from the analysis: max(plan.settle_s, 5 rate-loop time constants 5/(2 π f_bw)), s."""
    return max(cfg.plan.settle_s, 5.0 / (2 * math.pi * cfg.loops.rate_bandwidth_hz))


def settling_step_index(steps: Sequence[Step]) -> int | None:
    """The step whose rate-output transient gives the settling time: the first "rate" or "level" step whose table
    rate differs from the step before it (the first step starts from rest), that step not a sinusoid."""
    prev_rate, prev_kind = 0.0, "rest"
    for s in steps:
        if s.kind in ("rate", "level") and s.table_rate_dps != prev_rate and not prev_kind.startswith("sine"):
            return s.index
        prev_rate, prev_kind = s.table_rate_dps, s.kind
    return None


@dataclass
class StudySummary:
    """The summaries of a study-level run file (`read_summary`)."""

    windows: dict[str, np.ndarray]
    edges: dict[str, np.ndarray]

    def window_rows(self) -> dict[int, dict[str, float]]:
        """/windows by step index."""
        w = self.windows
        return {int(w["index"][i]): {k: float(w[k][i]) for k in w} for i in range(w["index"].shape[0])}


def read_summary(path: str | Path) -> StudySummary | None:
    """/windows and /edges of a study-level run file (every column cut to the shortest: a kill can fall between
    two columns' writes); None for a file written at the full level."""
    p = Path(path)
    try:
        h5 = h5py.File(p, "r", swmr=True, libver="latest")
    except OSError as exc:
        raise StorageError(f"{p}: HDF5 cannot open it: {exc}") from None
    with h5:
        level = h5.attrs.get(LEVEL_ATTR, "full")
        if (level.decode() if isinstance(level, bytes) else str(level)) != "study":
            return None
        out: dict[str, dict[str, np.ndarray]] = {}
        for g, units in (("windows", WINDOWS_UNITS), ("edges", EDGES_UNITS)):
            if g not in h5:
                raise StorageError(f"{p}: a study-level file without its /{g} group")
            n = min(h5[g][c].shape[0] for c in units)
            out[g] = {c: h5[g][c][:n] for c in units}
    return StudySummary(windows=out["windows"], edges=out["edges"])


def is_study_level(path: str | Path) -> bool:
    """True if the run file was written at the study storage level."""
    with h5py.File(Path(path), "r", swmr=True, libver="latest") as h5:
        level = h5.attrs.get(LEVEL_ATTR, "full")
    return (level.decode() if isinstance(level, bytes) else str(level)) == "study"


def _layout(h5: h5py.File) -> None:
    """The /windows and /edges groups (before SWMR)."""
    for g, units in (("windows", WINDOWS_UNITS), ("edges", EDGES_UNITS)):
        grp = h5.create_group(g)
        for col, unit in units.items():
            ds = grp.create_dataset(col, shape=(0,), maxshape=(None,), dtype=np.float64, chunks=(SUMMARY_CHUNK_ROWS,))
            ds.attrs["units"] = unit
            ds.attrs["description"] = SUMMARY_DESCRIPTIONS[f"{g}/{col}"]


@dataclass
class _EdgeIntegrator:
    """The rising dither edges and the rate output's running trapezoid integral at them, on the analysis's chunks.

    Bit for bit the analysis's computation on a full file: the integral is the sequential sum
    I_k = I_(k-1) + (t_k - t_(k-1)) (r_k + r_(k-1)) / 2 from I_0 = 0 (what numpy's cumsum does over the whole
    column), interpolated linearly at each edge between the samples around it.

    The integral is carried block by block as the blocks arrive, in one compiled pass per block
    (qmg_lab/storage/trapezoid.py: each term and each partial sum the same floating-point operation on the same
    operands as over the whole column); a chunk only joins its samples' times, dither and integral for the edge
    tracker and the interpolation."""

    tracker: EdgeTracker = field(default_factory=EdgeTracker)
    _t: list[np.ndarray] = field(default_factory=list)  # the current chunk's pieces: times,
    _d: list[np.ndarray] = field(default_factory=list)  # dither values,
    _i: list[np.ndarray] = field(default_factory=list)  # and the integral at those samples
    _pending: int = 0
    _hist_t: np.ndarray = field(default_factory=lambda: np.empty(0))
    _hist_i: np.ndarray = field(default_factory=lambda: np.empty(0))
    _last: tuple[float, float, float] | None = None  # (t, r, I) of the last sample fed

    def __post_init__(self) -> None:
        from qmg_lab.storage.trapezoid import running_trapezoid  # numba: loaded by the writer, never by analyze

        self._running_trapezoid = running_trapezoid

    def feed(self, t: np.ndarray, dither: np.ndarray, rate_output: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
        """Integrate and buffer a block; returns (edge times, integrals) of every whole chunk completed by it."""
        n = t.shape[0]
        if n == 0:
            return []
        self._t.append(t)
        self._d.append(dither)
        self._i.append(self._integrate(t, rate_output))
        self._pending += n
        out = []
        while self._pending >= EDGE_CHUNK_SAMPLES:
            out.append(self._chunk(EDGE_CHUNK_SAMPLES))
        return out

    def finish(self) -> list[tuple[np.ndarray, np.ndarray]]:
        """The last, partial chunk (the analysis processes it too)."""
        return [self._chunk(self._pending)] if self._pending else []

    def _integrate(self, t: np.ndarray, r: np.ndarray) -> np.ndarray:
        """I at the block's samples, from the last sample fed (from I_0 = 0 at the very first sample)."""
        t_prev, r_prev, i_prev = self._last if self._last is not None else (0.0, 0.0, 0.0)
        integral: np.ndarray = self._running_trapezoid(
            np.ascontiguousarray(t, dtype=np.float64),
            np.ascontiguousarray(r, dtype=np.float64),
            t_prev,
            r_prev,
            i_prev,
            self._last is None,
        )
        self._last = (float(t[-1]), float(r[-1]), float(integral[-1]))
        return integral

    def _chunk(self, n: int) -> tuple[np.ndarray, np.ndarray]:
        """Edges of the first n pending samples, and the integral interpolated at them."""
        t_parts, d_parts, i_parts = self._take(self._t, n), self._take(self._d, n), self._take(self._i, n)
        self._pending -= n
        xp = np.concatenate([self._hist_t, *t_parts])  # the chunk's times after the last ones of the chunk before
        fp = np.concatenate([self._hist_i, *i_parts])
        t = xp[self._hist_t.shape[0] :]
        d = d_parts[0] if len(d_parts) == 1 else np.concatenate(d_parts)
        rising, _ = self.tracker.process(t, d)
        self._hist_t, self._hist_i = xp[-_INTERP_HISTORY:].copy(), fp[-_INTERP_HISTORY:].copy()
        return rising, np.interp(rising, xp, fp)

    @staticmethod
    def _take(pieces: list[np.ndarray], n: int) -> list[np.ndarray]:
        """The first n rows of `pieces` (views), removed from it."""
        taken: list[np.ndarray] = []
        while n:
            p = pieces[0]
            if p.shape[0] <= n:
                taken.append(pieces.pop(0))
                n -= p.shape[0]
            else:
                taken.append(p[:n])
                pieces[0] = p[n:]
                n = 0
        return taken


@dataclass
class _Window:
    """Running sums of the truth over one step's analysis window."""

    start_s: float
    samples: int = 0
    sf_sum: float = 0.0
    temp_sum: float = 0.0

    def add(self, time: np.ndarray, scale_factor: np.ndarray, temperature: np.ndarray) -> None:
        """Add the truth samples at or after start_s: their count, and the sums (numpy's) of their scale factor and
        temperature. A block wholly inside the window (all but the first of a step) is summed as it is, with the
        same sums as over the selected samples (the same values in the same order)."""
        t = np.asarray(time, dtype=np.float64)
        m = t >= self.start_s
        k = int(np.count_nonzero(m))
        if k == 0:
            return
        sf = np.asarray(scale_factor, dtype=np.float64)
        temp = np.asarray(temperature, dtype=np.float64)
        if k < t.shape[0]:
            sf, temp = sf[m], temp[m]
        self.samples += k
        self.sf_sum += float(np.sum(sf))
        self.temp_sum += float(np.sum(temp))


class StudyRunWriter(RunWriter):
    """A RunWriter at the study storage level (module docstring): /lockin and /truth appends are reduced to /edges,
    /windows and the settling step's raw rows. Use `create_run_writer`."""

    _settle_s: float = 0.0
    _settling_index: int | None = None
    _recording = False

    def _start_study(self, settle_s: float, settling_index: int | None, dither_min_step_v: float) -> None:
        self._settle_s = settle_s
        self._settling_index = settling_index
        self._recording = settling_index == 0
        # the analysis's edge locator, with its minimum dither step (analysis.py)
        self._edges = _EdgeIntegrator(tracker=EdgeTracker(min_step_v=dither_min_step_v))
        self._edges_done = False
        self._tail: list[dict[str, np.ndarray]] = []
        self._window = _Window(start_s=0.0 + settle_s)  # the first step starts at t = 0
        # /windows and /edges rows are buffered and written by the writer thread, like every other group's
        for g, units in (("windows", WINDOWS_UNITS), ("edges", EDGES_UNITS)):
            self._buffer_group(g, list(units))

    def append(self, group: str, **columns: np.ndarray) -> None:
        """Reduce /lockin and /truth blocks to the summaries; every other group as at the full level."""
        if group == "truth":
            self._check_open()
            self._window.add(columns["time"], columns["scale_factor"], columns["temperature"])
            return
        if group != "lockin":
            super().append(group, **columns)
            return
        self._check_open()
        keep = self._recording or self._settling_index is not None  # after the settling step: the edges only
        names = columns if keep else ("time", "dither", "rate_output")
        block = {c: np.asarray(columns[c], dtype=np.float64) for c in names}
        if block["time"].shape[0] == 0:
            return
        for rising, integral in self._edges.feed(block["time"], block["dither"], block["rate_output"]):
            self._write_edges(rising, integral)
        if self._recording:
            super().append("lockin", **block)
        elif self._settling_index is not None:
            self._tail.append(block)
            while len(self._tail) > 1 and self._tail[-1]["time"][-1] - self._tail[1]["time"][0] >= TAIL_S:
                self._tail.pop(0)

    def append_row(self, group: str, **values: float) -> None:
        """As RunWriter.append_row; a /lockin or /truth row goes through `append`'s reductions."""
        if group in ("lockin", "truth"):
            self.append(group, **{c: np.array([v], dtype=np.float64) for c, v in values.items()})
            return
        super().append_row(group, **values)

    def append_step(self, **step: Any) -> None:
        """The step's /windows row and the settling step's raw rows, then the /steps row (RunWriter.append_step's
        keywords: index, kind, t_start, t_end, table_rate, chamber_setpoint, status)."""
        index, t_start, t_end = int(step["index"]), float(step["t_start"]), float(step["t_end"])
        self._check_open()
        if step["status"] == "completed":
            w = self._window
            n = max(w.samples, 1)
            row = {
                "index": float(index),
                "window_start": t_start + self._settle_s,
                "window_end": t_end,
                "truth_samples": float(w.samples),
                "truth_scale_factor": w.sf_sum / n if w.samples else math.nan,
                "truth_temperature": w.temp_sum / n if w.samples else math.nan,
            }
            self._buffer_row("windows", tuple(row[c] for c in WINDOWS_UNITS))
            if self._recording and index == self._settling_index:
                self._recording = False
                self._settling_index = None
            elif self._settling_index is not None and index == self._settling_index - 1:
                self._recording = True
                for block in self._tail:
                    super().append("lockin", **block)
                self._tail = []
        self._window = _Window(start_s=t_end + self._settle_s)
        super().append_step(**step)

    def set_status(self, status: str, abort_reason: str = "") -> None:
        """At the end of a run the last, partial edge chunk is processed before the final flush."""
        if status != "running" and not self.closed:
            self._finish_edges()
        super().set_status(status, abort_reason)

    def close(self) -> None:
        if not self.closed:
            self._finish_edges()
        super().close()

    def _finish_edges(self) -> None:
        if self._edges_done:
            return
        self._edges_done = True
        for rising, integral in self._edges.finish():
            self._write_edges(rising, integral)

    def _write_edges(self, rising: np.ndarray, integral: np.ndarray) -> None:
        if rising.shape[0] == 0:
            return
        self._buffer_block("edges", (np.asarray(rising, dtype=np.float64), np.asarray(integral, dtype=np.float64)))


def create_run_writer(
    path: Path,
    cfg: Config,
    steps: Sequence[Step],
    *,
    config_text: str,
    config_sha256: str,
    mode: str,
    software_version: str,
    t0_unix: float,
    instrument_modes: Mapping[str, str],
    clock: Callable[[], float] | None = None,
) -> RunWriter:
    """A new run file at the configuration's storage level (`[storage] level`): a RunWriter ("full") or a
    StudyRunWriter ("study")."""
    kwargs: dict[str, Any] = dict(
        config_text=config_text,
        config_sha256=config_sha256,
        mode=mode,
        software_version=software_version,
        t0_unix=t0_unix,
        flush_interval_s=cfg.storage.flush_interval_s,
        compression=cfg.storage.resolved_compression(cfg.lockin.sim),
        instrument_modes=instrument_modes,
        realtime=not cfg.lockin.sim,
    )
    if clock is not None:
        kwargs["clock"] = clock
    if cfg.storage.level == "full":
        return RunWriter.create(path, truth=cfg.lockin.sim, **kwargs)
    writer = StudyRunWriter.create(path, truth=False, extra_attrs={LEVEL_ATTR: "study"}, extra_layout=_layout, **kwargs)
    assert isinstance(writer, StudyRunWriter)
    writer._start_study(analysis_settle_s(cfg), settling_step_index(steps), 0.5 * dither_amplitude_vpp(cfg))
    return writer


def refuse_study_resume(path: Path) -> None:
    """StorageError if `path` is a study-level run file (those are rerun, not resumed)."""
    try:
        study = is_study_level(path)
    except OSError:
        return  # check_resumable reports an unreadable file in its own words
    if study:
        raise StorageError(
            f'{path}: written at storage.level = "study", which cannot be resumed (its summaries are computed in '
            "the writer's memory); run the campaign again"
        )
