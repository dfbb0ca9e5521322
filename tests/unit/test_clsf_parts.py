"""The CLSF estimator's parts against their equations: the demodulator filter model, edge location, stream plan."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import signal

from qmg_lab.clsf.demod_filter import DemodFilter
from qmg_lab.clsf.dither_edges import EdgeTracker
from qmg_lab.clsf.stream_plan import StreamPlan, edge_phase_gap, hf2_rate


# ---------------------------------------------------------------------------------------------- demod filter
@pytest.mark.parametrize(("order", "tc"), [(1, 1e-4), (3, 3e-4), (8, 1e-3)])
def test_ramp_response_matches_a_fine_numerical_integration_of_the_cascade(order: int, tc: float) -> None:
    # n first-order stages y_j' = (y_(j-1) - y_j)/tc driven by u = t, integrated by scipy's lsim on a fine grid
    f = DemodFilter(order, tc)
    t = np.linspace(0.0, 30 * tc * order, 20001)
    sys = signal.lti([], [-1.0 / tc] * order, (1.0 / tc) ** order)
    _, y, _ = signal.lsim(sys, t, t)
    np.testing.assert_allclose(f.ramp_response(t), y, atol=1e-9 * t[-1])
    # steady state: the input delayed by the group delay n tc
    assert f.ramp_response(np.array([200 * tc * order]))[0] == pytest.approx(200 * tc * order - order * tc)


def test_foh_discretization_is_exact_for_inputs_linear_between_samples() -> None:
    f = DemodFilter(4, 5e-4)
    dt = 1 / 1800
    t = np.arange(400) * dt
    u = np.where(t < 0.05, t, 0.05 - 2 * (t - 0.05))  # piecewise linear with its kink on a sample
    fine = np.linspace(0, t[-1], 400 * 200 + 1)
    sys = signal.lti([], [-1 / 5e-4] * 4, (1 / 5e-4) ** 4)
    _, yf, _ = signal.lsim(sys, np.interp(fine, t, u), fine)
    y = signal.sosfilt(f.foh_sos(dt), u)
    np.testing.assert_allclose(y, np.interp(t, fine, yf), atol=1e-7)


def test_filter_gain_and_bandwidth() -> None:
    f = DemodFilter(2, 1e-3)
    f3 = f.bandwidth_3db_hz()
    assert float(f.gain(f3)) == pytest.approx(1 / math.sqrt(2), rel=1e-12)
    assert f.delay_s == pytest.approx(2e-3)
    with pytest.raises(ValueError, match="order"):
        DemodFilter(9, 1e-3)


# ---------------------------------------------------------------------------------------------- edges
def _square_record(t: np.ndarray, period: float, t0: float, window: float) -> np.ndarray:
    """AuxIn readings of a +-1 square wave (high on [t0 + k T, t0 + (k + 1/2) T)), each the mean over [t - W, t]."""

    def integral(x: np.ndarray) -> np.ndarray:  # of the square wave from t0
        u = (x - t0) / period
        fr = u - np.floor(u)
        return period * np.where(fr < 0.5, fr, 1.0 - fr)

    if window == 0:
        u = (t - t0) / period
        return np.where(u - np.floor(u) < 0.5, 1.0, -1.0)
    return (integral(t) - integral(t - window)) / window


def test_edges_inside_an_averaging_window_are_located_exactly() -> None:
    dt, period, t0, w = 1 / 1800, 1 / 7.0003, 0.01234, 0.8 / 1800
    t = np.arange(1, 1800 * 20) * dt
    d = _square_record(t, period, t0, w)
    rising, _ = EdgeTracker(window_s=w).process(t, d)
    true = t0 + period * np.round((rising - t0) / period)
    assert rising.size > 100
    # edges caught inside a window are exact; the rest sit in gaps of 0.2 dt; the 32-edge line fits them all
    assert np.max(np.abs(rising[40:] - true[40:])) < 0.05 * dt


def test_edges_between_instantaneous_readings_are_refined_by_the_line_fit() -> None:
    dt, period, t0 = 1 / 1800, 1 / 7.0, 0.0031
    t = np.arange(1, 1800 * 30) * dt
    d = _square_record(t, period, t0, 0.0)
    tracker = EdgeTracker()
    parts = [tracker.process(t[i : i + 3600], d[i : i + 3600]) for i in range(0, t.size, 3600)]
    rising = np.concatenate([p[0] for p in parts])
    falling = np.concatenate([p[1] for p in parts])
    true_r = t0 + period * np.round((rising - t0) / period)
    true_f = t0 + period * (np.round((falling - t0) / period - 0.5) + 0.5)
    # 257.14 samples per period: the gap errors (uniform within +-dt/2) average out over the fit window
    assert np.sqrt(np.mean((rising[40:] - true_r[40:]) ** 2)) < 0.1 * dt
    assert np.sqrt(np.mean((falling[40:] - true_f[40:]) ** 2)) < 0.1 * dt


# ---------------------------------------------------------------------------------------------- stream plan
def test_edge_phase_gap() -> None:
    assert edge_phase_gap(200.0) == pytest.approx(1.0)  # every edge at the same place
    assert edge_phase_gap(200.5) == pytest.approx(0.5)  # two places
    assert edge_phase_gap(1800 / 7) == pytest.approx(1 / 7, abs=1e-9)  # seven places, evenly spread


def test_stream_plan_refuses_commensurate_pairs_and_hf2_rates_are_the_ladder() -> None:
    assert StreamPlan(1800.0, 9.0, 1, 1e-4).problem() is not None  # exactly 200 samples per period
    assert StreamPlan(1800.0, 7.0, 1, 1e-4).problem() is None
    assert [hf2_rate(r) for r in (1400, 1800, 2000, 3000, 1e6)] == [1800.0, 1800.0, 1800.0, 3600.0, 460800.0]
