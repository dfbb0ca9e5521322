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

from dataclasses import dataclass, field

import numpy as np

INTERMEDIATE = 0.02  # a sample within 2 % of either level counts as that level
HYSTERESIS = 0.25  # high above 1 - this fraction of the step, low below it, else the previous side


def plateau_levels(d: np.ndarray, lo: float, hi: float) -> tuple[float, float]:
    """(lo, hi) updated from a block of readings d: the means of the readings above mid + 0.45 span and below
    mid - 0.45 span (mid, span of the current levels: plateau readings only, an edge's intermediate reading is
    excluded); a level with no such reading is kept."""
    mid = 0.5 * (lo + hi)
    span = hi - lo
    high = d[d > mid + 0.45 * span]
    low = d[d < mid - 0.45 * span]
    new_hi = float(np.sum(high)) / high.size if high.size else hi
    new_lo = float(np.sum(low)) / low.size if low.size else lo
    return new_lo, new_hi


def level_crossings(
    t: np.ndarray,
    d: np.ndarray,
    lo: float,
    hi: float,
    prev: tuple[float, float, int],
    window_s: float,
    hysteresis: float,
    intermediate: float,
) -> tuple[np.ndarray, np.ndarray, float, bool]:
    """The edges in a block of dither readings d at times t (module docstring): (rising times, falling times, the
    last reading's fraction s, its side). prev = (time, s, side 0/1) of the previous block's last reading, side -1
    when there is none (then its time and s are not used).

    With s_k = (d_k - lo) / (hi - lo): a reading is high above 1 - hysteresis, low below hysteresis, else on the
    side of the last clear one (the clear readings' sides carried forward); the first reading's side is the
    previous block's, or its own (s > 1/2 if unclear). At each change of side, k the first reading on the new side:
    the edge is at the middle of the gap t_e = (t_(k-1) + t_k - W) / 2, unless a window holds it:
    t_e = t_(k-1) - W f_old if window k-1 has a fraction f_old > intermediate on the new level, and
    t_e = t_k - W f_new if window k has intermediate < f_new < 1 - intermediate (the latter wins)."""
    prev_t, prev_s, prev_side = prev
    ss = (d - lo) / (hi - lo)
    tt = t
    if prev_side >= 0:
        tt = np.concatenate(([prev_t], t))
        ss = np.concatenate(([prev_s], ss))
        first = prev_side == 1
    elif ss[0] > 1.0 - hysteresis:
        first = True
    elif ss[0] < hysteresis:
        first = False
    else:
        first = bool(ss[0] > 0.5)
    state = np.full(ss.size, -1, dtype=np.int8)  # -1: unclear, keeps the side before it
    state[ss < hysteresis] = 0
    state[ss > 1.0 - hysteresis] = 1
    state[0] = first
    last_clear = np.where(state >= 0, np.arange(ss.size), 0)
    np.maximum.accumulate(last_clear, out=last_clear)
    side = state[last_clear] == 1
    k = np.flatnonzero(side[1:] != side[:-1]) + 1
    now = side[k]
    frac_new = np.where(now, ss[k], 1.0 - ss[k])
    frac_old = np.where(now, ss[k - 1], 1.0 - ss[k - 1])
    e = 0.5 * (tt[k - 1] + tt[k] - window_s)
    if window_s > 0.0:
        e = np.where(frac_old > intermediate, tt[k - 1] - window_s * frac_old, e)
        inside = (frac_new > intermediate) & (frac_new < 1.0 - intermediate)
        e = np.where(inside, tt[k] - window_s * frac_new, e)
    return e[now], e[~now], float(ss[-1]), bool(side[-1])


def line_at(hist_t: np.ndarray, hist_j: np.ndarray, j: np.ndarray) -> np.ndarray:
    """The least-squares line t = a + b j through the pairs (hist_j, hist_t), at the indices j: about the last pair
    (t0, j0), x = j - j0, y = t - t0, slope = sum (x - xm)(y - ym) / sum (x - xm)^2 (0 if the latter is 0),
    t(j) = t0 + ym + slope (j - j0 - xm); the last time when fewer than two pairs."""
    n = hist_t.size
    if n < 2:
        return np.full(j.size, hist_t[n - 1])
    t0, j0 = hist_t[n - 1], hist_j[n - 1]
    x = hist_j - j0
    y = hist_t - t0
    xm = x.sum() / n
    ym = y.sum() / n
    dx = x - xm
    sxx = float(dx @ dx)
    slope = float(dx @ (y - ym)) / sxx if sxx > 0 else 0.0
    return (j - (j0 + xm)) * slope + (t0 + ym)


def rolling_line_fit(all_t: np.ndarray, all_j: np.ndarray, start_new: int, fit_edges: int) -> np.ndarray:
    """For each point from start_new on, the least-squares line through it and the fit_edges - 1 points before
    (fewer at the start), evaluated at its own index; the point itself where fewer than 4 points are fitted.

    About the first point (t0, j0): x = j - j0, y = t - t0; with window sums n, Sx, Sy, Sxx, Sxy (differences of
    running sums), slope = (n Sxy - Sx Sy) / (n Sxx - Sx^2) (0 if that is <= 0), intercept = (Sy - slope Sx) / n,
    t = t0 + intercept + slope x."""
    t0, j0 = all_t[0], all_j[0]
    c = np.zeros((5, all_t.size + 1))
    c[0, 1:] = 1.0
    np.subtract(all_j, j0, out=c[1, 1:])
    np.subtract(all_t, t0, out=c[2, 1:])
    np.multiply(c[1, 1:], c[1, 1:], out=c[3, 1:])
    np.multiply(c[1, 1:], c[2, 1:], out=c[4, 1:])
    np.cumsum(c, axis=1, out=c)
    end = np.arange(start_new + 1, all_t.size + 1)
    n, sx, sy, sxx, sxy = c[:, end] - c[:, np.maximum(0, end - fit_edges)]
    den = n * sxx - sx * sx
    slope = np.zeros(end.size)
    np.divide(n * sxy - sx * sy, den, out=slope, where=den > 0)
    icpt = (sy - slope * sx) / n
    return np.where(n >= 4, t0 + icpt + slope * (all_j[start_new:] - j0), all_t[start_new:])


def continue_fit(
    hist_t: np.ndarray, hist_j: np.ndarray, te: np.ndarray, period: float, fit_edges: int
) -> tuple[bool, np.ndarray, np.ndarray]:
    """New edges of one kind continuing a fit's history (the last fit_edges edges, times hist_t at cycle indices
    hist_j): (they follow the line, their cycle indices, their smoothed times).

    Each new edge's index advances by max(1, rint(gap / period)) cycles from the previous edge; when any lies more
    than a quarter period off the history's line (line_at) they do not follow it (the generator was reprogrammed);
    otherwise each is replaced by rolling_line_fit's value."""
    steps = np.maximum(1.0, np.rint(np.diff(te, prepend=hist_t[-1]) / period))
    j = np.int64(hist_j[-1]) + np.cumsum(steps.astype(np.int64))
    jf = j.astype(np.float64)
    if (np.abs(te - line_at(hist_t, hist_j, jf)) > 0.25 * period).any():
        return False, j, te
    return True, j, rolling_line_fit(np.concatenate((hist_t, te)), np.concatenate((hist_j, jf)), hist_t.size, fit_edges)


def edge_threshold_v(amplitude_vpp: float) -> float:
    """The smallest recorded level step taken for a running dither: half the square wave's peak-to-peak amplitude.

    A running dither steps by its full Vpp at every edge; with the dither muted (AMPL 0VP) the AuxIn shows only its
    reading noise and ADC steps, orders of magnitude below Vpp / 2, so half the amplitude tells the two apart with a
    factor of two of margin on either side (an attenuated or a mis-set amplitude still counts as running)."""
    return 0.5 * amplitude_vpp


@dataclass
class EdgeTracker:
    """Streams dither samples in; returns the smoothed times of the rising and falling edges found."""

    window_s: float = 0.0  # the AuxIn averaging window W, s
    fit_edges: int = 32
    min_step_v: float = 0.0  # the smallest level step taken for a running dither (edge_threshold_v), V
    lo: float | None = None
    hi: float | None = None
    _prev_t: float | None = None
    _prev_s: float | None = None
    _prev_high: bool | None = None
    # each kind's edge history: row 0 the times (s), row 1 the cycle indices, in the first _count columns
    _hist: dict[int, np.ndarray] = field(default_factory=lambda: {1: np.empty((2, 0)), -1: np.empty((2, 0))})
    _count: dict[int, int] = field(default_factory=lambda: {1: 0, -1: 0})

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
        self.lo, self.hi = plateau_levels(d, self.lo, self.hi)

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
        rising, falling, last_s, last_high = level_crossings(
            t, d, self.lo, self.hi, prev, self.window_s, HYSTERESIS, INTERMEDIATE
        )
        self._prev_t, self._prev_s, self._prev_high = float(t[-1]), float(last_s), bool(last_high)
        return self._smooth_all(1, rising), self._smooth_all(-1, falling)

    def _history(self, kind: int) -> tuple[np.ndarray, np.ndarray]:
        """(times, cycle indices) of the edges of one kind remembered (views)."""
        n = self._count[kind]
        return self._hist[kind][0, :n], self._hist[kind][1, :n]

    def _smooth_all(self, kind: int, te: np.ndarray) -> np.ndarray:
        """Smoothed times of a block's new edges of one kind (a rolling least-squares line; continue_fit).

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
        follows, j, fitted = continue_fit(hist_t, hist_j, te, period, self.fit_edges)
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
        """The least-squares line through the last fit_edges (index, time) pairs, at index j (line_at)."""
        return float(line_at(raw[-self.fit_edges :], idx[-self.fit_edges :], np.array([j]))[0])
