"""GyroSim contract: construction checks, reproducibility, settled start, temperature model of the true SF."""

from __future__ import annotations

import math

import numpy as np
import pytest

from qmg_lab.config.schema import ConfigError, SimSection, parse_config
from sims.carrier import CarrierGyroSim
from sims.gyro import GyroParams, GyroSim, LoopSettings, held_inputs
from sims.gyro_params import NONIDEALITIES_OFF
from sims.world import BlockInputs
from tests.support.paper_loops import paper_loops
from tests.support.twin_params import paper_gyro_params, paper_world

DT = 1.0 / 1400.0
QUIET = paper_gyro_params().noiseless(**NONIDEALITIES_OFF)


def _loops(gain: float = 1.0) -> LoopSettings:
    return paper_loops(gain)


def test_from_mapping_takes_the_config_sections_gyro_keys_and_refuses_unknown_and_missing_keys() -> None:
    section = SimSection(q_factor=1e6).model_dump(include=set(GyroParams.field_names()))
    section["drive_amplitude_vrms"] = 0.5  # [device]'s, not [sim]'s
    p = GyroParams.from_mapping(section)
    assert p.q_factor == 1e6
    with pytest.raises(ValueError, match=r"unknown parameters \['q_facter'\]"):
        GyroParams.from_mapping({**section, "q_facter": 1e6})
    with pytest.raises(ValueError, match=r"missing parameters \['f0_hz'\]"):
        GyroParams.from_mapping({k: v for k, v in section.items() if k != "f0_hz"})
    assert p.arw_rad_per_rt_s == pytest.approx(0.02 / 60.0 * math.pi / 180.0)


@pytest.mark.parametrize(
    "toml, word",
    [
        ("q_factor = -1.0", "q_factor"),
        ("damping_mismatch = 1.5", "damping_mismatch"),
        ("arw_deg_per_rt_h = nan", "arw"),
        ("forcer_noise_v_per_rt_hz = -1e-6", "forcer_noise"),
        ("auxin_bits = 40", "auxin_bits"),
        ("auxout_range_v = 0.0", "auxout_range_v"),
        ("f0_hz = 100.0\nfreq_mismatch_hz = 10.0", "freq_mismatch_hz"),
    ],
)
def test_bad_params_are_named_by_the_schema(toml: str, word: str) -> None:
    """The gyro's parameters are declared and bounded once, in the configuration schema; the twin re-checks none."""
    with pytest.raises(ConfigError, match=word):
        parse_config(f"[sim]\n{toml}\n")


def test_bad_construction_and_inputs_are_named() -> None:
    with pytest.raises(ValueError, match="dt_s"):
        GyroSim(QUIET, -1.0, seed=1)
    with pytest.raises(ValueError, match="seed"):
        GyroSim(QUIET, DT, seed=-3)
    with pytest.raises(ValueError, match="samples per f0 cycle"):
        CarrierGyroSim(QUIET, 1.0 / (20 * 2200.0), seed=1)
    sim = GyroSim(QUIET, DT, seed=1)
    bad = held_inputs(10, DT)
    bad.dither_v = np.zeros(9)
    with pytest.raises(ValueError, match="same length"):
        sim.run(bad, _loops())
    with pytest.raises(ValueError, match="demod_order"):
        sim.run(held_inputs(10, DT), LoopSettings(demod_order=9))


def test_same_seed_same_output_independent_of_block_split() -> None:
    loops = _loops()
    one = GyroSim(paper_gyro_params(), DT, seed=7).run(held_inputs(3000, DT), loops)
    sim = GyroSim(paper_gyro_params(), DT, seed=7)
    parts = [sim.run(held_inputs(n, DT), loops) for n in (1000, 1, 1999)]
    split = np.concatenate([b.rate_output_v for b in parts])
    np.testing.assert_array_equal(one.rate_output_v, split)
    other = GyroSim(paper_gyro_params(), DT, seed=8).run(held_inputs(3000, DT), loops)
    assert not np.array_equal(one.rate_output_v, other.rate_output_v)


def test_settled_start_has_no_transient() -> None:
    p = QUIET
    b = GyroSim(p, DT, seed=1).run(held_inputs(1400, DT, rate_dps=5.0), _loops())
    assert np.allclose(b.x_drive, p.drive_amplitude_vrms, rtol=1e-9)
    assert np.allclose(b.frequency_hz, p.f0_hz, rtol=1e-12)
    assert b.pll_locked
    sf_rad = p.sf_true_v_per_dps * 180 / math.pi
    omega_b = 0.5 * p.damping_mismatch / p.tau_s * math.sin(math.radians(2 * p.damping_axis_deg)) / p.angular_gain
    # V_r = SF (Omega + Omega_b), Omega_b = Gamma_xy / k the damping-coupling bias (physics.md section 2)
    expected = sf_rad * (math.radians(5.0) + omega_b)
    assert b.rate_output_v == pytest.approx(np.full(1400, expected), rel=1e-6)


def test_true_sf_follows_temperature_and_gain() -> None:
    """At 35 C, g = 1.02, after the PLL and loops follow: V_r / Omega = sf (w/w0) / (G_f g) (loops.py header)."""
    p = QUIET
    sim = GyroSim(p, DT, seed=1)
    loops = _loops(1.02)
    sim.run(held_inputs(1400, DT, rate_dps=5.0, temperature_c=25.0), loops)
    b = sim.run(held_inputs(14000, DT, rate_dps=5.0, temperature_c=35.0), loops)
    w_ratio = 1 + p.frequency_tempco_ppm_per_c * 1e-6 * 10
    expected_sf = p.sf_true_v_per_dps * w_ratio / ((1 + p.forcer_tempco_ppm_per_c * 1e-6 * 10) * 1.02)
    assert b.frequency_hz[-1] == pytest.approx(p.f0_hz * w_ratio, abs=1e-6)
    assert b.pll_locked
    assert b.sf_true_v_per_dps[-1] == pytest.approx(expected_sf, rel=2e-6)
    rate_sf = (b.rate_output_v[-1400:].mean() - sim_bias_v(p, loops, 35.0)) / 5.0
    assert rate_sf == pytest.approx(expected_sf, rel=2e-5)


def sim_bias_v(p: GyroParams, loops: LoopSettings, temperature_c: float) -> float:
    """Rate output of the damping-coupling bias Omega_b = Gamma_xy/k at temperature T (Gamma scales with w)."""
    w = p.omega_rad_s(temperature_c)
    omega_b = 0.5 * p.damping_mismatch * w / (2 * p.q_factor) * math.sin(math.radians(2 * p.damping_axis_deg))
    omega_b /= p.angular_gain
    sf = p.true_scale_factor(temperature_c, loops.forcer_gain)
    return sf * math.degrees(omega_b)


def test_unsettled_start_locks() -> None:
    """From rest: the AGC builds the drive up and the PLL locks onto the drive resonance."""
    sim = GyroSim(QUIET, DT, seed=1)
    sim.reset(settled=False)
    sim.set_modal_state(1e-3, 0.0, 0.0, 0.0)  # a small seed motion for the PLL to see
    b = None
    for _ in range(40):
        b = sim.run(held_inputs(1400, DT), _loops())
    assert b is not None and b.pll_locked
    assert b.x_drive[-1] == pytest.approx(QUIET.drive_amplitude_vrms, rel=1e-3)


def test_block_inputs_from_a_world_are_accepted() -> None:

    w = paper_world()
    sim = GyroSim(QUIET, DT, seed=1)
    inp = w.advance(700, DT)
    assert isinstance(inp, BlockInputs)
    b = sim.run(inp, _loops())
    assert len(b) == 700 and b.rate_true_dps.shape == (700,)
