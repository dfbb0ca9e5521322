"""The shared world's dynamics against their closed forms (sims/world.py)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sims.world import DITHER_SINE, DITHER_SQUARE, World, WorldParams, first_order_lag

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
    w = World(WorldParams(table_rate_scale_error_ppm=100.0))
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
    w = World(WorldParams(table_rate_scale_error_ppm=0.0))
    w.set_table_rate(5.0, 300.0)
    w.advance(700, DT)
    w.set_table_rate(-5.0, 300.0)
    b = w.advance(700, DT)
    i = int(np.argmin(np.abs(b.table_rate_dps)))
    assert (i + 0.5) * DT == pytest.approx(5.0 / 300.0, abs=DT)
    assert b.table_rate_dps[-1] == pytest.approx(-5.0)


def test_chamber_setpoint_ramps_and_air_lags_first_order():
    tau_air = 60.0
    w = World(WorldParams(chamber_time_constant_s=tau_air, thermal_lag_s=600.0, initial_temperature_c=25.0))
    w.set_chamber(35.0, 1.0)  # 1 degC/min
    for _ in range(120):
        w.advance(1400, DT)
    t = 120.0
    # ramp input r(t) = 25 + t/60 through a first-order lag: y = 25 + (t - tau (1 - e^-t/tau)) / 60
    expected_air = 25 + (t - tau_air * (1 - math.exp(-t / tau_air))) / 60.0
    assert w.chamber.controller_setpoint_c == pytest.approx(27.0, abs=1e-9)
    assert w.chamber_air_c() == pytest.approx(expected_air, abs=2e-4)
    assert 25.0 < w.chamber.gyro_c < w.chamber_air_c()


def test_square_dither_has_exact_edges_levels_and_period():
    w = World()
    w.set_dither(function=DITHER_SQUARE, frequency_hz=7.0, amplitude_vpp=0.6, offset_v=0.0, phase_deg=0.0)
    b = w.advance(1400, DT)
    d = b.dither_v.reshape(7, 200)  # 200 steps per period at 1400 steps/s
    assert np.all(d[:, :100] == 0.3) and np.all(d[:, 100:] == -0.3)


def test_sine_dither_and_mute():
    w = World()
    w.set_dither(function=DITHER_SINE, frequency_hz=10.0, amplitude_vpp=2.0, offset_v=0.5)
    b = w.advance(700, DT)
    t_mid = b.t + DT / 2
    assert b.dither_v == pytest.approx(0.5 + np.sin(2 * np.pi * 10.0 * t_mid), abs=1e-12)
    w.set_dither(amplitude_vpp=0.0)
    assert np.all(w.advance(10, DT).dither_v == 0.5)


def test_interlock_brakes_the_table_to_rest():
    w = World()
    w.set_table_rate(50.0, 300.0)
    w.advance(1400, DT)
    w.trip_interlock()
    w.advance(1400, DT)
    assert w.table.interlock and w.table_rate_dps() == 0.0
