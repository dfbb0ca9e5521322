"""Plans: step sequences from the configuration and the limit checks made before anything moves."""

from __future__ import annotations

import math
import re

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from qmg_lab.campaign.plan import (
    LimitCheck,
    StepKind,
    assert_within_limits,
    build_plan,
    limit_checks,
    plan_duration_s,
)
from qmg_lab.config.schema import (
    MAX_PLAN_STEPS,
    Config,
    ConfigError,
    dither_amplitude_vpp,
    parse_config,
    plan_step_bound,
)
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


# (plan text, instrument limit text, the limit_checks row, the key that sets the bound, the bound's value)
INSTRUMENT_BOUNDS = [
    ("table_rate_dps = {v}", "[table]\nmax_rate_dps = 100", "table rate", "table.max_rate_dps", 100.0),
    ("table_accel_dps2 = {v}", "[table]\nmax_accel_dps2 = 500", "table acceleration", "table.max_accel_dps2", 500.0),
    ("chamber_end_c = {v}", "[chamber]\nmax_c = 85", "chamber setpoint (highest)", "chamber.max_c", 85.0),
    (
        "chamber_ramp_c_per_min = {v}",
        "[chamber]\nmax_ramp_c_per_min = 5",
        "chamber ramp",
        "chamber.max_ramp_c_per_min",
        5.0,
    ),
]


@pytest.mark.parametrize("plan_line, limit_text, what, key, bound", INSTRUMENT_BOUNDS)
def test_the_schema_and_the_limit_checks_share_one_bound(plan_line, limit_text, what, key, bound):
    """At the instrument's limit both accept; just above it the schema refuses naming the limit's key, and the
    limit check (on the same values, unvalidated) refuses at the same bound: one source for the bound."""
    at = cfg(f"[plan]\n{plan_line.format(v=bound)}\n{limit_text}\n")
    assert all(ch.ok for ch in limit_checks(at, build_plan(at)) if ch.what == what)
    above = bound * 1.01
    with pytest.raises(ConfigError, match=rf"plan\.\w+ = {above:g} is .*{re.escape(key)}"):
        cfg(f"[plan]\n{plan_line.format(v=above)}\n{limit_text}\n")
    field = plan_line.split(" = ")[0]
    unchecked = at.model_copy(update={"plan": at.plan.model_copy(update={field: above})})
    row = next(ch for ch in limit_checks(unchecked, build_plan(unchecked)) if ch.what == what)
    assert not row.ok and row.high == bound
    assert row.describe().endswith(f"outside [{row.low:g}, {bound:g}] {row.unit}")


def test_a_limit_check_says_within_only_when_it_passes():
    ok, bad = LimitCheck("table rate", 50.0, 0.0, 100.0, "deg/s"), LimitCheck("table rate", 500.0, 0.0, 100.0, "deg/s")
    assert ok.describe() == "table rate = 50 deg/s within [0, 100] deg/s"
    assert bad.describe() == "table rate = 500 deg/s outside [0, 100] deg/s"


def test_sinusoid_peak_acceleration_checked():
    # 5 deg/s at 20 Hz needs 2 pi 20 5 = 628 deg/s^2 > 300
    c = cfg("[campaign]\nkind = 'bandwidth'\n[plan]\nbandwidth_frequencies_hz = [20.0]\n")
    bad = [ch for ch in limit_checks(c, build_plan(c)) if not ch.ok]
    assert bad and bad[0].value == pytest.approx(2 * math.pi * 20 * 5)


def test_duration_is_sum_of_steps():
    steps = build_plan(cfg())
    assert plan_duration_s(steps) == pytest.approx(sum(s.duration_s for s in steps))


@settings(max_examples=80, deadline=None)
@given(
    kind=st.sampled_from(["temperature_sweep", "allan", "bandwidth", "linearity"]),
    dwell=st.floats(1.0, 600.0),
    ramp=st.floats(0.05, 5.0),
    end_c=st.floats(20.0, 45.0),
    hold=st.floats(0.0, 3600.0),
    duration=st.floats(60.0, 86400.0),
    interval=st.sampled_from([0.0, 10.0, 300.0, 1000.0, 5000.0]),
)
def test_the_schema_bounds_the_plan_s_length_from_above(kind, dwell, ramp, end_c, hold, duration, interval):
    """plan_step_bound (what the schema refuses plans above MAX_PLAN_STEPS by) is never below the plan built."""
    c = cfg(
        f"[campaign]\nkind = '{kind}'\n[plan]\ndwell_s = {dwell!r}\nsettle_s = 0.0\nchamber_ramp_c_per_min = {ramp!r}\n"
        f"chamber_end_c = {end_c!r}\nchamber_end_hold_s = {hold!r}\nduration_s = {duration!r}\n"
        f"table_step_interval_s = {interval!r}\n[chamber]\nmax_ramp_c_per_min = 5.0\n"
    )
    assert len(build_plan(c)) <= plan_step_bound(c)


@pytest.mark.parametrize(
    "text, keys",
    [
        ("[plan]\nchamber_ramp_c_per_min = 1e-9\n", "plan.chamber_ramp_c_per_min (degC/min), plan.dwell_s (s)"),
        ("[plan]\ndwell_s = 1e-6\nsettle_s = 0.0\n", "plan.chamber_ramp_c_per_min (degC/min), plan.dwell_s (s)"),
        (
            "[campaign]\nkind = 'allan'\n[plan]\ntable_step_interval_s = 1e-3\ndwell_s = 1e-3\nsettle_s = 0.0\n",
            "plan.table_step_interval_s (s), plan.dwell_s (s)",
        ),
    ],
)
def test_a_plan_of_billions_of_steps_is_refused_at_once(text, keys):
    with pytest.raises(ConfigError, match=re.escape(f"more than {MAX_PLAN_STEPS}: check {keys}")):
        cfg(text)
