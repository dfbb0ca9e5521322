"""The study storage level's running reductions (qmg_lab/storage/summary.py), bit for bit against the direct
computations they replace."""

from __future__ import annotations

import numpy as np

from qmg_lab.clsf.dither_edges import EdgeTracker
from qmg_lab.storage.summary import EDGE_CHUNK_SAMPLES, _EdgeIntegrator, _Window

FS = 1800.0


def test_window_sums_equal_the_sums_over_the_selected_samples() -> None:
    """A step's truth means: count and numpy sums of the samples at or after the window start, block by block
    (a block before the window, one across its start, blocks inside), exactly as summing the masked samples."""
    rng = np.random.default_rng(6)
    start = 7.25
    w = _Window(start_s=start)
    count, sf_sum, temp_sum = 0, 0.0, 0.0
    for k in range(6):
        t = (k * 3600 + np.arange(3600)) / FS
        sf = 0.06 * (1.0 + 1e-3 * rng.standard_normal(3600))
        temp = 25.0 + rng.standard_normal(3600)
        w.add(t, sf, temp)
        m = t >= start
        count += int(m.sum())
        if m.any():
            sf_sum += float(np.sum(sf[m]))
            temp_sum += float(np.sum(temp[m]))
    assert w.samples == count == 6 * 3600 - int(start * FS)
    assert w.sf_sum == sf_sum
    assert w.temp_sum == temp_sum


def _dither_stream(n: int, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """n samples at FS of a recorded 7 Hz square dither (+-0.3 V, reading noise) and a noisy rate output."""
    rng = np.random.default_rng(seed)
    t = 12.5 + np.arange(n) / FS
    dither = 0.3 * np.sign(np.sin(2 * np.pi * 7.0 * t + 0.3)) + 1e-4 * rng.standard_normal(n)
    rate_output = 0.3 + 0.01 * np.sin(2 * np.pi * 0.05 * t) + 1e-3 * rng.standard_normal(n)
    return t, dither, rate_output


def test_edges_and_integrals_equal_the_analysis_over_the_whole_column() -> None:
    """Blocks of any size in (a straddling block, a single sample, blocks longer than a chunk), edges and
    integrals out: bit for bit what the analysis computes on the whole columns of a full file, the integral as one
    cumsum from the first sample, the edges by a tracker fed 36000-sample chunks, the integral interpolated at
    them over the whole column."""
    n = 3 * EDGE_CHUNK_SAMPLES + 12345
    t, d, r = _dither_stream(n, seed=7)
    sizes = [3600, 1, 999, EDGE_CHUNK_SAMPLES + 5, 3600, 17, n]  # the last block takes the rest
    integrator = _EdgeIntegrator(tracker=EdgeTracker(min_step_v=0.3))
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

    whole = np.cumsum(np.concatenate(([0.0], 0.5 * np.diff(t) * (r[1:] + r[:-1]))))
    tracker = EdgeTracker(min_step_v=0.3)
    edges = np.concatenate(
        [
            tracker.process(t[k : k + EDGE_CHUNK_SAMPLES], d[k : k + EDGE_CHUNK_SAMPLES])[0]
            for k in range(0, n, EDGE_CHUNK_SAMPLES)
        ]
    )
    assert edges.shape[0] > 7 * (t[-1] - t[0]) - 2  # a rising edge every dither period
    np.testing.assert_array_equal(np.concatenate(got_edges), edges)
    np.testing.assert_array_equal(np.concatenate(got_integrals), np.interp(edges, t, whole))
