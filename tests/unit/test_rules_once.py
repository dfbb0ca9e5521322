"""The rules written once (issue: "each rule once"): the +-rate pair rule, the 60 s window mean, the dither edge
threshold. Each is checked against its definition written out here, on cases built to hit its edges."""

from __future__ import annotations

import math

import numpy as np
import pytest

from qmg_lab.analysis.reductions import rate_pairs
from qmg_lab.clsf.dither_edges import edge_threshold_v
from qmg_lab.clsf.moving_mean import MovingMean, centred_mean, last_window_mean, trailing_mean, window_mean


def test_rate_pairs_are_plus_then_minus_rate_steps_in_a_row() -> None:
    steps = {
        0: ("lock", 0.0),
        1: ("rate", 5.0),
        2: ("rate", -5.0),  # pair 1-2
        3: ("rate", 5.0),
        # 4 missing (not completed): 3 has no partner
        5: ("rate", -5.0),
        6: ("rate", 5.0),
        7: ("hold", -5.0),  # a hold is not a rate step
        8: ("rate", -5.0),
        9: ("rate", 5.0),  # -5 then +5: the wrong order, no pair 8-9
        10: ("rate", 0.0),
        11: ("rate", -5.0),  # 0 is not > 0
        12: ("rate", 2.0),
        13: ("rate", -3.0),  # unequal magnitudes are still a pair
    }
    assert rate_pairs(steps) == [1, 12]


def test_the_window_mean_skips_nan_and_is_nan_only_for_an_empty_window() -> None:
    t = np.arange(0.0, 200.0, 2.0)
    y = t.copy()
    y[50] = np.nan  # t = 100
    got = trailing_mean(t, y)
    for i, ti in enumerate(t):
        inside = (t >= ti - 60.0) & (t <= ti) & np.isfinite(y)
        assert got[i] == pytest.approx(y[inside].mean(), rel=1e-15)
    assert math.isnan(last_window_mean(np.zeros(0), np.zeros(0)))
    assert math.isnan(float(window_mean(t, np.full_like(t, np.nan), t[:1] - 60.0, t[:1])[0]))
    c = centred_mean(t, y, 20.0)
    inside = (t >= 40.0 - 10.0) & (t <= 40.0 + 10.0)
    assert c[20] == pytest.approx(y[inside].mean(), rel=1e-15)


def test_the_stream_mean_and_the_array_mean_are_one_rule() -> None:
    rng = np.random.default_rng(1)
    t = np.cumsum(rng.uniform(0.05, 0.3, 2000))
    y = rng.normal(0.0, 1e-4, t.shape[0])
    y[rng.integers(0, t.shape[0], 40)] = np.nan
    stream = MovingMean()
    for ti, yi in zip(t, y, strict=True):
        stream.add(float(ti), float(yi))
    # the same sum from two cumulative sums (over the window, over the record): n eps max|y| bounds the difference
    bound = t.shape[0] * np.finfo(float).eps * np.nanmax(np.abs(y))
    assert abs(stream.mean - last_window_mean(t, y)) <= bound
    assert stream.count == int(np.count_nonzero(np.isfinite(y[t >= t[-1] - 60.0])))


def test_the_edge_threshold_is_half_the_peak_to_peak_amplitude() -> None:
    assert edge_threshold_v(0.6) == 0.3
