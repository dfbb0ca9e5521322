"""The study storage level's reducer: the analysis's reductions computed while the campaign runs (docs/hdf5.md,
"The study storage level").

The study level keeps what `qmg-lab analyze` reads of the raw streams, computed by the same code it uses on a full
file (qmg_lab/analysis/reductions.py):

* /edges: every rising edge of the recorded dither and the rate output's running integral at it;
* /windows: per completed step, its analysis window [t_start + settle, t_end] and, on the twins, the truth's
  sample count and means over it;
* /lockin: only the rows of the one step the settling-time figure uses (the first table move from rest,
  `settling_step_index`), from TAIL_S before it starts to its end. /truth is not written.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from qmg_lab.analysis.reductions import EdgeIntegrator, WindowSums, analysis_settle_s
from qmg_lab.campaign.plan import Step
from qmg_lab.clsf.dither_edges import EdgeTracker, edge_threshold_v
from qmg_lab.config.schema import Config, dither_amplitude_vpp
from qmg_lab.storage.study_level import StudyRunWriter

#: lock-in rows kept before the settling step: the settling analysis reads from 1 s plus one dither period before
TAIL_S = 2.5


def settling_step_index(steps: Sequence[Step]) -> int | None:
    """The step whose rate-output transient gives the settling time: the first "rate" or "level" step whose table
    rate differs from the step before it (the first step starts from rest), that step not a sinusoid."""
    prev_rate, prev_kind = 0.0, "rest"
    for s in steps:
        if s.kind in ("rate", "level") and s.table_rate_dps != prev_rate and not prev_kind.startswith("sine"):
            return s.index
        prev_rate, prev_kind = s.table_rate_dps, s.kind
    return None


class StudyReductions:
    """The study level's reducer (storage.study_level.StudyReducer): edges and integrals, window sums, and the
    settling step's raw rows."""

    def __init__(self, settle_s: float, settling_index: int | None, dither_min_step_v: float) -> None:
        self._settle_s = settle_s
        self._settling_index = settling_index
        self._recording = settling_index == 0
        self._edges = EdgeIntegrator(tracker=EdgeTracker(min_step_v=dither_min_step_v))
        self._tail: list[dict[str, np.ndarray]] = []
        self._window = WindowSums(start_s=0.0 + settle_s)  # the first step starts at t = 0

    def lockin(self, block: dict[str, np.ndarray], out: StudyRunWriter) -> None:
        for rising, integral in self._edges.feed(block["time"], block["dither"], block["rate_output"]):
            out.write_edges(rising, integral)
        if self._recording:
            out.write_lockin(**block)
        elif self._settling_index is not None:
            self._tail.append(block)
            while len(self._tail) > 1 and self._tail[-1]["time"][-1] - self._tail[1]["time"][0] >= TAIL_S:
                self._tail.pop(0)

    def truth(self, block: dict[str, np.ndarray], out: StudyRunWriter) -> None:
        self._window.add(block["time"], block["scale_factor"], block["temperature"])

    def step(self, step: Mapping[str, Any], out: StudyRunWriter) -> None:
        index, t_end = int(step["index"]), float(step["t_end"])
        if step["status"] == "completed":
            row = self._window.row(index, t_end)
            row["window_start"] = float(step["t_start"]) + self._settle_s
            out.write_window(**row)
            if self._recording and index == self._settling_index:
                self._recording = False
                self._settling_index = None
            elif self._settling_index is not None and index == self._settling_index - 1:
                self._recording = True
                for block in self._tail:
                    out.write_lockin(**block)
                self._tail = []
        self._window = WindowSums(start_s=t_end + self._settle_s)

    def finish(self, out: StudyRunWriter) -> None:
        for rising, integral in self._edges.finish():
            out.write_edges(rising, integral)


def study_reductions(cfg: Config, steps: Sequence[Step]) -> StudyReductions:
    """The reducer a study-level run file of `cfg` hands its /lockin and /truth blocks to (the analysis's settle
    time, the settling step, the dither edge threshold)."""
    return StudyReductions(
        analysis_settle_s(cfg), settling_step_index(steps), edge_threshold_v(dither_amplitude_vpp(cfg))
    )
