"""The twin's deterministic non-idealities, each against its own equation (docs/accuracy-budget.md).

Every expected number is computed here from the physics (parallel-plate electrostatics, the FTR steady state,
the AGC/PLL steady states, the demodulator filter's response at 2 omega, the table's ripple), independently of the
kernel's code path.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from scipy.optimize import brentq

from sims.carrier import CarrierGyroSim
from sims.gyro import GyroParams, GyroSim, LoopSettings, held_inputs
from sims.gyro_params import DEG_PER_RAD, NONIDEALITIES_OFF
from sims.world import World
from tests.support.paper_loops import paper_loops
from tests.support.twin_params import paper_gyro_params, paper_world_params

DT = 1.0 / 1400.0
EPS0 = 8.8541878128e-12
QUIET = paper_gyro_params().noiseless(**NONIDEALITIES_OFF)  # every random source and converter step off


def _loops(gain: float = 1.0) -> LoopSettings:
    return paper_loops(gain)


# ------------------------------------------------------------------------------------------ electrostatic forcer


@pytest.mark.parametrize("v_p, gap_um, c_e", [(5.0, 2.0, 1.0), (2.0, 1.0, 10.0), (0.5, 0.2, 100.0)])
def test_forcer_cubic_is_the_parallel_plate_gap_closing(v_p: float, gap_um: float, c_e: float) -> None:
    """Solve the full parallel-plate statics: k_m y = eps0 A (V_p^2 + v^2/2) / (2 (g - y)^2) for the quasi-static
    deflection y (v the electrode's AC amplitude), then the 1-omega force eps0 A V_p v / (g - y)^2. Its gain change
    from v = 0 to v must be beta u^2 (u = v / c_e) to first order in beta u^2. A and m are any pair consistent with
    the SF (the mass cancels from beta: two different masses give the same answer)."""
    p = paper_gyro_params(forcer_bias_v=v_p, forcer_gap_um=gap_um, forcer_electrode_v_per_v=c_e)
    g = gap_um * 1e-6
    a_m = p.drive_amplitude_um * 1e-6
    sf_rad = p.sf_true_v_per_dps * DEG_PER_RAD
    for mass_kg in (1e-7, 1e-5):
        k_m = mass_kg * p.omega0_rad_s**2
        eps_a = 2.0 * mass_kg * p.angular_gain * p.omega0_rad_s * a_m * g * g / (c_e * sf_rad * v_p)  # eps0 A

        def deflection(v: float, eps_a: float = eps_a, k_m: float = k_m) -> float:
            def balance(y: float, v: float = v, eps_a: float = eps_a, k_m: float = k_m) -> float:
                return k_m * y - eps_a * (v_p**2 + 0.5 * v * v) / (2.0 * (g - y) ** 2)

            return float(brentq(balance, 0.0, g / 3, xtol=1e-30, rtol=1e-15))

        y0 = deflection(0.0)
        for u in (0.01, 0.03):  # command volts; beta u^2 stays small
            v = c_e * u
            y_v = deflection(v)
            gain_change = ((g - y0) / (g - y_v)) ** 2 - 1.0
            assert gain_change == pytest.approx(p.forcer_cubic_per_v2 * u * u, rel=2e-3)
        assert eps_a * v_p**2 / g**3 / k_m == pytest.approx(p.electrostatic_spring_ratio, rel=1e-9)


def test_pull_in_is_refused_by_name() -> None:
    """The station, which turns [sim] into the twin's parameters, refuses a forcer near pull-in as bad input."""
    from qmg_lab.config.schema import ConfigError, parse_config
    from qmg_lab.station import gyro_params

    cfg = parse_config("[sim]\nforcer_bias_v = 200.0\nforcer_gap_um = 0.01\nforcer_electrode_v_per_v = 0.01\n")
    with pytest.raises(ConfigError, match="electrostatic spring"):
        gyro_params(cfg)
    assert paper_gyro_params().electrostatic_spring_ratio < 0.5  # the default configuration's twin is far from it


def _settled_rate_output(p: GyroParams, rate_dps: float, temperature_c: float = 25.0, seconds: float = 30.0) -> float:
    sim = GyroSim(p, DT, seed=1)
    b = sim.run(held_inputs(round(seconds / DT), DT, rate_dps=rate_dps, temperature_c=temperature_c), _loops())
    return float(np.mean(b.rate_output_v[-1400:]))


def test_ftr_output_solves_the_cubic_forcer_balance() -> None:
    """Steady FTR: K u (1 + beta u^2) = K u_lin, u_lin the linear forcer's output (the same Coriolis load)."""
    cubic = dataclasses.replace(QUIET, forcer_bias_v=0.5, forcer_gap_um=0.2, forcer_electrode_v_per_v=100.0)
    beta = cubic.forcer_cubic_per_v2
    for rate in (2.0, 5.0):
        u_lin = _settled_rate_output(QUIET, rate)
        expected = brentq(lambda u, u_lin=u_lin: u * (1.0 + beta * u * u) - u_lin, 0.0, 2.0 * u_lin)
        assert beta * u_lin**2 > 1e-3  # the effect tested is far above the settling residual
        assert _settled_rate_output(cubic, rate) == pytest.approx(expected, rel=2e-6)


# ------------------------------------------------------------------------------------------ feedthrough


def test_feedthrough_into_x_shifts_the_ftr_output_by_its_equation() -> None:
    """The loop nulls X_s = G_py (c_y - kappa' u)/sqrt2, so c_y = kappa' u and the balance
    K u / (2 omega) - g_y kappa' u = k Omega a gives u_ft / u_0 = 1 / (1 - 2 omega g_y kappa' / K)."""
    kappa = 1e-2
    ft = dataclasses.replace(QUIET, feedthrough_v_per_v=kappa, feedthrough_phase_deg=90.0)
    u0, u1 = _settled_rate_output(QUIET, 5.0), _settled_rate_output(ft, 5.0)
    w = QUIET.omega_x_rad_s(25.0)
    g_y = (
        QUIET.omega0_rad_s
        / (2 * QUIET.q_factor)
        * (1.0 - 0.5 * QUIET.damping_mismatch * math.cos(math.radians(2 * QUIET.damping_axis_deg)))
    )
    expected = 1.0 / (1.0 - 2.0 * w * g_y * kappa / QUIET.k_forcer)
    assert expected - 1.0 > 1e-4
    assert u1 / u0 == pytest.approx(expected, rel=1e-6)


# ------------------------------------------------------------------------------------------ temperature laws


def test_q_and_damping_mismatch_tempcos_set_the_agc_drive() -> None:
    """AGC steady state: V_d = 2 omega_r gamma_xx a / K_d, gamma_xx = (omega/2Q(T))(1 + (dmis(T)/2) cos 2 theta)."""
    p = dataclasses.replace(QUIET, q_tempco_ppm_per_c=-20000.0, damping_mismatch_tempco_per_c=0.003)
    t = 35.0
    sim = GyroSim(p, DT, seed=1)
    b = sim.run(held_inputs(round(20.0 / DT), DT, temperature_c=t), _loops())
    q = p.q_factor * (1.0 - 0.02 * 10.0)
    dmis = p.damping_mismatch + 0.003 * 10.0
    w = p.omega_rad_s(t)
    gamma_xx = w / (2 * q) * (1.0 + 0.5 * dmis * math.cos(math.radians(2 * p.damping_axis_deg)))
    wr = 2 * math.pi * float(b.frequency_hz[-1])
    expected = 2.0 * wr * gamma_xx * p.a0 / p.k_drive
    assert float(b.drive_output_v[-1]) == pytest.approx(expected, rel=1e-5)
    assert expected / (2.0 * p.omega0_rad_s * (p.omega0_rad_s / (2 * p.q_factor)) * p.a0 / p.k_drive) > 1.2


def test_split_tempco_moves_the_pll_to_the_drive_resonance() -> None:
    """PLL on the drive mode: f = sqrt(omega^2 + omega dw(T) cos 2 theta_w) / 2 pi, dw = 2 pi (df + alpha dT)."""
    p = dataclasses.replace(QUIET, freq_mismatch_hz=0.5, freq_mismatch_tempco_hz_per_c=0.3, stiffness_axis_deg=0.0)
    t = 33.0
    b = GyroSim(p, DT, seed=1).run(held_inputs(round(5.0 / DT), DT, temperature_c=t), _loops())
    w = p.omega_rad_s(t)
    dw = 2 * math.pi * (0.5 + 0.3 * 8.0)
    expected = math.sqrt(w * w + w * dw) / (2 * math.pi)  # axis 0: no drive-sense coupling to shift the phase
    assert float(b.frequency_hz[-1]) == pytest.approx(expected, abs=1e-6)
    assert expected - p.omega_rad_s(t) / (2 * math.pi) > 1.0


# ------------------------------------------------------------------------------------------ the HF2's 2-omega ripple


def test_carrier_stream_carries_the_filters_two_omega_residual() -> None:
    """X + iY picks up sqrt2 G (C + iS)/2 e^{-2i phi} H(-2j omega): on the drive, |ripple| = |H(2 omega)| R_d."""
    dt = 1.0 / (32 * QUIET.f0_hz)
    loops = _loops()
    tc, order = 1e-4, 2
    loops = dataclasses.replace(loops, demod_timeconstant_s=tc, demod_order=order)
    n = 2000
    blocks = []
    for ripple in (False, True):
        sim = CarrierGyroSim(dataclasses.replace(QUIET, hf2_demod_ripple=ripple), dt, seed=1)
        inp = held_inputs(n, sim.demod_interval_s)
        blocks.append(sim.run(inp, loops))
    d = (blocks[1].x_drive - blocks[0].x_drive) + 1j * (blocks[1].y_drive - blocks[0].y_drive)
    wr = 2 * math.pi * float(blocks[0].frequency_hz[-1])
    h = (1.0 + (2 * wr * tc) ** 2) ** (-order / 2)
    r_d = abs(blocks[0].x_drive[-1] + 1j * blocks[0].y_drive[-1])
    assert np.abs(d[-100:]) == pytest.approx(h * r_d, rel=1e-3)
    assert np.allclose(blocks[1].rate_output_v, blocks[0].rate_output_v, atol=1e-12)  # the loops never see it


# ------------------------------------------------------------------------------------------ the rate table


def test_table_ripple_follows_the_angle_and_averages_out_over_a_revolution() -> None:
    """Delivered rate = Omega (1 + e)(1 + r sin(theta + phi)); over one whole revolution its mean is Omega (1 + e)."""
    r_ppm, e_ppm, phi = 2000.0, 60.0, 30.0
    world = World(
        paper_world_params(table_rate_ripple_ppm=r_ppm, table_rate_scale_error_ppm=e_ppm, table_ripple_phase_deg=phi)
    )
    world.set_table_rate(10.0, 1e9)
    dt = 1e-3
    inp = world.advance(36000, dt)  # 360 deg at 10 deg/s
    base = 10.0 * (1 + e_ppm * 1e-6)
    mid_angle = base * dt * (np.arange(36000) + 0.5)  # the ripple-free profile's angle at mid-step
    expected = base * (1 + r_ppm * 1e-6 * np.sin(np.radians(mid_angle + phi)))
    assert inp.table_rate_dps == pytest.approx(expected, rel=1e-12)
    assert inp.table_angle_deg[-1] == pytest.approx(float(np.sum(expected[:-1])) * dt, rel=1e-12)
    assert float(np.mean(inp.table_rate_dps)) == pytest.approx(10.0 * (1 + e_ppm * 1e-6), rel=2e-6)
    assert world.table_rate_dps() == pytest.approx(
        10.0 * (1 + e_ppm * 1e-6) * (1 + r_ppm * 1e-6 * math.sin(math.radians(world.table_angle_deg() + phi))),
        rel=1e-9,
    )
