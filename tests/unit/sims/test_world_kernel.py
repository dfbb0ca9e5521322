"""The compiled World loops (sims/world_kernel.py) against the equations of sims/world.py's docstring written as numpy
array expressions.

What is compared exactly and what to a bound: the elementwise IEEE operations (+ - * /) are correctly rounded, so
the same operations on the same operands give the same number in any implementation, and a cumulative sum
(np.cumsum, an accumulate: out_k = out_(k-1) + x_k by definition) has one order; those comparisons are exact.
Library functions are not: numpy's float64 sin and cos (SIMD code, documented within 4 ulp) and the C library's
(within 1 ulp) may differ by 5 ulp of a value <= 1, i.e. by at most TRIG_BOUND = 5 eps / 2 (ulp <= eps/2 below 1);
scipy's lfilter is its own code and is held to the recursion's rounding bound (test_first_order_lag...)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.signal import lfilter

from sims import world_kernel as wk

EPS = 2.0**-52
TRIG_BOUND = 5 * EPS / 2  # |numpy sin/cos - C library sin/cos| (module docstring)
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
        # lfilter is scipy's code: each step rounds a product, a product and a sum (<= 3 eps/2 |y| together), and a
        # difference decays by a per step, so the two recursions differ by at most 3 eps/2 max|y| min(N, 1/(1-a))
        bound = 1.5 * EPS * np.max(np.abs(ref)) * min(N, 1.0 / (1.0 - a))
        assert np.max(np.abs(y - ref)) <= bound
        assert y[0] == 25.3


@pytest.mark.parametrize(
    ("tau_air_s", "tau_gyro_s", "disturbance_c"), [(60.0, 600.0, 0.0), (60.0, 600.0, -1.5), (1e-4, 1e-3, 2.0)]
)
def test_chamber_lags_are_the_two_lags_and_the_measured_air_of_the_separate_loops(
    tau_air_s: float, tau_gyro_s: float, disturbance_c: float
) -> None:
    rng = np.random.default_rng(6)
    setpoint = 25.0 + np.minimum(np.arange(N) * DT * 0.25 / 60.0, 10.0) + rng.normal(0.0, 1e-3, N)
    a_air, a_gyro = math.exp(-DT / tau_air_s), math.exp(-DT / tau_gyro_s)
    air_ref, gyro_ref = np.empty(N), np.empty(N)
    wk.first_order_lag(setpoint, 25.4, a_air, air_ref)
    measured_ref = air_ref + disturbance_c
    wk.first_order_lag(measured_ref, 24.9, a_gyro, gyro_ref)
    air, measured, gyro = np.empty(N), np.empty(N), np.empty(N)
    wk.chamber_lags(setpoint, 25.4, a_air, disturbance_c, 24.9, a_gyro, air, measured, gyro)
    np.testing.assert_array_equal(air, air_ref)
    np.testing.assert_array_equal(measured, measured_ref)
    np.testing.assert_array_equal(gyro, gyro_ref)


@pytest.mark.parametrize("ripple_ppm", [0.0, 100.0, -2500.0])
@pytest.mark.parametrize("profile", ["hold", "ramp", "sine"])
def test_table_block_is_the_vectorised_ripple_and_angle(profile: str, ripple_ppm: float) -> None:
    k = np.arange(N) * DT + 0.5 * DT
    prof = {"hold": np.full(N, 5.0), "ramp": 5.0 - np.minimum(300.0 * k, 10.0), "sine": 3.0 * np.sin(2.1 * k)}[profile]
    angle0, scale, phase = 359.9, 1.0 + 60e-6, 17.0
    rate = prof * scale
    r, a = np.empty(N), np.empty(N)
    wk.table_block(prof, scale, DT, angle0, ripple_ppm * 1e-6, phase, r, a)
    if ripple_ppm != 0.0:
        mid = angle0 + np.cumsum(rate) * DT - 0.5 * rate * DT
        ripple = ripple_ppm * 1e-6
        bound = np.abs(rate) * (abs(ripple) * TRIG_BOUND + 2 * EPS)  # module docstring: the sine's bound,
        rate = rate * (1.0 + ripple * np.sin(np.deg2rad(mid + phase)))  # then one rounding of 1 + r sin
        assert np.all(np.abs(r - rate) <= bound)
    else:
        np.testing.assert_array_equal(r, rate)
    angle = angle0 + np.concatenate(([0.0], np.cumsum(r[:-1]) * DT))  # the angle of the delivered rates, exactly
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
    u, w, means = np.empty(N + 1), np.empty(N + 1), np.empty(N)
    wk.dither_grid(tb, e0, amp_s, per, float(tau_origin), f_hz, phase, fn, offset, half, u, w, means)
    # the wander's cosine within TRIG_BOUND of numpy's (module docstring): tau within amp_s TRIG_BOUND plus a
    # rounding of the wander term and of the sum, u within f times that plus a rounding of the product and the sum
    tau_bound = amp_s * TRIG_BOUND + np.spacing(amp_s) + np.spacing(tau)
    assert np.all(np.abs(u - u_ref) <= f_hz * tau_bound + 2 * np.spacing(np.abs(u_ref)))
    w_ref = _wave_integral(fn, u)  # from here on the equations of the kernel's phases, exactly
    np.testing.assert_array_equal(w, w_ref)
    np.testing.assert_array_equal(means, offset + half * (w_ref[1:] - w_ref[:-1]) / (u[1:] - u[:-1]))
    u_ref = u
    window = 0.3 * DT
    du = (u_ref[1:] - u_ref[:-1]) / (tb[1:] - tb[:-1]) * window
    win_ref = offset + half * (w_ref[1:] - _wave_integral(fn, u_ref[1:] - du)) / du
    win = np.empty(N)
    wk.dither_window_means(tb, u, w, window, fn, offset, half, win)
    np.testing.assert_array_equal(win, win_ref)
    # and the means are what they mean: a square wave's step mean is the time-weighted mix of its two levels
    if fn == wk.DITHER_SQUARE:
        assert np.all(np.abs(means - offset) <= half * (1 + 1e-12))


@pytest.mark.parametrize(("r0", "r1"), [(5.0, 5.0), (5.0, -5.0), (0.0, 5.0)])
@pytest.mark.parametrize(("s0", "s1"), [(25.0, 25.0), (25.0, 35.0), (35.0, 34.99)])
def test_ramp_block_is_the_vectorised_profile_and_setpoint(r0: float, r1: float, s0: float, s1: float) -> None:
    t0, accel, slope = 1234.5678, 300.0, 0.25 / 60.0
    k = np.arange(N + 1, dtype=np.float64) * DT  # the block's offsets from its start, as World.advance had them
    mid = k[:N] + 0.5 * DT
    prof_ref = np.full(N, r0) if r0 == r1 else r0 + math.copysign(1.0, r1 - r0) * np.minimum(accel * mid, abs(r1 - r0))
    sp_ref = np.full(N, s0) if s0 == s1 else s0 + math.copysign(1.0, s1 - s0) * np.minimum(slope * k[:N], abs(s1 - s0))
    t, tb, prof, sp = np.empty(N), np.empty(N + 1), np.empty(N), np.empty(N)
    wk.ramp_block(
        t0, DT, True, r0, math.copysign(1.0, r1 - r0), accel, abs(r1 - r0),
        s0, math.copysign(1.0, s1 - s0), slope, abs(s1 - s0), t, tb, prof, sp,
    )  # fmt: skip
    np.testing.assert_array_equal(tb, t0 + k)
    np.testing.assert_array_equal(t, t0 + k[:N])
    np.testing.assert_array_equal(prof, prof_ref)
    np.testing.assert_array_equal(sp, sp_ref)
    if r0 != r1:  # the reversal takes |r1 - r0| / a = 33 ms, well inside the block, and then holds r1
        assert prof[-1] == r1
    # not in rate mode: the profile (the sine's, computed by the World) is left as given
    given = np.linspace(-3.0, 3.0, N)
    kept = given.copy()
    wk.ramp_block(t0, DT, False, r0, 1.0, accel, abs(r1 - r0), s0, 1.0, slope, abs(s1 - s0), t, tb, kept, sp)
    np.testing.assert_array_equal(kept, given)


@pytest.mark.parametrize("dither_on", [True, False])
def test_block_inputs_is_the_loops_one_after_another(dither_on: bool) -> None:
    t0, r0, r1, accel, s0, s1, slope = 600.25, -5.0, 5.0, 300.0, 26.0, 35.0, 0.25 / 60.0
    a_air, a_gyro, air0, gyro0, disturbance = math.exp(-DT / 60.0), math.exp(-DT / 600.0), 25.9, 25.1, 0.4
    scale, angle0, ripple, ripple_phase = 1.0 + 60e-6, 123.4, 100e-6, 17.0
    e0, amp_s, per, tau_origin, f_hz, phase, offset, half = 3e-6, 2.9e-4, 3600.0, 7.5, 7.0, 0.0, 0.0, 0.3
    # reference: each loop on its own, the measured air in numpy
    t, tb, prof, sp = np.empty(N), np.empty(N + 1), np.empty(N), np.empty(N)
    sign_r, sign_s = math.copysign(1.0, r1 - r0), math.copysign(1.0, s1 - s0)
    wk.ramp_block(t0, DT, True, r0, sign_r, accel, abs(r1 - r0), s0, sign_s, slope, abs(s1 - s0), t, tb, prof, sp)
    rate, angle, air, gyro = np.empty(N), np.empty(N), np.empty(N), np.empty(N)
    wk.table_block(prof, scale, DT, angle0, ripple, ripple_phase, rate, angle)
    wk.first_order_lag(sp, air0, a_air, air)
    air_meas = air + disturbance
    wk.first_order_lag(air_meas, gyro0, a_gyro, gyro)
    u, w, means = np.empty(N + 1), np.empty(N + 1), np.empty(N)
    wk.dither_grid(tb, e0, amp_s, per, tau_origin, f_hz, phase, wk.DITHER_SQUARE, offset, half, u, w, means)
    # the fused call
    out = {name: np.empty(N) for name in ("t", "prof", "rate", "angle", "sp", "air", "air_meas", "gyro", "means")}
    out_tb, out_u, out_w = np.empty(N + 1), np.empty(N + 1), np.empty(N + 1)
    out["means"][:] = offset
    wk.block_inputs(
        np.array([t0, DT, r0, sign_r, accel, abs(r1 - r0), scale, angle0, ripple, ripple_phase]),
        np.array([s0, sign_s, slope, abs(s1 - s0), a_air, air0, disturbance, a_gyro, gyro0]),
        np.array([e0, amp_s, per, tau_origin, f_hz, phase, offset, half]),
        True, dither_on, wk.DITHER_SQUARE,
        out["t"], out_tb, out["prof"], out["rate"], out["angle"], out["sp"], out["air"], out["air_meas"],
        out["gyro"], out_u, out_w, out["means"],
    )  # fmt: skip
    for name, ref in (("t", t), ("prof", prof), ("rate", rate), ("angle", angle), ("sp", sp), ("air", air)):
        np.testing.assert_array_equal(out[name], ref, err_msg=name)
    np.testing.assert_array_equal(out["air_meas"], air_meas)
    np.testing.assert_array_equal(out["gyro"], gyro)
    np.testing.assert_array_equal(out_tb, tb)
    if dither_on:
        np.testing.assert_array_equal(out["means"], means)
        np.testing.assert_array_equal(out_u, u)
    else:  # a muted generator: its constant output is left as the caller filled it
        np.testing.assert_array_equal(out["means"], offset)
