"""Dither (virtual rate) with the rate loop open: paper eq. 8, c_y = a0 * integral(Omega_v dt).

The forcer term of eq. 6 is the virtual rate times x'. In the averaged equations (physics.md section 2,
Coriolis term 2 k Omega q') the dither voltage V enters as dc_y/dt = K_f G_f g V / (2 omega) = a0 Omega_v with
Omega_v = k V G_f g (omega0/omega) / SF (SF in V per rad/s): a square wave of +-V gives a triangle whose swing
over each half period T/2 is a0 Omega_v T/2 (the 1/tau decay changes it by T/(4 tau) = 2e-4 at most).
The response the CLSF demodulates, X_s = G_py c_y / sqrt(2), is then proportional to G_py G_f g / omega.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from qmg_lab.campaign.loops import lockin_setup
from qmg_lab.config.schema import Config
from sims.gyro import GyroSim, LoopSettings, PidSettings, PllSettings, held_inputs
from sims.gyro_params import NONIDEALITIES_OFF
from tests.support.twin_params import paper_gyro_params

QUIET = paper_gyro_params().noiseless(**NONIDEALITIES_OFF)
DT = 1.0 / 1400.0
F_DITHER = 7.0  # 200 steps per period: edges on step boundaries
V_DITHER = 0.3


def _open_loops(forcer_gain: float = 1.0) -> LoopSettings:
    su = lockin_setup(Config())
    return LoopSettings(
        pll=PllSettings.from_gains(su.pll),
        agc=PidSettings.from_gains(su.agc),
        rate=PidSettings.from_gains(su.rate, enabled=False),
        quadrature=PidSettings.from_gains(su.quadrature, enabled=False),
        forcer_gain=forcer_gain,
        demod_timeconstant_s=1e-7,
    )  # no demod lag on the triangle


def _square(n: int) -> np.ndarray:
    k = np.arange(n)
    return np.where((k % 200) < 100, V_DITHER, -V_DITHER)


def _half_period_swings(temperature_c: float, forcer_gain: float) -> np.ndarray:
    sim = GyroSim(QUIET, DT, seed=1)
    loops = _open_loops(forcer_gain)
    n = 200 * 10
    b = sim.run(held_inputs(n, DT, dither_v=_square(n), temperature_c=temperature_c), loops)
    x = b.x_sense
    # values at the end of steps 99, 199, 299, ...: the triangle's corners
    corners = x[99::100]
    return np.diff(corners)


def test_triangle_swing_matches_eq8() -> None:
    p = QUIET
    swings = _half_period_swings(25.0, 1.0)
    sf_rad = p.sf_true_v_per_dps * 180.0 / math.pi
    omega_v = p.angular_gain * V_DITHER / sf_rad
    expected_cy = p.a0 * omega_v * (0.5 / F_DITHER)  # swing of c_y over half a period
    expected_x = expected_cy / math.sqrt(2.0)  # X_s = G_py c_y / sqrt 2, G_py = 1 at T_ref
    assert np.all(np.abs(np.abs(swings) / expected_x - 1.0) < 1e-3)
    assert swings[0] < 0 < swings[1]  # swings[0] spans the second (-V) half period: -V lowers c_y


def test_dither_response_scales_as_gpy_gf_g_over_omega() -> None:
    p = QUIET
    t_hot, g = 35.0, 1.01
    base = np.mean(np.abs(_half_period_swings(25.0, 1.0)))
    hot = np.mean(np.abs(_half_period_swings(t_hot, g)))
    d = t_hot - p.reference_temperature_c
    expected = (
        p.sense_pickoff_gain(t_hot)  # the front-end board in equilibrium at the held temperature
        * (1 + p.forcer_tempco_ppm_per_c * 1e-6 * d)
        * g
        / (1 + p.frequency_tempco_ppm_per_c * 1e-6 * d)
    )
    assert hot / base == pytest.approx(expected, rel=2e-5)
