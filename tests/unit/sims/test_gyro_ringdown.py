"""Ring-down of the free sense mode: amplitude decay time tau = 2Q/omega (physics.md section 1: 173.6 s)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sims.carrier import CarrierGyroSim
from sims.gyro import GyroSim, LoopSettings, PllSettings, held_inputs
from sims.gyro_params import NOISE_OFF, NONIDEALITIES_OFF
from tests.support.twin_params import paper_gyro_params

QUIET = {**NOISE_OFF, **NONIDEALITIES_OFF}
OPEN = LoopSettings(pll=PllSettings(enabled=False, center_hz=2200.0))  # every loop open, reference at f0


def _decay_time_s(t: np.ndarray, x: np.ndarray, y: np.ndarray) -> float:
    """Fit log|X + iY| = c - t/tau by least squares."""
    slope = np.polyfit(t, np.log(np.hypot(x, y)), 1)[0]
    return -1.0 / slope


def test_tau_formula_is_the_papers_value() -> None:
    assert paper_gyro_params().tau_s == pytest.approx(173.6, abs=0.05)


@pytest.mark.parametrize("mismatch, tol", [(0.0, 1e-5), (0.01, 0.01)])
def test_averaged_sense_ringdown(mismatch: float, tol: float) -> None:
    p = paper_gyro_params(damping_mismatch=mismatch, **QUIET)
    dt = 1.0 / 1400.0
    sim = GyroSim(p, dt, seed=1)
    sim.reset(settled=False)
    sim.set_modal_state(0.0, 0.0, 1.0, 0.0)
    n = int(300.0 / dt)
    b = sim.run(held_inputs(n, dt), OPEN)
    t = dt * np.arange(1, n + 1)
    tau = _decay_time_s(t, b.x_sense, b.y_sense)
    assert tau == pytest.approx(2 * p.q_factor / (2 * math.pi * p.f0_hz), rel=tol)


def test_carrier_sense_ringdown_is_exact_not_rk4() -> None:
    """At 32 samples per cycle the exact ZOH keeps tau (RK4 would ring down in 29.7 s, physics.md section 2)."""
    p = paper_gyro_params(damping_mismatch=0.0, **QUIET)
    sim = CarrierGyroSim(p, 1.0 / (32 * p.f0_hz), seed=1)
    sim.reset(settled=False)
    sim.set_modal_state(0.0, 0.0, 1.0, 0.0)
    dtd = sim.demod_interval_s
    n = int(20.0 / dtd)
    b = sim.run(held_inputs(n, dtd), OPEN)
    t = dtd * np.arange(1, n + 1)
    tau = _decay_time_s(t[100:], b.x_sense[100:], b.y_sense[100:])
    assert tau == pytest.approx(p.tau_s, rel=1e-3)
