"""A moving mean over run time: what the panel and the run's summary show of the CLSF scale-factor estimate.

One dither period's estimate scatters by several hundred ppm on the paper's bench; the mean over the last
SF_MEAN_WINDOW_S of run time is the figure a person can read (the page of `qmg-lab watch` draws the same mean).
"""

from __future__ import annotations

import math
from collections import deque

SF_MEAN_WINDOW_S = 60.0  # run time over which the SF estimate is averaged, s


class MovingMean:
    """Mean of (run time, value) samples over the last `window_s` of run time; non-finite values are skipped, and
    a run time that goes back (a new run) starts the window afresh."""

    def __init__(self, window_s: float) -> None:
        self.window_s = window_s
        self._samples: deque[tuple[float, float]] = deque()

    def add(self, t_s: float, value: float) -> None:
        if self._samples and t_s < self._samples[-1][0]:
            self._samples.clear()
        if math.isfinite(value):
            self._samples.append((t_s, value))
        while self._samples and self._samples[0][0] < t_s - self.window_s:
            self._samples.popleft()

    @property
    def count(self) -> int:
        return len(self._samples)

    @property
    def mean(self) -> float:
        """The window's mean (math.fsum / n), NaN when the window holds no estimate."""
        n = len(self._samples)
        return math.fsum(v for _, v in self._samples) / n if n else float("nan")
