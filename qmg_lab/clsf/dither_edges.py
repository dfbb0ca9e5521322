"""The dither's edges, located from its own record to a fraction of a sample.

The DS345's square wave reaches the host through an AuxIn: each recorded value is the mean of the input over the
AuxIn averaging window [t_k - W, t_k] that ends at the sample's timestamp t_k (W <= the sample interval; W -> 0
is a single ADC sample). The generator runs on its own timebase, so its edges fall anywhere between samples.

Location of one edge, with s_k = (d_k - lo)/(hi - lo) the recorded value as a fraction of the level step:

* a sample whose window contains the edge reads an intermediate value, and the edge lies exactly where that
  fraction of the window is high: rising t_e = t_k - W s_k, falling t_e = t_k - W (1 - s_k);
* otherwise the edge lies in the gap between two windows, (t_(k-1), t_k - W); it is taken at the gap's middle
  (error uniform within +-(dt - W)/2).

Levels and noise: the recorded levels lo and hi are the means of the plateau readings; a block whose spread is
below `min_step_v` (the dither is not running: only the AuxIn's noise and quantisation) does not set them. A
sample counts as high above 3/4 of the step and low below 1/4; in between it keeps the previous side
(hysteresis), so the AuxIn's noise on a muted or constant input never makes an edge.

Smoothing: edges of one kind follow t_j = a + b j (cycle index j) up to the timebase's slow wander, so each edge is
replaced by the least-squares line through the last `window` edges of its kind (itself included), evaluated at its
own index. A gap-located edge then carries an error of about (dt - W) / sqrt(3 window) instead of dt/2. An edge
that lies more than a quarter period off the line (the generator was reprogrammed) restarts the fit.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

INTERMEDIATE = 0.02  # a sample within 2 % of either level counts as that level
HYSTERESIS = 0.25  # high above 1 - this fraction of the step, low below it, else the previous side


class EdgeKernels(Protocol):
    """The tracker's per-sample work: qmg_lab/clsf/kernels.py (numba) or qmg_lab/clsf/edges_numpy.py (numpy),
    which give the same results bit for bit (read-only members: module functions and numba dispatchers both fit)."""

    @property
    def plateau_levels(self) -> Callable[[np.ndarray, float, float], tuple[float, float]]: ...
    @property
    def level_crossings(
        self,
    ) -> Callable[
        [np.ndarray, np.ndarray, float, float, tuple[float, float, int], float, float, float],
        tuple[np.ndarray, np.ndarray, float, bool],
    ]: ...
    @property
    def line_at(self) -> Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray]: ...
    @property
    def continue_fit(
        self,
    ) -> Callable[[np.ndarray, np.ndarray, np.ndarray, float, int], tuple[bool, np.ndarray, np.ndarray]]: ...


def edge_kernels(compiled: bool) -> EdgeKernels:
    """The numba kernels (a campaign streams small blocks and loads numba anyway) or their numpy forms (one pass
    over a whole file, in a process that need not pay numba's ~1 s start-up: `qmg-lab analyze`)."""
    if compiled:
        from qmg_lab.clsf import kernels

        return kernels
    from qmg_lab.clsf import edges_numpy

    return edges_numpy


@dataclass
class EdgeTracker:
    """Streams dither samples in; returns the smoothed times of the rising and falling edges found.

    compiled: run the per-sample work in numba's kernels (True) or in their numpy forms (False: same edges,
    bit for bit, without importing numba)."""

    window_s: float = 0.0  # the AuxIn averaging window W, s
    fit_edges: int = 32
    min_step_v: float = 0.0  # the smallest level step taken for a running dither, V
    compiled: bool = True
    lo: float | None = None
    hi: float | None = None
    _prev_t: float | None = None
    _prev_s: float | None = None
    _prev_high: bool | None = None
    # each kind's edge history: row 0 the times (s), row 1 the cycle indices, in the first _count columns
    _hist: dict[int, np.ndarray] = field(default_factory=lambda: {1: np.empty((2, 0)), -1: np.empty((2, 0))})
    _count: dict[int, int] = field(default_factory=lambda: {1: 0, -1: 0})

    def __post_init__(self) -> None:
        self._k = edge_kernels(self.compiled)

    def reset(self) -> None:
        """Forget the sample history and the fits (after a gap in the stream)."""
        self._prev_t = self._prev_s = None
        self._prev_high = None
        self._count = {1: 0, -1: 0}

    def _update_levels(self, d: np.ndarray) -> None:
        if self.lo is None or self.hi is None:
            lo_b, hi_b = float(np.min(d)), float(np.max(d))
            if hi_b - lo_b <= max(1e-9 * max(1.0, abs(hi_b)), self.min_step_v):
                return
            self.lo, self.hi = lo_b, hi_b
        # plateau readings only (beyond mid +- 0.45 span): an edge's intermediate reading is excluded
        self.lo, self.hi = self._k.plateau_levels(d, self.lo, self.hi)

    def process(self, t: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(rising, falling) smoothed edge times located in this block of samples (times t_k, values d_k)."""
        empty = np.empty(0)
        if t.size == 0:
            return empty, empty
        self._update_levels(d)
        if self.lo is None or self.hi is None or self.hi - self.lo <= 0.0:
            return empty, empty
        if self._prev_t is not None and self._prev_s is not None and self._prev_high is not None:
            prev = (self._prev_t, self._prev_s, int(self._prev_high))
        else:
            prev = (0.0, 0.0, -1)
        rising, falling, last_s, last_high = self._k.level_crossings(
            t, d, self.lo, self.hi, prev, self.window_s, HYSTERESIS, INTERMEDIATE
        )
        self._prev_t, self._prev_s, self._prev_high = float(t[-1]), float(last_s), bool(last_high)
        return self._smooth_all(1, rising), self._smooth_all(-1, falling)

    def _history(self, kind: int) -> tuple[np.ndarray, np.ndarray]:
        """(times, cycle indices) of the edges of one kind remembered (views)."""
        n = self._count[kind]
        return self._hist[kind][0, :n], self._hist[kind][1, :n]

    def _smooth_all(self, kind: int, te: np.ndarray) -> np.ndarray:
        """Smoothed times of a block's new edges of one kind (a rolling least-squares line; kernels.continue_fit).

        The history of each kind: the edges' times and their cycle indices (whole numbers, held as floats, the
        fits' abscissae), up to 4 fit_edges of them (then cut to the last fit_edges)."""
        if te.size == 0:
            return te
        raw, idx = self._history(kind)
        hist_t, hist_j = raw[-self.fit_edges :], idx[-self.fit_edges :]
        if raw.size >= 2 and idx[-1] > hist_j[0]:  # the period from the history's own span
            period = float((raw[-1] - hist_t[0]) / (idx[-1] - hist_j[0]))
        else:
            period = float(np.median(np.diff(np.concatenate((hist_t, te))))) if hist_t.size + te.size >= 2 else 0.0
        if raw.size == 0 or period <= 0.0:
            return np.asarray([self._smooth(kind, float(x)) for x in te])
        follows, j, fitted = self._k.continue_fit(hist_t, hist_j, te, period, self.fit_edges)
        if not follows:  # the generator was reprogrammed: edge by edge
            return np.asarray([self._smooth(kind, float(x)) for x in te])
        self._remember(kind, te, j)
        return fitted

    def _remember(self, kind: int, te: np.ndarray | float, j: np.ndarray | float) -> None:
        """Append edges (times, cycle indices) to a history, cut to its last fit_edges entries when it grows beyond
        4 fit_edges (the columns are reused; the array doubles when new edges do not fit)."""
        hist, n = self._hist[kind], self._count[kind]
        k = np.size(te)
        if n + k > hist.shape[1]:
            grown = np.empty((2, 2 * (n + k) + 4 * self.fit_edges))
            grown[:, :n] = hist[:, :n]
            self._hist[kind] = hist = grown
        hist[0, n : n + k] = te
        hist[1, n : n + k] = j
        n += k
        if n > 4 * self.fit_edges:
            hist[:, : self.fit_edges] = hist[:, n - self.fit_edges : n]
            n = self.fit_edges
        self._count[kind] = n

    def _smooth(self, kind: int, te: float) -> float:
        raw, idx = self._history(kind)
        if raw.size:
            diffs = np.diff(raw[-self.fit_edges :])
            period = float(np.median(diffs)) if diffs.size else None
            if period is not None and period > 0.0:
                j = float(idx[-1]) + max(1, round((te - float(raw[-1])) / period))
                pred = self._line(raw, idx, j)
                if abs(te - pred) > 0.25 * period:
                    self._count[kind] = 0  # restart the fit
                    j = 0.0
            else:
                j = float(idx[-1]) + 1.0
        else:
            j = 0.0
        self._remember(kind, te, j)
        raw, idx = self._history(kind)
        if raw.size < 4:
            return te
        return self._line(raw, idx, j)

    def _line(self, raw: np.ndarray, idx: np.ndarray, j: float) -> float:
        """The least-squares line through the last fit_edges (index, time) pairs, at index j (kernels.line_at)."""
        return float(self._k.line_at(raw[-self.fit_edges :], idx[-self.fit_edges :], np.array([j]))[0])
