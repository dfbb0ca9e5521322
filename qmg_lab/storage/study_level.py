"""The study storage level's file format: a run file that keeps reductions of /lockin and /truth (docs/hdf5.md).

A design study runs hundreds of campaigns; their raw lock-in streams (/lockin and /truth at the lock-in rate) are
what costs disk and time, and the analysis reads them only through a few reductions. At `[storage] level =
"study"` the file carries, instead of those streams:

* /windows, one row per completed step: its analysis window and the truth's sample count and means over it;
* /edges, one row per rising edge of the recorded dither: its time and the rate output's integral at it;
* /lockin with only the raw rows the reducer chose to keep (the settling step's);
* the root attribute storage_level = "study".

What the rows hold is computed by a `StudyReducer` the caller hands in (qmg_lab/campaign/study_level.py: the
analysis's own reductions); this module knows only where they go. A study-level file cannot be resumed (the
reductions live in the writer's memory): a study reruns a campaign that did not finish.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import h5py
import numpy as np

from qmg_lab.storage.runfile import open_run_file
from qmg_lab.storage.writer import RunWriter, StorageError

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


@dataclass
class StudySummary:
    """The summaries of a study-level run file (`read_summary`)."""

    windows: dict[str, np.ndarray]
    edges: dict[str, np.ndarray]

    def window_rows(self) -> dict[int, dict[str, float]]:
        """/windows by step index."""
        w = self.windows
        return {int(w["index"][i]): {k: float(w[k][i]) for k in w} for i in range(w["index"].shape[0])}


def _level(h5: h5py.File) -> str:
    level = h5.attrs.get(LEVEL_ATTR, "full")
    return level.decode() if isinstance(level, bytes) else str(level)


def read_summary(path: str | Path) -> StudySummary | None:
    """/windows and /edges of a study-level run file (every column cut to the shortest: a kill can fall between
    two columns' writes); None for a file written at the full level."""
    p = Path(path)
    with open_run_file(p) as run:
        h5 = run.h5
        if _level(h5) != "study":
            return None
        out: dict[str, dict[str, np.ndarray]] = {}
        for g, units in (("windows", WINDOWS_UNITS), ("edges", EDGES_UNITS)):
            if g not in h5:
                raise StorageError(f"{p}: a study-level file without its /{g} group")
            out[g] = run.read(g, list(units))  # whole rows (fill rows are never data)
    return StudySummary(windows=out["windows"], edges=out["edges"])


def is_study_level(path: str | Path) -> bool:
    """True if the run file was written at the study storage level."""
    with open_run_file(path) as run:
        return _level(run.h5) == "study"


def refuse_study_resume(path: Path) -> None:
    """StorageError if `path` is a study-level run file (those are rerun, not resumed)."""
    try:
        study = is_study_level(path)
    except StorageError:
        return  # check_resumable reports an unreadable file in its own words
    if study:
        raise StorageError(
            f'{path}: written at storage.level = "study", which cannot be resumed (its summaries are computed in '
            "the writer's memory); run the campaign again"
        )


def _layout(h5: h5py.File) -> None:
    """The /windows and /edges groups (before SWMR)."""
    for g, units in (("windows", WINDOWS_UNITS), ("edges", EDGES_UNITS)):
        grp = h5.create_group(g)
        for col, unit in units.items():
            ds = grp.create_dataset(col, shape=(0,), maxshape=(None,), dtype=np.float64, chunks=(SUMMARY_CHUNK_ROWS,))
            ds.attrs["units"] = unit
            ds.attrs["description"] = SUMMARY_DESCRIPTIONS[f"{g}/{col}"]


class StudyReducer(Protocol):
    """What reduces /lockin and /truth to a study-level file's rows; it writes them with the StudyRunWriter's
    write_lockin, write_edges and write_window."""

    def lockin(self, block: dict[str, np.ndarray], out: StudyRunWriter) -> None:
        """A /lockin block (every column, float64, at least one row)."""

    def truth(self, block: dict[str, np.ndarray], out: StudyRunWriter) -> None:
        """A /truth block."""

    def step(self, step: Mapping[str, Any], out: StudyRunWriter) -> None:
        """A /steps row (RunWriter.append_step's keywords), before it is written."""

    def finish(self, out: StudyRunWriter) -> None:
        """The run ends: write what is still held (called once, before the final flush)."""


class StudyRunWriter(RunWriter):
    """A RunWriter at the study storage level: /lockin and /truth appends go to the reducer, which writes the
    /windows and /edges rows (and any raw /lockin rows it keeps); every other group as at the full level.
    Use `create_study_writer`."""

    reducer: StudyReducer  #: what reduces /lockin and /truth (given to create_study_writer)
    _finished = False

    def append(self, group: str, **columns: np.ndarray) -> None:
        """/lockin and /truth blocks to the reducer; every other group as RunWriter.append."""
        if group not in ("lockin", "truth"):
            super().append(group, **columns)
            return
        self._check_open()
        block = {c: np.asarray(v, dtype=np.float64) for c, v in columns.items()}
        if block["time"].shape[0] == 0:
            return
        if group == "lockin":
            self.reducer.lockin(block, self)
        else:
            self.reducer.truth(block, self)

    def append_row(self, group: str, **values: float) -> None:
        """As RunWriter.append_row; a /lockin or /truth row goes through `append`."""
        if group in ("lockin", "truth"):
            self.append(group, **{c: np.array([v], dtype=np.float64) for c, v in values.items()})
            return
        super().append_row(group, **values)

    def append_step(self, **step: Any) -> None:
        """The reducer sees the step first (its /windows row), then the /steps row is written."""
        self._check_open()
        self.reducer.step(step, self)
        super().append_step(**step)

    def set_status(self, status: str, abort_reason: str = "") -> None:
        """At the end of a run the reducer writes what it still holds before the final flush."""
        if status != "running" and not self.closed:
            self._finish()
        super().set_status(status, abort_reason)

    def close(self) -> None:
        if not self.closed:
            self._finish()
        super().close()

    def _finish(self) -> None:
        if not self._finished:
            self._finished = True
            self.reducer.finish(self)

    # ---- what the reducer writes -----------------------------------------------------------------------------

    def write_lockin(self, **columns: np.ndarray) -> None:
        """Raw /lockin rows kept in the file (every column)."""
        super().append("lockin", **columns)

    def write_edges(self, time: np.ndarray, rate_integral: np.ndarray) -> None:
        """/edges rows: rising dither edges (s) and the rate output's integral at them (V s)."""
        if time.shape[0]:
            self._buffer_block("edges", (np.asarray(time, dtype=np.float64), np.asarray(rate_integral, np.float64)))

    def write_window(self, **row: float) -> None:
        """One /windows row (every column of WINDOWS_UNITS)."""
        self._buffer_row("windows", tuple(float(row[c]) for c in WINDOWS_UNITS))


def create_study_writer(path: Path, reducer: StudyReducer, **create: Any) -> StudyRunWriter:
    """A new study-level run file (RunWriter.create's keywords; no /truth group) whose /lockin and /truth go to
    `reducer`."""
    attrs = {**(create.pop("extra_attrs", None) or {}), LEVEL_ATTR: "study"}
    writer = StudyRunWriter.create(path, truth=False, extra_attrs=attrs, extra_layout=_layout, **create)
    assert isinstance(writer, StudyRunWriter)
    writer.reducer = reducer
    for g, units in (("windows", WINDOWS_UNITS), ("edges", EDGES_UNITS)):
        writer._buffer_group(g, list(units))
    return writer
