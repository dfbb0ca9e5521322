"""qmg_lab.budget.linearity_scan: the scan of Fig. 2's 0.5 % FS against the budget's own laws.

Every expected number comes from the budget's model (docs/accuracy-budget.md), not from an earlier print:
* the loop tail is second order in the sense detuning d (the split couples the rate channel to the quadrature
  channel and back), so its nonlinearity scales as df^2 while d << w_c (d/w_c = 0.05 at 0.1 Hz);
* for levels much shorter than the tail's 1/z = 174 s the level means carry the earlier steps' tails decaying
  linearly in time, and the part that is not a straight line in the rate is the decay between levels: first
  order in T z, so halving dwell and settle halves it, up to the next order (T z = 0.06 at T = 10 s);
* a source linear in its parameter needs parameter * target / (its nonlinearity alone);
* an undithered n-bit converter over +-10 V: RMS error (20 V / 2^n) / sqrt(12) against SF * FS.

The split's tail exists under the zero-on-pole sense PIs, which these scans use ([loops] sense_pi_design); the
default critically damped PIs leave none (a split then costs only its CLSF-ratio term).
"""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from qmg_lab.budget.linearity_scan import (
    STAIRCASE_DPS,
    LevelProtocol,
    accuracy_tempco_window,
    nonlinearity_pct_fs,
    other_source_requirements,
    split_for_nonlinearity_hz,
    split_sim,
    startup_share_ppm,
    with_overrides,
)
from qmg_lab.budget.sweep import DETERMINISTIC_OFF, sweep_accuracy
from qmg_lab.config.schema import Config, load_config

PAPER = Path(__file__).resolve().parents[2] / "configs" / "paper_campaign.toml"


@pytest.fixture(scope="module")
def paper() -> Config:
    cfg = load_config(PAPER)[0]
    return cfg.model_copy(update={"loops": cfg.loops.model_copy(update={"sense_pi_design": "zero_on_pole"})})


@pytest.fixture(scope="module")
def tail_only(paper: Config) -> Config:
    return with_overrides(paper, DETERMINISTIC_OFF)


def test_tail_nonlinearity_grows_as_the_split_squared(tail_only: Config) -> None:
    small = nonlinearity_pct_fs(with_overrides(tail_only, split_sim(0.05, 0.0)))
    double = nonlinearity_pct_fs(with_overrides(tail_only, split_sim(0.1, 0.0)))
    assert small > 1e-3
    assert double / small == pytest.approx(4.0, rel=0.02)


def test_short_levels_lower_the_tail_nonlinearity_in_proportion_to_the_dwell(tail_only: Config) -> None:
    cfg = with_overrides(tail_only, split_sim(0.3, 0.0))
    ten = nonlinearity_pct_fs(cfg, LevelProtocol("10 s", STAIRCASE_DPS, 10.0, 1.0))
    five = nonlinearity_pct_fs(cfg, LevelProtocol("5 s", STAIRCASE_DPS, 5.0, 0.5))
    sixty = nonlinearity_pct_fs(cfg, LevelProtocol("60 s", STAIRCASE_DPS, 60.0, 5.0))
    assert ten / five == pytest.approx(2.0, rel=0.1)  # first order in T z: 10 s / 174 s = 0.06
    assert sixty > ten  # the paper's 0.5 s settling allows short levels, which only lower the figure


def test_the_split_for_a_target_inverts_the_budget_and_follows_the_square_law(paper: Config) -> None:
    target = 0.25
    df = split_for_nonlinearity_hz(paper, target, axis_deg=0.0)
    assert nonlinearity_pct_fs(with_overrides(paper, split_sim(df, 0.0))) == pytest.approx(target, rel=2e-3)
    # the square law from a small split's tail alone predicts the same split (the other sources are 0.003 % FS)
    tail = with_overrides(paper, {"table_rate_ripple_ppm": 0.0})
    ref = nonlinearity_pct_fs(with_overrides(tail, split_sim(0.1, 0.0)))
    assert df == pytest.approx(0.1 * math.sqrt(target / ref), rel=0.02)


def test_other_sources_need_what_their_linear_laws_say(paper: Config) -> None:
    req = other_source_requirements(paper, 0.5)
    lsb_rms_pct = 100.0 * 20.0 / 2.0**16 / math.sqrt(12.0) / (paper.sim.sf_true_v_per_dps * 5.0)
    assert req["converter_bits"]["alone_pct_fs"] == pytest.approx(lsb_rms_pct, rel=1e-9)
    bits = req["converter_bits"]["needed"]
    assert 100.0 * 20.0 / 2.0**bits / math.sqrt(12.0) / (paper.sim.sf_true_v_per_dps * 5.0) == pytest.approx(0.5)
    ripple = req["table_rate_ripple_ppm"]["needed"]
    only_ripple = with_overrides(paper, {**DETERMINISTIC_OFF, "table_rate_ripple_ppm": ripple})
    assert sweep_accuracy(only_ripple).nonlinearity_rms_pct_fs == pytest.approx(0.5, rel=0.01)
    rms_rate = math.sqrt(sum(r * r for r in STAIRCASE_DPS) / len(STAIRCASE_DPS))
    assert req["table_level_error_ppm"]["needed"] == pytest.approx(0.5e-2 * 5.0 / rms_rate * 1e6)


def test_the_split_start_up_share_is_second_order_and_decays_with_the_tail(paper: Config) -> None:
    """With nothing depending on temperature the split still moves the pairs against pair 0 (which follows the
    first step from rest): by d^2, like any tail; against pair 3 (started 6 dwells = 360 s after the first step)
    what is left of the start-up difference has decayed at least by e^{-z t}, z = 1/tau_n."""
    small, _ = startup_share_ppm(paper, 0.02, 0.0)
    big, later = startup_share_ppm(paper, 0.1, 0.0)
    assert big > 100.0
    assert big / small == pytest.approx(25.0, rel=0.02)
    z = 1.0 / paper.device.tau_s
    assert later < math.exp(-z * 6.0 * paper.plan.dwell_s) * big


@pytest.mark.slow
def test_the_tempco_window_edges_sit_on_the_accuracy_bound(paper: Config) -> None:
    """The window's edges are where the sweep accuracy crosses the bound; inside it, below; 1e-4 Hz/degC outside,
    above. The default tempco (-0.002 Hz/degC) with a 0.21 Hz split on the sense axis is outside it."""
    bound = 525.0
    w = accuracy_tempco_window(paper, 0.21, 0.0, bound)

    def acc(tc: float) -> float:
        return sweep_accuracy(with_overrides(paper, split_sim(0.21, 0.0, tc))).total_ppm

    assert w.min_accuracy_ppm < bound
    assert acc(w.low_hz_per_c) == pytest.approx(bound, rel=1e-3)
    assert acc(w.high_hz_per_c) == pytest.approx(bound, rel=1e-3)
    assert acc(w.low_hz_per_c - 1e-4) > bound < acc(w.high_hz_per_c + 1e-4)
    assert acc(w.tempco_at_min_hz_per_c) <= min(acc(w.low_hz_per_c), acc(w.high_hz_per_c))
    assert not w.low_hz_per_c <= paper.sim.freq_mismatch_tempco_hz_per_c <= w.high_hz_per_c
