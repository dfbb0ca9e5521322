"""FTR rate loop designed by qmg_lab.campaign.loops (Kp = 2 pi 2 Hz / b, Ki = Kp / tau): the closed loop is first order,
T(s) = w_c / (s + w_c), w_c = 2 pi 2 Hz (physics.md section 3): -3 dB and -45 deg at 2.0 Hz, 2 % settling
after ln(50) / w_c = 0.311 s."""

from __future__ import annotations

import math

import numpy as np
import pytest

from qmg_lab.campaign.loops import lockin_setup, rate_pi
from qmg_lab.config.schema import Config, DeviceSection
from sims.gyro import GyroSim, LoopSettings, PidSettings, PllSettings, held_inputs
from sims.gyro_params import NONIDEALITIES_OFF
from sims.world import World
from tests.support.twin_params import paper_gyro_params, paper_world_params

QUIET = paper_gyro_params().noiseless(**NONIDEALITIES_OFF)
DT = 1.0 / 1400.0
BW_HZ = 2.0


def _loops() -> LoopSettings:
    su = lockin_setup(Config())
    rate = rate_pi(DeviceSection(), BW_HZ)
    return LoopSettings(
        pll=PllSettings.from_gains(su.pll),
        agc=PidSettings.from_gains(su.agc),
        rate=PidSettings.from_gains(rate),
        quadrature=PidSettings.from_gains(su.quadrature),
    )


def _response(freq_hz: float, amp_dps: float = 5.0) -> complex:
    """Complex gain V_r / (SF * Omega) at freq_hz, table driven sinusoidally through a World."""
    world = World(paper_world_params(table_rate_scale_error_ppm=0.0))
    sim = GyroSim(QUIET, DT, seed=1)
    loops = _loops()
    world.set_table_sine(amp_dps, freq_hz)
    settle = int(round(2.0 / DT))
    sim.run(world.advance(settle, DT), loops)
    cycles = max(4, int(4 * freq_hz))
    n = int(round(cycles / freq_hz / DT))
    inp = world.advance(n, DT)
    b = sim.run(inp, loops)
    t_end = inp.t + DT  # outputs are at the end of each step
    w = 2 * math.pi * freq_hz
    basis = np.column_stack(
        [np.sin(w * (t_end - world.table.sine_start_s)), np.cos(w * (t_end - world.table.sine_start_s))]
    )
    coef = np.linalg.lstsq(basis, b.rate_output_v / QUIET.sf_true_v_per_dps, rcond=None)[0]
    return complex(coef[0], coef[1]) / amp_dps  # in-phase + i quadrature relative to the input sine


def test_bandwidth_is_2hz() -> None:
    freqs = [1.5, 2.0, 2.5]
    mags = [abs(_response(f)) for f in freqs]
    assert mags[0] > mags[1] > mags[2]
    # -3 dB crossing by log-linear interpolation between the bracketing points
    target = 1 / math.sqrt(2)
    i = 0 if mags[1] < target else 1
    f_3db = math.exp(np.interp(target, [mags[i + 1], mags[i]], [math.log(freqs[i + 1]), math.log(freqs[i])]))
    assert f_3db == pytest.approx(BW_HZ, rel=0.05)
    g2 = _response(2.0)
    assert abs(g2) == pytest.approx(1 / math.sqrt(2), rel=0.02)
    # phase of w_c/(jw + w_c) at w = w_c: -45 deg (sin reference: atan2 of the cos coefficient)
    assert math.degrees(math.atan2(g2.imag, g2.real)) == pytest.approx(-45.0, abs=3.0)


def test_step_settles_to_2_percent_within_half_a_second() -> None:
    sim = GyroSim(QUIET, DT, seed=1)
    loops = _loops()
    sim.run(held_inputs(1400, DT), loops)
    v0 = sim.state["rate_output_v"]
    n = int(round(3.0 / DT))
    b = sim.run(held_inputs(n, DT, rate_dps=5.0), loops)
    step = 5.0 * QUIET.sf_true_v_per_dps
    final = v0 + step
    t = DT * np.arange(1, n + 1)
    outside = np.nonzero(np.abs(b.rate_output_v - final) > 0.02 * step)[0]
    t_settle = t[outside[-1]] if outside.size else 0.0
    expected = math.log(50.0) / (2 * math.pi * BW_HZ)
    assert t_settle <= 0.5
    assert t_settle == pytest.approx(expected, rel=0.05)
