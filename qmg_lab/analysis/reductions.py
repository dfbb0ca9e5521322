"""The analysis's reductions of the raw streams, written once: used by `qmg-lab analyze` on a full file and by the
study storage level while the campaign runs (qmg_lab/campaign/study_level.py).

* The settle time that starts each step's analysis window: max(plan.settle_s, the configured rate loop's time to
  within e^-5 of the end of a step), the floor from its step response (qmg_lab/config/rate_loop.py settle_time_s):
  1 - e^(-pt) (1 - (p - g) t) critically damped (pt = 6.75, 1.33 s at 2 Hz), e^(-w_c t) for the first-order
  zero-on-pole loop (5/w_c, 0.40 s at 2 Hz).
* The rate output's running integral by the trapezoid rule, I_k = I_(k-1) + (t_k - t_(k-1)) (r_k + r_(k-1)) / 2
  from I_0 = 0 at the first sample, carried from block to block (`RateIntegral`).
* The rising edges of the recorded dither, located by the CLSF estimator's edge tracker
  (qmg_lab/clsf/dither_edges.py) on chunks of EDGE_CHUNK_SAMPLES samples (the tracker updates its level estimate
  per chunk), and the integral interpolated linearly at each edge (`EdgeIntegrator`). A step's rate-output mean
  over whole dither periods is then (I(e_last) - I(e_first)) / (e_last - e_first) (`mean_between_edges`).
* The truth's sample count and sums over a step's window (`WindowSums`).
* The step pairs that measure the scale factor (`rate_pairs`): step i and step i + 1, both "rate" steps, at
  +r then -r (r+ > 0 > r-); the pair's SF is (m+ - m-) / (r+ - r-), m+- the steps' rate-output means.

Fed the same samples in blocks of any size, these give the same values as over the whole columns up to the
rounding of the running sums (the integral's partial sums are formed in the same order; blocks only change
where a chunk's arrays are joined).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from qmg_lab.clsf.dither_edges import EdgeTracker
from qmg_lab.config.rate_loop import config_settle_floor_s
from qmg_lab.config.schema import Config

#: the edge tracker is fed chunks of this many lock-in samples (its level estimate is updated per chunk)
EDGE_CHUNK_SAMPLES = 36000
#: lock-in samples kept from the previous chunk: a smoothed edge may lie a sample or two before its chunk
_INTERP_HISTORY = 16


def rate_pairs(steps: Mapping[int, tuple[str, float]]) -> list[int]:
    """The first index i of every +rate/-rate pair among `steps` (step index -> (kind, table rate in deg/s)):
    i and i + 1 both present, both of kind "rate", rate(i) > 0 > rate(i + 1); in index order."""
    pairs = []
    for i in sorted(steps):
        plus, minus = steps[i], steps.get(i + 1)
        if minus is not None and plus[0] == "rate" == minus[0] and plus[1] > 0 > minus[1]:
            pairs.append(i)
    return pairs


def analysis_settle_s(cfg: Config) -> float:
    """Start of a step excluded from the analysis: max(plan.settle_s, the configured rate loop's time to within
    e^-5 of the end of a step, qmg_lab/config/rate_loop.py config_settle_floor_s), s."""
    return max(cfg.plan.settle_s, config_settle_floor_s(cfg))


@dataclass
class RateIntegral:
    """The rate output's running trapezoid integral over a stream of blocks (module docstring), V s."""

    _last: tuple[float, float, float] | None = None  # (t, r, I) of the last sample fed

    def feed(self, t: np.ndarray, r: np.ndarray) -> np.ndarray:
        """I at the block's samples (t, r 1-D, at least one sample), continuing from the last sample fed."""
        if self._last is None:
            terms = np.concatenate(([0.0], 0.5 * np.diff(t) * (r[1:] + r[:-1])))
        else:
            t_prev, r_prev, i_prev = self._last
            terms = 0.5 * np.diff(t, prepend=t_prev) * (r + np.concatenate(([r_prev], r[:-1])))
            terms[0] += i_prev
        integral = np.cumsum(terms)
        self._last = (float(t[-1]), float(r[-1]), float(integral[-1]))
        return integral


@dataclass
class EdgeIntegrator:
    """The rising dither edges and the rate output's integral at them, from blocks of (time, dither, rate output)
    fed in order; the edges found chunk by chunk (module docstring)."""

    tracker: EdgeTracker = field(default_factory=EdgeTracker)
    _integral: RateIntegral = field(default_factory=RateIntegral)
    _t: list[np.ndarray] = field(default_factory=list)  # the current chunk's pieces: times,
    _d: list[np.ndarray] = field(default_factory=list)  # dither values,
    _i: list[np.ndarray] = field(default_factory=list)  # and the integral at those samples
    _pending: int = 0
    _hist_t: np.ndarray = field(default_factory=lambda: np.empty(0))
    _hist_i: np.ndarray = field(default_factory=lambda: np.empty(0))

    def feed(self, t: np.ndarray, dither: np.ndarray, rate_output: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
        """Integrate and buffer a block; returns (edge times, integrals) of every whole chunk completed by it."""
        if t.shape[0] == 0:
            return []
        self._t.append(t)
        self._d.append(dither)
        self._i.append(self._integral.feed(t, rate_output))
        self._pending += t.shape[0]
        out = []
        while self._pending >= EDGE_CHUNK_SAMPLES:
            out.append(self._chunk(EDGE_CHUNK_SAMPLES))
        return out

    def finish(self) -> list[tuple[np.ndarray, np.ndarray]]:
        """The last, partial chunk."""
        return [self._chunk(self._pending)] if self._pending else []

    def _chunk(self, n: int) -> tuple[np.ndarray, np.ndarray]:
        """Edges of the first n pending samples, and the integral interpolated at them."""
        t_parts, d_parts, i_parts = _take(self._t, n), _take(self._d, n), _take(self._i, n)
        self._pending -= n
        xp = np.concatenate([self._hist_t, *t_parts])  # the chunk's times after the last ones of the chunk before
        fp = np.concatenate([self._hist_i, *i_parts])
        rising, _ = self.tracker.process(xp[self._hist_t.shape[0] :], np.concatenate(d_parts))
        self._hist_t, self._hist_i = xp[-_INTERP_HISTORY:].copy(), fp[-_INTERP_HISTORY:].copy()
        return rising, np.interp(rising, xp, fp)


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


def edges_and_integrals(
    t: np.ndarray, dither: np.ndarray, rate_output: np.ndarray, min_step_v: float
) -> tuple[np.ndarray, np.ndarray]:
    """Every rising edge of a whole record and the rate output's integral at it (EdgeIntegrator fed once)."""
    integrator = EdgeIntegrator(tracker=EdgeTracker(min_step_v=min_step_v))
    parts = integrator.feed(t, dither, rate_output) + integrator.finish()
    empty = np.empty(0)
    return np.concatenate([empty, *(p[0] for p in parts)]), np.concatenate([empty, *(p[1] for p in parts)])


def mean_between_edges(edges: np.ndarray, integral: np.ndarray, t0: float, t1: float, dt: float) -> float:
    """Mean rate output over [t0, t1] cut to whole dither periods: between the first and the last rising edge at
    least a sample interval dt inside it (an edge's interpolation reaches one sample either side),
    (I(e_last) - I(e_first)) / (e_last - e_first); NaN with fewer than two such edges."""
    inside = np.flatnonzero((edges >= t0 + dt) & (edges <= t1 - dt))
    if inside.size < 2:
        return math.nan
    a, b = inside[0], inside[-1]
    return float((integral[b] - integral[a]) / (edges[b] - edges[a]))


@dataclass
class WindowSums:
    """The truth's samples at or after start_s (a step's analysis window, fed until the step ends): their count
    and the sums of their scale factor and gyro temperature."""

    start_s: float
    samples: int = 0
    sf_sum: float = 0.0
    temp_sum: float = 0.0

    def add(self, time: np.ndarray, scale_factor: np.ndarray, temperature: np.ndarray) -> None:
        m = np.asarray(time) >= self.start_s
        k = int(np.count_nonzero(m))
        if k:
            self.samples += k
            self.sf_sum += float(np.sum(np.asarray(scale_factor)[m]))
            self.temp_sum += float(np.sum(np.asarray(temperature)[m]))

    def row(self, index: int, end_s: float) -> dict[str, float]:
        """The window's /windows row: its bounds, the count and the means (NaN without samples)."""
        n = self.samples
        return {
            "index": float(index),
            "window_start": self.start_s,
            "window_end": end_s,
            "truth_samples": float(n),
            "truth_scale_factor": self.sf_sum / n if n else math.nan,
            "truth_temperature": self.temp_sum / n if n else math.nan,
        }
