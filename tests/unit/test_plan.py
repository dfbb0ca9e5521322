"""Plans: step sequences from the configuration and the limit checks made before anything moves."""

from __future__ import annotations

import math

import pytest

from qmg_lab.campaign.plan import (
    StepKind,
    assert_within_limits,
    build_plan,
    dither_amplitude_vpp,
    limit_checks,
    plan_duration_s,
)
from qmg_lab.config.schema import Config, parse_config
from qmg_lab.instruments import LimitError


def cfg(text: str = "") -> Config:
    return parse_config(text)


def test_paper_sweep_alternates_rates_over_ramp_and_end_hold():
    c = cfg(
        "[plan]\nchamber_start_c = 25\nchamber_end_c = 35\nchamber_ramp_c_per_min = 0.25\n"
        "chamber_end_hold_s = 600\ndwell_s = 60\n"
    )
    steps = build_plan(c)
    kinds = [s.kind for s in steps]
    assert kinds[:3] == ["lock", "dither", "soak"] and kinds[-1] == "return"
    rates = [s.table_rate_dps for s in steps if s.kind == "rate"]
    # (10 degC / 0.25 degC/min = 2400 s) + 600 s, in pairs of 2 x 60 s
    assert len(rates) == 2 * math.ceil(3000 / 120)
    assert rates[0::2] == [5.0] * (len(rates) // 2) and rates[1::2] == [-5.0] * (len(rates) // 2)
    assert all(s.chamber_target_c == 35.0 for s in steps if s.kind == "rate")
    assert [s.index for s in steps] == list(range(len(steps)))


def test_allan_plan_covers_duration_with_step_pairs():
    c = cfg("[campaign]\nkind = 'allan'\n[plan]\nduration_s = 3600\ntable_step_interval_s = 600\ndwell_s = 30\n")
    steps = build_plan(c)
    logged = sum(s.duration_s for s in steps if s.kind in ("hold", "rate"))
    assert logged == pytest.approx(3600.0)
    assert sum(1 for s in steps if s.kind == "rate") == 2 * 6


def test_bandwidth_plan_has_one_sine_step_per_frequency():
    c = cfg("[campaign]\nkind = 'bandwidth'\n[plan]\nbandwidth_frequencies_hz = [0.5, 2.0]\nbandwidth_cycles = 4\n")
    sines = [s for s in build_plan(c) if s.kind is StepKind.SINE]
    assert [s.label for s in sines] == ["sine:0.500Hz", "sine:2.000Hz"]
    assert [s.sine_frequency_hz for s in sines] == [0.5, 2.0]
    assert sines[1].duration_s >= 4 / 2.0


def test_dither_amplitude_is_twice_virtual_rate_times_sf():
    c = cfg("[dither]\nvirtual_rate_dps = 15\n[device]\nsf_nominal_v_per_dps = 0.06\n")
    assert dither_amplitude_vpp(c) == pytest.approx(1.8)


@pytest.mark.parametrize(
    "text, what",
    [
        ("[plan]\ntable_rate_dps = 150\n[table]\nmax_rate_dps = 100\n", "table rate"),
        ("[plan]\ntable_accel_dps2 = 800\n[table]\nmax_accel_dps2 = 500\n", "table acceleration"),
        ("[plan]\nchamber_end_c = 90\n[chamber]\nmax_c = 85\n", "chamber setpoint (highest)"),
        ("[plan]\nchamber_ramp_c_per_min = 10\n[chamber]\nmax_ramp_c_per_min = 5\n", "chamber ramp"),
        ("[dither]\nvirtual_rate_dps = 90\n", "dither amplitude"),
        ("[plan]\ntable_rate_dps = 170\n[table]\nmax_rate_dps = 200\n", "peak forcer command"),
    ],
)
def test_limits_refused_with_the_limit_named(text, what):
    c = cfg(text)
    steps = build_plan(c)
    bad = [ch for ch in limit_checks(c, steps) if not ch.ok]
    assert any(ch.what.startswith(what) for ch in bad), [ch.what for ch in bad]
    with pytest.raises(LimitError, match=what.split(" (")[0]):
        assert_within_limits(c, steps)


def test_sinusoid_peak_acceleration_checked():
    # 5 deg/s at 20 Hz needs 2 pi 20 5 = 628 deg/s^2 > 300
    c = cfg("[campaign]\nkind = 'bandwidth'\n[plan]\nbandwidth_frequencies_hz = [20.0]\n")
    bad = [ch for ch in limit_checks(c, build_plan(c)) if not ch.ok]
    assert bad and bad[0].value == pytest.approx(2 * math.pi * 20 * 5)


def test_duration_is_sum_of_steps():
    steps = build_plan(cfg())
    assert plan_duration_s(steps) == pytest.approx(sum(s.duration_s for s in steps))
