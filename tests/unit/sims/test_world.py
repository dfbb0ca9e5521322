"""The shared world's dynamics against their closed forms (sims/world.py)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sims.world import DITHER_SINE, DITHER_SQUARE, World, WorldParams, first_order_lag
from tests.support.twin_params import paper_world, paper_world_params

DT = 1 / 1400


def test_first_order_lag_is_the_exact_recursion_across_chunks():
    rng = np.random.default_rng(3)
    u = 30 + rng.standard_normal(20000)
    for a in (0.5, 0.99, math.exp(-DT / 60)):
        y = np.empty_like(u)
        y[0] = 25.0
        for k in range(u.size - 1):
            y[k + 1] = a * y[k] + (1 - a) * u[k]
        assert np.max(np.abs(first_order_lag(u, 25.0, a) - y)) < 1e-9


def test_table_ramps_at_the_acceleration_limit_then_holds_with_scale_error():
    w = World(paper_world_params(table_rate_scale_error_ppm=100.0, table_rate_ripple_ppm=0.0))
    w.set_table_rate(5.0, 300.0)
    b = w.advance(1400, DT)
    scale = 1 + 100e-6
    # mid-step rate during the ramp: a (k + 1/2) dt
    k = np.arange(20)
    assert b.table_rate_dps[:20] == pytest.approx(300.0 * (k + 0.5) * DT * scale, rel=1e-12)
    assert b.table_rate_dps[-1] == pytest.approx(5.0 * scale, rel=1e-12)
    # angle = integral of the delivered rate: ramp (r^2 / 2a) then constant rate
    t_end = 1400 * DT
    ramp_t = 5.0 / 300.0
    expected = scale * (5.0 * ramp_t / 2 + 5.0 * (t_end - ramp_t))
    # the midpoint rule is exact on each linear piece; the one step holding the ramp's end errs by <= a dt^2 / 8
    assert w.table_angle_deg() == pytest.approx(expected, abs=300.0 * DT**2 / 8)
    assert w.table_rate_dps() == pytest.approx(5.0 * scale)


def test_reversal_passes_through_zero_at_the_acceleration_limit():
    w = World(paper_world_params(table_rate_scale_error_ppm=0.0, table_rate_ripple_ppm=0.0))
    w.set_table_rate(5.0, 300.0)
    w.advance(700, DT)
    w.set_table_rate(-5.0, 300.0)
    b = w.advance(700, DT)
    i = int(np.argmin(np.abs(b.table_rate_dps)))
    assert (i + 0.5) * DT == pytest.approx(5.0 / 300.0, abs=DT)
    assert b.table_rate_dps[-1] == pytest.approx(-5.0)


def test_chamber_setpoint_ramps_and_air_lags_first_order():
    tau_air = 60.0
    w = World(paper_world_params(chamber_time_constant_s=tau_air, thermal_lag_s=600.0, initial_temperature_c=25.0))
    w.set_chamber(35.0, 1.0)  # 1 degC/min
    for _ in range(120):
        w.advance(1400, DT)
    t = 120.0
    # ramp input r(t) = 25 + t/60 through a first-order lag: y = 25 + (t - tau (1 - e^-t/tau)) / 60
    expected_air = 25 + (t - tau_air * (1 - math.exp(-t / tau_air))) / 60.0
    assert w.chamber.controller_setpoint_c == pytest.approx(27.0, abs=1e-9)
    assert w.chamber_air_c() == pytest.approx(expected_air, abs=2e-4)
    assert 25.0 < w.chamber.gyro_c < w.chamber_air_c()


def _ds345_phase_cycles(t: np.ndarray, f: float, p: WorldParams, t_cmd: float = 0.0) -> np.ndarray:
    """u(t) from the DS345 timebase equation, written out here: rate error e0 + e_w sin(2 pi t/P)."""
    e0, ew, per = (
        p.ds345_timebase_offset_ppm * 1e-6,
        p.ds345_timebase_wander_ppm * 1e-6,
        p.ds345_timebase_wander_period_s,
    )

    def tau(x: np.ndarray | float) -> np.ndarray:
        x = np.asarray(x, dtype=float)
        return x * (1 + e0) + ew * per / (2 * math.pi) * (1 - np.cos(2 * math.pi * x / per))

    return f * (tau(t) - tau(t_cmd + p.ds345_command_latency_s))


def test_square_dither_runs_on_the_ds345_timebase_with_exact_step_means():
    # a fast crystal (+50 ppm) and a large wander, so that edges drift through the step grid measurably
    p = paper_world_params(
        ds345_timebase_offset_ppm=50.0,
        ds345_timebase_wander_ppm=20.0,
        ds345_timebase_wander_period_s=30.0,
        ds345_command_latency_s=0.37e-3,
    )
    w = World(p)
    w.set_dither(function=DITHER_SQUARE, frequency_hz=7.0, amplitude_vpp=0.6, offset_v=0.0, phase_deg=0.0)
    b = w.advance(1400 * 20, DT)
    # expected: on a fine grid (1000 points per step) the fraction of each step spent high, from u(t) directly
    fine = b.t[:, None] + DT * (np.arange(1000) + 0.5)[None, :] / 1000
    u = _ds345_phase_cycles(fine, 7.0, p)
    high = ((u - np.floor(u)) < 0.5).mean(axis=1)
    np.testing.assert_allclose(b.dither_v, 0.3 * (2 * high - 1), atol=0.6 / 1000)
    levels = np.unique(np.round(b.dither_v, 12))
    assert 0.3 in levels and -0.3 in levels and levels.size > 20  # steps that hold an edge read in between
    # the period the HF2 sees is the DS345's 1/7 s divided by (1 + 50 ppm) on average
    edges = b.t[1:][(b.dither_v[1:] > 0) & (b.dither_v[:-1] <= 0)]
    period = (edges[-1] - edges[0]) / (edges.size - 1)
    assert period == pytest.approx(1 / 7.0 / (1 + 50e-6), abs=DT / edges.size * 2)


def _step_means_from_the_phase(w: World, n: int) -> np.ndarray:
    """The exact square-wave step means of the next n steps, from World._dither_phase (which reads the DS345
    timebase at the phase origin afresh) and the waveform's antiderivative, in numpy."""
    d = w.dither
    u = w._dither_phase(w.t + DT * np.arange(n + 1))
    frac = u - np.floor(u)
    big_w = np.where(frac < 0.5, frac, 1.0 - frac)
    return d.offset_v + 0.5 * d.amplitude_vpp * (big_w[1:] - big_w[:-1]) / (u[1:] - u[:-1])


def test_dither_origin_follows_new_frequencies_and_timebase_parameters():
    """Block after block the step means equal those formed from the phase afresh, through a new frequency (a new
    phase origin), a changed timebase offset, wander and wander period, and a return to earlier values."""
    w = World(paper_world_params(ds345_timebase_wander_ppm=20.0, ds345_timebase_wander_period_s=30.0))
    w.set_dither(function=DITHER_SQUARE, frequency_hz=7.0, amplitude_vpp=0.6)
    changes = [
        lambda: None,
        lambda: w.set_dither(frequency_hz=9.0),
        lambda: setattr(w.params, "ds345_timebase_offset_ppm", 40.0),
        lambda: setattr(w.params, "ds345_timebase_wander_ppm", 3.0),
        lambda: setattr(w.params, "ds345_timebase_wander_period_s", 55.0),
        lambda: w.set_dither(frequency_hz=7.0),
        lambda: setattr(w.params, "ds345_timebase_offset_ppm", 3.0),
    ]
    eps = np.finfo(float).eps
    for change in changes:
        change()
        expected = _step_means_from_the_phase(w, 700)
        got = w.advance(700, DT).dither_v
        # The World's kernel takes the wander's cosine from the C library, the reference from numpy (SIMD code,
        # within 4 ulp): the two cosines differ by at most 5 eps / 2, so each phase u by at most
        # delta = f (e_w P / 2 pi) 5 eps / 2 plus a rounding of tau (eps t) and of u (eps |u|). A step mean
        # A (W(u1) - W(u0)) / (u1 - u0) with |W'| <= 1 and |W(u1) - W(u0)| <= u1 - u0 then moves by at most
        # 4 A delta / (u1 - u0), A = Vpp / 2 (plus its own few roundings, 8 eps A / (u1 - u0)).
        p, d = w.params, w.dither
        u = w._dither_phase(w.t - DT * np.arange(701)[::-1])
        wander_s = p.ds345_timebase_wander_ppm * 1e-6 * p.ds345_timebase_wander_period_s / (2 * math.pi)
        delta = d.frequency_hz * (wander_s * 2.5 * eps + eps * w.t) + eps * np.max(np.abs(u))
        amp = 0.5 * d.amplitude_vpp
        assert np.all(np.abs(got - expected) <= (4 * amp * delta + 8 * eps * amp) / np.diff(u))


def test_sine_dither_step_means_and_mute():
    p = paper_world_params()
    w = World(p)
    w.set_dither(function=DITHER_SINE, frequency_hz=10.0, amplitude_vpp=2.0, offset_v=0.5)
    b = w.advance(700, DT)
    u0 = _ds345_phase_cycles(b.t, 10.0, p)
    u1 = _ds345_phase_cycles(b.t + DT, 10.0, p)
    expected = 0.5 + (np.cos(2 * np.pi * u0) - np.cos(2 * np.pi * u1)) / (2 * np.pi * (u1 - u0))
    assert b.dither_v == pytest.approx(expected, abs=1e-9)
    w.set_dither(amplitude_vpp=0.0)
    assert np.all(w.advance(10, DT).dither_v == 0.5)


def test_auxin_windows_read_point_values_and_exact_fractions():
    p = paper_world_params(ds345_timebase_offset_ppm=20.0, ds345_timebase_wander_ppm=0.0, ds345_command_latency_s=0.0)
    w = World(p)
    w.set_dither(function=DITHER_SQUARE, frequency_hz=7.3, amplitude_vpp=0.6)
    b = w.advance(1400 * 2, DT)
    t_end = b.t + DT
    # a zero window reads the waveform at the step's end, from u(t) written out here
    u = _ds345_phase_cycles(t_end, 7.3, p)
    np.testing.assert_array_equal(w.window_means_at_step_ends(0.0), np.where(u - np.floor(u) < 0.5, 0.3, -0.3))
    # a window of 0.6 step reads the fraction of it spent high (fine grid of 2000 points per window)
    win = 0.6 * DT
    fine = t_end[:, None] - win * (np.arange(2000) + 0.5)[None, :] / 2000
    uf = _ds345_phase_cycles(fine, 7.3, p)
    expected = 0.3 * (2 * ((uf - np.floor(uf)) < 0.5).mean(axis=1) - 1)
    means = w.window_means_at_step_ends(win)
    np.testing.assert_allclose(means, expected, atol=0.6 / 2000)
    # 29 edges in 2 s, each inside a window with probability 0.6 (~17 expected): those read in between
    assert np.sum(np.abs(means) < 0.29) >= 10


def test_interlock_brakes_the_table_to_rest():
    w = paper_world()
    w.set_table_rate(50.0, 300.0)
    w.advance(1400, DT)
    w.trip_interlock()
    w.advance(1400, DT)
    assert w.table.interlock and w.table_rate_dps() == 0.0


def test_restore_puts_back_time_chamber_and_gyro_but_not_the_time_of_a_wall_clock() -> None:
    w = paper_world()
    w.restore(time_s=1234.5, chamber_setpoint_c=31.0, chamber_air_c=30.2, gyro_c=29.9)
    assert w.t == 1234.5
    assert w.chamber.controller_setpoint_c == w.chamber.target_c == 31.0
    assert (w.chamber.air_c, w.chamber.gyro_c) == (30.2, 29.9)
    w.restore(gyro_c=28.0)  # None leaves a quantity as it is
    assert (w.t, w.chamber.air_c, w.chamber.gyro_c) == (1234.5, 30.2, 28.0)
    w.restore(table_angle_deg=137.5)  # the table stands where the file last saw it (its ripple depends on it)
    assert w.table_angle_deg() == 137.5 and w.t == 1234.5
    wall = paper_world(clock="wall")
    t0 = wall.t
    wall.restore(time_s=1e6)
    assert wall.t == t0
