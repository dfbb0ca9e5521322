"""Min/max decimation (qmg_lab/data/decimate.py): bounded output, the envelope of every span kept exactly."""

from __future__ import annotations

import numpy as np

from qmg_lab.data.decimate import minmax


def test_bounded_and_keeps_each_spans_extremes() -> None:
    rng = np.random.default_rng(1)
    t = np.cumsum(rng.uniform(0.5, 1.5, 100_000))  # irregular sampling
    y = rng.standard_normal(t.shape[0])
    y[12_345] = 50.0  # a spike a stride would drop
    y[777] = np.nan
    bins = 500
    td, yd = minmax(t, y, bins)
    assert td.shape[0] <= 2 * bins + 2 and np.all(np.diff(td) > 0)
    assert td[0] == t[0] and td[-1] == t[-1]
    assert 50.0 in yd
    edges = np.linspace(t[0], t[-1], bins + 1)
    span = np.clip(np.searchsorted(edges, t, side="right") - 1, 0, bins - 1)
    span_d = np.clip(np.searchsorted(edges, td, side="right") - 1, 0, bins - 1)
    for k in range(0, bins, 37):  # the same values: selection only, no arithmetic, so compared exactly
        assert np.nanmax(yd[span_d == k]) == np.nanmax(y[span == k])
        assert np.nanmin(yd[span_d == k]) == np.nanmin(y[span == k])


def test_short_input_unchanged() -> None:
    t = np.arange(10.0)
    td, yd = minmax(t, t * 2, 5)
    assert td is t and np.array_equal(yd, t * 2)
