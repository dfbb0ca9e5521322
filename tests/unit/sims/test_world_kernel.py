"""The compiled World loops equal the vectorised equations they replace, bit for bit (sims/world_kernel.py).

Each reference below is the equation of sims/world.py's docstring written as numpy array expressions (sequential
cumulative sums, scipy's one-pole lfilter): the loops must give the same floating-point numbers, so a block's
inputs do not depend on which evaluated them."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.signal import lfilter

from sims import world_kernel as wk

DT = 1.0 / 1799.994857157551  # the HF2's 1800 Sa/s rung on a 210 MHz clockbase
N = 3600


def test_first_order_lag_is_lfilter_step_for_step() -> None:
    rng = np.random.default_rng(1)
    u = 25.0 + np.cumsum(rng.normal(0.0, 0.01, N))
    for tau_s in (60.0, 600.0, 1e-3):
        a = math.exp(-DT / tau_s)
        ref, _ = lfilter([0.0, 1.0 - a], [1.0, -a], u, zi=[25.3])
        y = np.empty(N)
        wk.first_order_lag(u, 25.3, a, y)
        np.testing.assert_array_equal(y, ref)
        assert y[0] == 25.3


@pytest.mark.parametrize("ripple_ppm", [0.0, 100.0, -2500.0])
@pytest.mark.parametrize("profile", ["hold", "ramp", "sine"])
def test_table_block_is_the_vectorised_ripple_and_angle(profile: str, ripple_ppm: float) -> None:
    k = np.arange(N) * DT + 0.5 * DT
    prof = {"hold": np.full(N, 5.0), "ramp": 5.0 - np.minimum(300.0 * k, 10.0), "sine": 3.0 * np.sin(2.1 * k)}[profile]
    angle0, scale, phase = 359.9, 1.0 + 60e-6, 17.0
    rate = prof * scale
    if ripple_ppm != 0.0:
        mid = angle0 + np.cumsum(rate) * DT - 0.5 * rate * DT
        rate = rate * (1.0 + ripple_ppm * 1e-6 * np.sin(np.deg2rad(mid + phase)))
    angle = angle0 + np.concatenate(([0.0], np.cumsum(rate[:-1]) * DT))
    r, a = np.empty(N), np.empty(N)
    wk.table_block(prof, scale, DT, angle0, ripple_ppm * 1e-6, phase, r, a)
    np.testing.assert_array_equal(r, rate)
    np.testing.assert_array_equal(a, angle)


def _wave_integral(fn: int, u: np.ndarray) -> np.ndarray:
    f = u - np.floor(u)
    if fn == wk.DITHER_SQUARE:
        return np.where(f < 0.5, f, 1.0 - f)
    if fn == wk.DITHER_TRIANGLE:
        return np.where(f < 0.5, -f + 2 * f * f, 3 * (f - 0.5) - 2 * (f * f - 0.25))
    if fn == wk.DITHER_RAMP:
        return f * f - f
    return (1.0 - np.cos(2 * np.pi * u)) / (2 * np.pi)


@pytest.mark.parametrize("fn", [wk.DITHER_SINE, wk.DITHER_SQUARE, wk.DITHER_TRIANGLE, wk.DITHER_RAMP])
def test_dither_grid_and_window_means_are_the_exact_integral_means(fn: int) -> None:
    t0, e0, ew, per = 1234.5678, 3e-6, 0.5e-6, 3600.0
    tb = t0 + DT * np.arange(N + 1)
    amp_s = ew * per / (2 * np.pi)
    origin = 1000.00037
    tau_origin = origin * (1.0 + e0) + amp_s * (1.0 - np.cos(2 * np.pi * origin / per))
    f_hz, phase, offset, half = 7.0, 0.125, 0.01, 0.5 * 0.8
    tau = tb * (1.0 + e0) + amp_s * (1.0 - np.cos(2 * np.pi * tb / per))
    u_ref = f_hz * (tau - tau_origin) + phase
    w_ref = _wave_integral(fn, u_ref)
    means_ref = offset + half * (w_ref[1:] - w_ref[:-1]) / (u_ref[1:] - u_ref[:-1])
    u, w, means = np.empty(N + 1), np.empty(N + 1), np.empty(N)
    wk.dither_grid(tb, e0, amp_s, per, float(tau_origin), f_hz, phase, fn, offset, half, u, w, means)
    np.testing.assert_array_equal(u, u_ref)
    np.testing.assert_array_equal(w, w_ref)
    np.testing.assert_array_equal(means, means_ref)
    window = 0.3 * DT
    du = (u_ref[1:] - u_ref[:-1]) / (tb[1:] - tb[:-1]) * window
    win_ref = offset + half * (w_ref[1:] - _wave_integral(fn, u_ref[1:] - du)) / du
    win = np.empty(N)
    wk.dither_window_means(tb, u, w, window, fn, offset, half, win)
    np.testing.assert_array_equal(win, win_ref)
    # and the means are what they mean: a square wave's step mean is the time-weighted mix of its two levels
    if fn == wk.DITHER_SQUARE:
        assert np.all(np.abs(means - offset) <= half * (1 + 1e-12))
