"""The edge tracker's four kernels as numpy expressions, for processes that should not load numba.

`qmg-lab analyze` locates the dither's edges of a whole run file once (qmg_lab/analysis/compute.py); importing
numba and loading its cached kernels would cost it about a second of start-up (numba's own modules, LLVM), more
than the work itself. These are the numpy forms that the compiled kernels (qmg_lab/clsf/kernels.py) reproduce
operation for operation: the same floating-point operations in the same order (sums are numpy's pairwise sums,
which kernels.pairwise_sum follows; running sums are sequential), so EdgeTracker(compiled=False) returns the same
edges bit for bit (tests/unit/test_clsf_parts.py). The equations are in the kernels' docstrings.
"""

from __future__ import annotations

import numpy as np


def plateau_levels(d: np.ndarray, lo: float, hi: float) -> tuple[float, float]:
    """kernels.plateau_levels: (lo, hi) from the means of the readings beyond mid +- 0.45 span (kept if none)."""
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
    """kernels.level_crossings: (rising times, falling times, last fraction s, last side).

    The side of each reading (high above 1 - hysteresis, low below hysteresis, else the last clear side) is the
    clear readings' sides carried forward; at each change of side the edge time follows the kernel's rules."""
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
    """kernels.line_at: the least-squares line through (hist_j, hist_t), about the last pair, at the indices j."""
    n = hist_t.size
    if n < 2:
        return np.full(j.size, hist_t[n - 1])
    t0, j0 = hist_t[n - 1], hist_j[n - 1]
    x = hist_j - j0
    y = hist_t - t0
    xm = np.sum(x) / n
    ym = np.sum(y) / n
    dx = x - xm
    sxx = np.sum(dx * dx)
    slope = np.sum(dx * (y - ym)) / sxx if sxx > 0 else 0.0
    return np.asarray(t0 + ym + slope * (j - j0 - xm), dtype=np.float64)


def rolling_line_fit(all_t: np.ndarray, all_j: np.ndarray, start_new: int, fit_edges: int) -> np.ndarray:
    """kernels.rolling_line_fit: each point from start_new on replaced by the line through it and the
    fit_edges - 1 points before (window sums as differences of running sums), itself below 4 points."""
    t0, j0 = all_t[0], all_j[0]
    x = all_j - j0
    y = all_t - t0
    c = np.zeros((5, all_t.size + 1))
    for row, v in enumerate((np.ones(all_t.size), x, y, x * x, x * y)):
        np.cumsum(v, out=c[row, 1:])
    end = np.arange(start_new, all_t.size) + 1
    w = c[:, end] - c[:, np.maximum(0, end - fit_edges)]
    n, sx, sy, sxx, sxy = w
    den = n * sxx - sx * sx
    slope = np.zeros(end.size)
    np.divide(n * sxy - sx * sy, den, out=slope, where=den > 0)
    icpt = (sy - slope * sx) / n
    return np.where(n >= 4, t0 + icpt + slope * (all_j[start_new:] - j0), all_t[start_new:])


def continue_fit(
    hist_t: np.ndarray, hist_j: np.ndarray, te: np.ndarray, period: float, fit_edges: int
) -> tuple[bool, np.ndarray, np.ndarray]:
    """kernels.continue_fit: (the new edges follow the history's line, their cycle indices, smoothed times)."""
    steps = np.maximum(1.0, np.rint(np.diff(np.concatenate(([hist_t[-1]], te))) / period))
    j = np.int64(hist_j[-1]) + np.cumsum(steps.astype(np.int64))
    jf = j.astype(np.float64)
    if np.any(np.abs(te - line_at(hist_t, hist_j, jf)) > 0.25 * period):
        return False, j, te
    return True, j, rolling_line_fit(np.concatenate((hist_t, te)), np.concatenate((hist_j, jf)), hist_t.size, fit_edges)
