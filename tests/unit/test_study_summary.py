"""The analysis's reductions (qmg_lab/analysis/reductions.py), fed block by block as the study storage level feeds
them, against independent numpy forms over the whole columns, to derived rounding bounds."""

from __future__ import annotations

import numpy as np

from qmg_lab.analysis.reductions import (
    EDGE_CHUNK_SAMPLES,
    EdgeIntegrator,
    RateIntegral,
    WindowSums,
    edges_and_integrals,
    mean_between_edges,
)
from qmg_lab.clsf.dither_edges import EdgeTracker

FS = 1800.0
EPS = np.finfo(float).eps


def test_window_sums_are_the_counts_and_means_of_the_samples_in_the_window() -> None:
    """A step's truth window fed block by block (a block before the window, one across its start, blocks inside):
    the count of the samples at or after the start, and means within the rounding of a sum of n terms of one
    sign (n eps of the mean) of numpy's means over the masked samples."""
    rng = np.random.default_rng(6)
    start = 7.25
    w = WindowSums(start_s=start)
    t_all, sf_all, temp_all = [], [], []
    for k in range(6):
        t = (k * 3600 + np.arange(3600)) / FS
        sf = 0.06 * (1.0 + 1e-3 * rng.standard_normal(3600))
        temp = 25.0 + rng.standard_normal(3600)
        w.add(t, sf, temp)
        t_all.append(t), sf_all.append(sf), temp_all.append(temp)
    t, sf, temp = np.concatenate(t_all), np.concatenate(sf_all), np.concatenate(temp_all)
    m = t >= start
    row = w.row(3, 12.0)
    assert row["truth_samples"] == w.samples == m.sum() == 6 * 3600 - int(start * FS)  # counts: exact
    n = w.samples
    assert abs(row["truth_scale_factor"] - np.mean(sf[m])) <= 2 * n * EPS * np.mean(np.abs(sf[m]))
    assert abs(row["truth_temperature"] - np.mean(temp[m])) <= 2 * n * EPS * np.mean(np.abs(temp[m]))
    assert (row["index"], row["window_start"], row["window_end"]) == (3.0, start, 12.0)
    assert np.isnan(WindowSums(start_s=1.0).row(0, 2.0)["truth_scale_factor"])  # no samples: no mean


def _dither_stream(n: int, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """n samples at FS of a recorded 7 Hz square dither (+-0.3 V, reading noise) and a noisy rate output."""
    rng = np.random.default_rng(seed)
    t = 12.5 + np.arange(n) / FS
    dither = 0.3 * np.sign(np.sin(2 * np.pi * 7.0 * t + 0.3)) + 1e-4 * rng.standard_normal(n)
    rate_output = 0.3 + 0.01 * np.sin(2 * np.pi * 0.05 * t) + 1e-3 * rng.standard_normal(n)
    return t, dither, rate_output


def test_edges_and_integrals_fed_in_blocks_are_those_of_the_whole_columns() -> None:
    """Blocks of any size in (a straddling block, a single sample, blocks longer than a chunk): the same edges as
    the tracker fed the whole record in 36000-sample chunks (the same chunks of the same numbers: the same
    code's result), and the integral at them within the rounding of a running sum of k terms (k eps times the sum
    of their magnitudes, from both sides) of the trapezoid rule written as one cumsum over the whole column."""
    n = 3 * EDGE_CHUNK_SAMPLES + 12345
    t, d, r = _dither_stream(n, seed=7)
    sizes = [3600, 1, 999, EDGE_CHUNK_SAMPLES + 5, 3600, 17, n]  # the last block takes the rest
    integrator = EdgeIntegrator(tracker=EdgeTracker(min_step_v=0.3))
    got_edges, got_integrals = [], []
    start = 0
    for size in sizes:
        stop = min(start + size, n)
        for rising, integral in integrator.feed(t[start:stop], d[start:stop], r[start:stop]):
            got_edges.append(rising)
            got_integrals.append(integral)
        start = stop
    assert start == n
    for rising, integral in integrator.finish():
        got_edges.append(rising)
        got_integrals.append(integral)

    terms = np.concatenate(([0.0], 0.5 * np.diff(t) * (r[1:] + r[:-1])))
    whole = np.cumsum(terms)
    tracker = EdgeTracker(min_step_v=0.3)
    edges = np.concatenate(
        [
            tracker.process(t[k : k + EDGE_CHUNK_SAMPLES], d[k : k + EDGE_CHUNK_SAMPLES])[0]
            for k in range(0, n, EDGE_CHUNK_SAMPLES)
        ]
    )
    assert edges.shape[0] > 7 * (t[-1] - t[0]) - 2  # a rising edge every dither period
    np.testing.assert_array_equal(np.concatenate(got_edges), edges)
    bound = 2 * np.arange(1, n + 1) * EPS * np.cumsum(np.abs(terms))
    got = np.concatenate(got_integrals)
    assert np.all(np.abs(got - np.interp(edges, t, whole)) <= np.interp(edges, t, bound) + EPS * np.abs(got))
    # the whole-record form the analysis uses on a full file
    e_all, i_all = edges_and_integrals(t, d, r, 0.3)
    np.testing.assert_array_equal(e_all, edges)
    assert np.all(np.abs(i_all - got) <= 2 * np.interp(edges, t, bound) + 2 * EPS * np.abs(got))


def test_a_rate_integral_in_blocks_is_the_trapezoid_rule() -> None:
    """The integral of r = a + b t (the trapezoid rule is exact on a line) over blocks of several sizes: within the
    running sum's rounding (k eps of the partial sums) of a t + b t^2 / 2 from the first sample."""
    t = 3.0 + np.arange(20000) / FS
    a, b = 0.3, -0.02
    r = a + b * t
    integral = RateIntegral()
    got = np.concatenate([integral.feed(t[i:j], r[i:j]) for i, j in ((0, 1), (1, 7), (7, 5000), (5000, 20000))])
    exact = a * (t - t[0]) + 0.5 * b * (t**2 - t[0] ** 2)
    k = np.arange(1, t.size + 1)
    assert np.all(np.abs(got - exact) <= 4 * k * EPS * np.cumsum(np.abs(r) / FS) + 4 * EPS * np.abs(t) ** 2)


def test_mean_between_edges_is_the_mean_over_whole_periods() -> None:
    edges = 10.0 + np.arange(20) / 7.0
    integral = 0.25 * edges + 3.0  # a constant rate output of 0.25 V
    # the integral's values (<= 6 V s) each rounded within eps of their size, their difference over at least one
    # period (1/7 s): within 4 eps 6 * 7 of 0.25
    assert abs(mean_between_edges(edges, integral, 10.05, 12.0, 1 / FS) - 0.25) <= 4 * EPS * 6.0 * 7.0
    assert np.isnan(mean_between_edges(edges, integral, 10.05, 10.2, 1 / FS))  # fewer than two edges inside
