"""Min/max decimation: a trace of any length drawn with a bounded number of points that keeps its envelope.

The time axis is cut into `bins` equal spans; each span that holds samples contributes its minimum and its
maximum, in time order (two points; one if they are the same sample), and the first and last samples are always
kept (the trace starts and ends where the data does: a live page shows the newest time). A line through them
covers exactly the
vertical extent a line through every sample would cover in each span, which is what the eye reads from a
dense trace; spikes are never lost (what a stride `y[::k]` does). At most 2 x bins + 2 points come out,
whatever the input's length; an input of at most 2 x bins samples is returned as is.
"""

from __future__ import annotations

import numpy as np


def minmax(t: np.ndarray, y: np.ndarray, bins: int) -> tuple[np.ndarray, np.ndarray]:
    """(t, y) reduced to at most 2 x bins + 2 points (see the module docstring); t increasing, NaN in y skipped
    within a span (a span of only NaN keeps one NaN, so a gap stays a gap)."""
    n = t.shape[0]
    if n <= 2 * bins or bins < 1:
        return t, y
    edges = np.linspace(t[0], t[-1], bins + 1)
    starts = np.searchsorted(t, edges[:-1], side="left")
    starts = np.unique(starts[starts < n])
    finite = np.isfinite(y)
    ymin = np.where(finite, y, np.inf)
    ymax = np.where(finite, y, -np.inf)
    # the min and max of each span by reduceat, then their first position in the span (a span of only NaN
    # compares +-inf with +-inf and keeps its first sample)
    lo = np.minimum.reduceat(ymin, starts)
    hi = np.maximum.reduceat(ymax, starts)
    span = np.repeat(np.arange(starts.shape[0]), np.diff(np.append(starts, n)))
    first_lo = _first_index(ymin == lo[span], span, starts.shape[0])
    first_hi = _first_index(ymax == hi[span], span, starts.shape[0])
    idx = np.unique(np.concatenate((first_lo, first_hi, [0, n - 1])))
    return t[idx], y[idx]


def _first_index(hit: np.ndarray, span: np.ndarray, spans: int) -> np.ndarray:
    """The first index i with hit[i] in each span (every span has one: its own min and max)."""
    out = np.full(spans, -1, dtype=np.int64)
    where = np.flatnonzero(hit)
    s = span[where]
    first = np.ones(where.shape[0], dtype=bool)
    first[1:] = s[1:] != s[:-1]
    out[s[first]] = where[first]
    return out
