"""The twin kernel's fast paths against the formulas they replace, and GyroSim.run's per-block bookkeeping.

The averaged kernel evaluates the locked PLL's phase from the atan series, the HF2's single demod section in one
line, and runs a long block in chunks written in place; run() keeps the packed loop vector while the settings stay
equal. Each must give what the general formula or the unsplit run gives.
"""

from __future__ import annotations

import copy
import dataclasses
import itertools
import math

import numpy as np
import pytest

from sims import gyro_kernel as gk
from sims.gyro import CHUNK_STEPS, GyroSim, _same_loops, held_inputs
from sims.gyro_params import LoopSettings, pack_loops
from tests.support.paper_loops import paper_loops
from tests.support.twin_params import paper_gyro_params

DT = 1.0 / 1800.0
EPS = np.finfo(float).eps


@pytest.mark.parametrize("x", [0.5, 1.0, 3e-3, 1e6])
def test_locked_pll_phase_series_equals_atan2_to_rounding(x: float) -> None:
    # ratios up to the series' limit 1e-3 (both signs), then past it where math.atan2 takes over
    ratios = np.concatenate([np.geomspace(1e-12, 1e-3, 60), [0.0, 1.0001e-3, 0.5, 3.0]])
    for r in np.concatenate([ratios, -ratios]):
        y = r * x
        exact = math.atan2(y, x)
        assert abs(gk._atan2(y, x) - exact) <= 4 * EPS * abs(exact), (y, x)


def test_atan2_outside_the_series_is_math_atan2() -> None:
    for y, x in [(1.0, -1.0), (-2e-5, -0.5), (0.3, 0.0), (0.0, -1.0), (1e-4, 1e-3)]:
        assert gk._atan2(y, x) == math.atan2(y, x)


def _one_section_step(y: float, u_old: float, u_new: float, dt: float, tc: float) -> float:
    """The first-order section under a raw value linear over the step (gyro_kernel docstring):
    y+ = a y + (1 - a) u- + (u+ - u-)(1 - tc (1 - a)/dt), a = exp(-dt/tc)."""
    a = math.exp(-dt / tc)
    return a * y + (1.0 - a) * u_old + (u_new - u_old) * (1.0 - tc * (1.0 - a) / dt)


@pytest.mark.parametrize("tc", [1e-4, 2e-3, 0.05])
def test_single_demod_section_follows_the_first_order_hold_formula(tc: float) -> None:
    loops = paper_loops(1.0)
    loops.demod_timeconstant_s = tc
    loops.demod_order = 1
    lvec = pack_loops(loops)
    p = GyroSim(paper_gyro_params(), DT, seed=1)._P
    fj, fs, fr, order, a_d, c_d, sections = gk._lowpass_sections(p, lvec, DT)
    rng = np.random.default_rng(3)
    s = np.zeros(gk.N_STATE)
    start = rng.normal(size=(4, 2))  # (previous raw value, section state) per channel
    for ch in range(4):
        base = gk.S_FILT + gk.FILT_STRIDE * ch
        s[base], s[base + 1] = start[ch]
    raws = rng.normal(size=4)
    filt = np.empty(4)
    gk._control(s, lvec, raws, filt, DT, fj, fs, fr, order, a_d, c_d, sections)
    for ch in range(4):
        expected = _one_section_step(start[ch, 1], start[ch, 0], raws[ch], DT, tc)
        assert filt[ch] == pytest.approx(expected, rel=1e-13, abs=1e-15)


@pytest.mark.parametrize("n", [CHUNK_STEPS + 777, 8 * CHUNK_STEPS + 777])
def test_a_block_longer_than_a_chunk_equals_the_same_steps_in_short_blocks(n: int) -> None:
    """A long block runs chunk by chunk, each chunk drawing its own noise rows: the same run as short blocks."""
    loops = paper_loops(1.0)
    inputs = held_inputs(n, DT, rate_dps=5.0, temperature_c=np.linspace(25.0, 26.0, n))
    one = GyroSim(paper_gyro_params(), DT, seed=11).run(inputs, loops)
    sim = GyroSim(paper_gyro_params(), DT, seed=11)
    cuts = [0, 900, CHUNK_STEPS - 1, CHUNK_STEPS + 1, n]
    parts = []
    for a, b in itertools.pairwise(cuts):
        sub = held_inputs(b - a, DT, rate_dps=5.0, temperature_c=inputs.gyro_c[a:b], t0_s=a * DT)
        parts.append(sim.run(sub, loops))
    for name in ("rate_output_v", "x_drive", "pll_error_deg", "sf_true_v_per_dps"):
        np.testing.assert_array_equal(getattr(one, name), np.concatenate([getattr(b, name) for b in parts]))
    assert one.pll_locked and all(b.pll_locked for b in parts)


def test_loop_settings_changed_in_place_between_blocks_take_effect() -> None:
    loops = paper_loops(1.0)
    sim = GyroSim(paper_gyro_params().noiseless(), DT, seed=1)
    first = sim.run(held_inputs(200, DT, rate_dps=5.0), loops)
    assert abs(first.rate_output_v[-1]) > 0.01  # the rate loop balances the 5 deg/s Coriolis force
    loops.rate.enabled = False  # the same object, changed in place
    second = sim.run(held_inputs(200, DT, rate_dps=5.0), loops)
    np.testing.assert_array_equal(second.rate_output_v, np.full(200, loops.rate.center))


@pytest.mark.parametrize("n", [300, CHUNK_STEPS + 300])
def test_a_block_whose_state_went_nan_reads_as_unlocked(n: int) -> None:
    sim = GyroSim(paper_gyro_params().noiseless(), DT, seed=1)
    loops = paper_loops(1.0)
    assert sim.run(held_inputs(n, DT), loops).pll_locked
    sim._S[gk.S_CX] = float("nan")  # a diverged state: the PLL error is NaN from then on
    assert not sim.run(held_inputs(n, DT), loops).pll_locked


def test_the_loop_settings_comparison_sees_every_field() -> None:
    base = paper_loops(1.0)
    assert _same_loops(base, copy.deepcopy(base))
    for name in [f.name for f in dataclasses.fields(LoopSettings)]:
        value = getattr(base, name)
        if dataclasses.is_dataclass(value):
            for sub in dataclasses.fields(value):
                changed = copy.deepcopy(base)
                old = getattr(value, sub.name)
                setattr(getattr(changed, name), sub.name, (not old) if isinstance(old, bool) else old + 0.5)
                assert changed != base and not _same_loops(changed, base), (name, sub.name)
        else:
            changed = copy.deepcopy(base)
            setattr(changed, name, value + 1)
            assert changed != base and not _same_loops(changed, base), name


def test_a_disabled_pll_never_reads_as_locked() -> None:
    loops = paper_loops(1.0)
    loops.pll.enabled = False
    b = GyroSim(paper_gyro_params().noiseless(), DT, seed=1).run(held_inputs(100, DT), loops)
    assert not b.pll_locked


@pytest.mark.parametrize(
    ("name", "bad", "words"),
    [
        ("table_rate_dps", float("nan"), "table_rate_dps contains a non-finite"),
        ("dither_v", float("inf"), "dither_v contains a non-finite"),
        ("gyro_c", -float("inf"), "gyro_c contains a non-finite"),
    ],
)
def test_a_non_finite_input_is_named_and_the_state_is_kept(name: str, bad: float, words: str) -> None:
    loops = paper_loops(1.0)
    sim = GyroSim(paper_gyro_params(), DT, seed=5)
    sim.run(held_inputs(50, DT), loops)
    before = sim._S.copy()
    inputs = held_inputs(50, DT)
    getattr(inputs, name)[17] = bad
    with pytest.raises(ValueError, match=words):
        sim.run(inputs, loops)
    np.testing.assert_array_equal(sim._S, before)
    with pytest.raises(ValueError, match="1-D"):
        sim.run(held_inputs(50, DT, temperature_c=np.full((50, 1), 25.0)), loops)
