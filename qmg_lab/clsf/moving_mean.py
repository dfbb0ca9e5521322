"""The moving mean over run time of the CLSF scale-factor estimate: the one rule every display of it calls.

One dither period's estimate scatters by several hundred ppm on the paper's bench; the mean over the last
SF_MEAN_WINDOW_S of run time is the figure a person can read. The rule, for a window [lo, hi] of run time:

    mean = sum(y_i for lo <= t_i <= hi and y_i finite) / count(lo <= t_i <= hi and y_i finite)

NaN where the window holds no finite value. `window_mean` computes it for every row at once from cumulative sums
(the run's summary, the run list, the watch page, `Run.clsf_with_temperatures`, the figures); `MovingMean` keeps
the last window of a stream (the live panel, the runner's summary) and asks `window_mean` for its value.
"""

from __future__ import annotations

from collections import deque

import numpy as np

SF_MEAN_WINDOW_S = 60.0  # run time over which the SF estimate is averaged, s


def window_mean(t: np.ndarray, y: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Mean of the finite y over the rows with lo_i <= t <= hi_i (t increasing), O(n) from one cumulative sum of
    the finite values and one of their count; NaN for a window without a finite value."""
    t = np.asarray(t, dtype=float)
    if t.shape[0] == 0:
        return np.full(np.shape(lo), np.nan)
    y = np.asarray(y, dtype=float)
    finite = np.isfinite(y)
    sums = np.concatenate(([0.0], np.cumsum(np.where(finite, y, 0.0))))
    counts = np.concatenate(([0], np.cumsum(finite)))
    first = np.searchsorted(t, lo, side="left")
    last = np.searchsorted(t, hi, side="right")
    n = counts[last] - counts[first]
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(n > 0, (sums[last] - sums[first]) / np.maximum(n, 1), np.nan)


def trailing_mean(t: np.ndarray, y: np.ndarray, window_s: float = SF_MEAN_WINDOW_S) -> np.ndarray:
    """The mean over [t_i - window_s, t_i] at each row: what a live display can show, at the price of a lag of
    about window_s / 2 on a trend."""
    t = np.asarray(t, dtype=float)
    return window_mean(t, y, t - window_s, t)


def centred_mean(t: np.ndarray, y: np.ndarray, window_s: float = SF_MEAN_WINDOW_S) -> np.ndarray:
    """The mean over [t_i - window_s / 2, t_i + window_s / 2]: no lag on a trend, for a finished record."""
    t = np.asarray(t, dtype=float)
    return window_mean(t, y, t - 0.5 * window_s, t + 0.5 * window_s)


def last_window_mean(t: np.ndarray, y: np.ndarray, window_s: float = SF_MEAN_WINDOW_S) -> float:
    """The mean over the last window_s of the record, [t[-1] - window_s, t[-1]]; NaN for an empty record."""
    t = np.asarray(t, dtype=float)
    if t.shape[0] == 0:
        return float("nan")
    return float(window_mean(t, y, t[-1:] - window_s, t[-1:])[0])


class MovingMean:
    """The window mean of a stream of (run time, value) samples over its last `window_s` of run time (the rule
    above); a run time that goes back (a new run) starts the window afresh."""

    def __init__(self, window_s: float = SF_MEAN_WINDOW_S) -> None:
        self.window_s = window_s
        self._t: deque[float] = deque()
        self._y: deque[float] = deque()

    def add(self, t_s: float, value: float) -> None:
        if self._t and t_s < self._t[-1]:
            self._t.clear()
            self._y.clear()
        self._t.append(t_s)
        self._y.append(value)
        while self._t[0] < t_s - self.window_s:
            self._t.popleft()
            self._y.popleft()

    @property
    def count(self) -> int:
        """The finite values in the window."""
        return int(np.count_nonzero(np.isfinite(np.fromiter(self._y, float, len(self._y)))))

    @property
    def mean(self) -> float:
        """The window's mean, NaN when it holds no finite value."""
        return last_window_mean(
            np.fromiter(self._t, float, len(self._t)), np.fromiter(self._y, float, len(self._y)), self.window_s
        )
