"""FTR rate loop designed by qmg_lab.campaign.loops.

* The zero-on-pole design (Kp = 2 pi 2 Hz / b, Ki = Kp / tau): the closed loop is first order, T(s) = w_c / (s + w_c),
  w_c = 2 pi 2 Hz (physics.md section 3): -3 dB and -45 deg at 2.0 Hz, 2 % settling after ln(50) / w_c = 0.311 s.
* The critically damped design (the default): its step response, and the slow tail a table step leaves in the
  analysis window under a mode split and a Q drift against the budget's model, for both designs.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from qmg_lab.budget.sweep import loop_tail_errors
from qmg_lab.campaign.loops import lockin_setup, rate_pi
from qmg_lab.config.rate_loop import config_quadrature_loop, config_rate_loop
from qmg_lab.config.schema import Config, DeviceSection, LoopsSection, PlanSection
from sims.gyro import GyroSim, LoopSettings, PidSettings, PllSettings, held_inputs
from sims.gyro_params import NONIDEALITIES_OFF, GyroParams
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


# ------------------------------------------------------------------------------------------------ the default design


def _design_loops(cfg: Config) -> LoopSettings:
    su = lockin_setup(cfg)
    return LoopSettings(
        pll=PllSettings.from_gains(su.pll),
        agc=PidSettings.from_gains(su.agc),
        rate=PidSettings.from_gains(su.rate),
        quadrature=PidSettings.from_gains(su.quadrature),
    )


def _rate_step(params: GyroParams, cfg: Config, seconds: float) -> tuple[np.ndarray, np.ndarray]:
    """Time (s) and rate output over the twin's own true SF times 5 deg/s after a step 0 -> 5 deg/s at t = 0."""
    sim = GyroSim(params, DT, seed=1)
    loops = _design_loops(cfg)
    sim.run(held_inputs(2800, DT), loops)
    v0 = sim.state["rate_output_v"]
    n = int(round(seconds / DT))
    b = sim.run(held_inputs(n, DT, rate_dps=5.0), loops)
    return DT * np.arange(1, n + 1), (b.rate_output_v - v0) / (5.0 * b.sf_true_v_per_dps)


def test_critically_damped_step_response_follows_its_double_pole() -> None:
    """config.rate_loop.rate_loop_design: T(s) = (2p - g)(s + z)/(s + p)^2, z = p^2/(2p - g), so the step response is
    y(t) = 1 - e^{-pt} (1 - (p - g) t), p = 2 pi 2 Hz / sqrt(3 + sqrt 10) = 5.062 rad/s: 13.5 % overshoot at 2/p."""
    cfg = Config()
    assert cfg.loops.sense_pi_design == "critically_damped"
    p = 2 * math.pi * BW_HZ / math.sqrt(3 + math.sqrt(10))
    g = 1.0 / cfg.device.tau_s
    t, y = _rate_step(QUIET, cfg, 3.0)

    def step(tt: float) -> float:
        return 1 - math.exp(-p * tt) * (1 - (p - g) * tt)

    # the HF2's PID acts on sampled X once per sample: the twin's response may run up to 4 samples (2.9 ms) early
    # or late against the continuous equation where y moves fast
    for tt in (0.1, 0.2, 0.4, 2 / p, 0.8, 1.2, 2.0):
        lo, hi = sorted((step(tt - 4 * DT), step(tt + 4 * DT)))
        assert lo - 1e-3 <= float(np.interp(tt, t, y)) <= hi + 1e-3, tt
    assert float(np.max(y)) == pytest.approx(1 + math.exp(-2) * (1 - 2 * g / p), abs=1e-3)


@pytest.mark.parametrize("design", ["critically_damped", "zero_on_pole"])
def test_window_mean_after_a_step_is_the_budgets_loop_tail(design: str) -> None:
    """A 0.05 Hz split and Q 8 % below the design's: the window [5 s, 15 s] after a 5 deg/s step keeps the tail
    qmg_lab.budget.sweep.loop_tail_errors predicts from the linear sense-axis model (g = omega/2Q, d = 2 pi df
    cos 2 theta_w). Zero on the pole: the slow mode near -1/tau, -0.0018 deg/s (-370 ppm); critically damped
    (both sense PIs): no slow mode, nothing left (the model: 2e-11 of the rate)."""
    cfg = Config(loops=LoopsSection(sense_pi_design=design), plan=PlanSection(dwell_s=15.0, settle_s=5.0))
    params = paper_gyro_params().noiseless(**{**NONIDEALITIES_OFF, "freq_mismatch_hz": 0.05, "q_factor": 1.1e6})
    t, y = _rate_step(params, cfg, 15.0)
    window = (t >= 5.0) & (t <= 15.0)
    measured_dps = 5.0 * (float(np.mean(y[window])) - 1.0)
    g = 2 * math.pi * params.f0_hz / (2 * params.q_factor)
    d = 2 * math.pi * params.freq_mismatch_hz * math.cos(2 * math.radians(params.stiffness_axis_deg))
    predicted_dps = float(
        loop_tail_errors(
            cfg,
            [5.0],
            split_rad_s=np.array([d]),
            gamma_y=np.array([g]),
            wc_rad_s=np.array([config_rate_loop(cfg).gain_rad_s]),
            wq_rad_s=np.array([config_quadrature_loop(cfg).gain_rad_s]),
        )[0]
    )
    assert measured_dps == pytest.approx(predicted_dps, rel=0.1, abs=5e-7)
    if design == "critically_damped":
        assert abs(measured_dps) < 1e-7 * 5.0
    else:
        assert abs(measured_dps) > 300e-6 * 5.0
