"""Closed loops through the whole chain: HF2LI driver -> zhinst-toolkit -> HF2 twin -> sims.gyro physics.

Expected numbers (docs/physics.md, qmg_lab/campaign/loops.py):
* FTR output for a table rate Omega: V = SF * Omega * (1 + e_table), SF = 0.06 V per deg/s, e_table = 60 ppm
  (World default): +5 deg/s -> 0.3000180 V; (O+ - O-) / 10 deg/s = SF (1 + 60e-6), bias cancelled.
* Rate loop of the zero-on-pole design ([loops] sense_pi_design = "zero_on_pole", set here) with I = P/tau: the PI
  zero cancels the envelope pole, L = bP/s, closed loop first order with time constant 1/(bP) = 1/(2 pi 2 Hz) =
  79.6 ms; doubling P halves it (39.8 ms). The default critically damped design: tests/unit/sims/test_gyro_rate_loop.py.
* PLL on the 2200 Hz drive resonance, AGC holding R = 0.5 Vrms.
* After a rate step the sense X keeps the slow mode -(k R_d Omega)/(bP) exp(-t/tau) of the pole-zero
  cancellation: -2.78 mV for 5 deg/s (open loop: -6.1 Vrms).
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from zhinst.toolkit import Session

from drivers.hf2li import HF2LI
from qmg_lab.campaign.loops import lockin_setup
from qmg_lab.config.schema import Config, LoopsSection
from qmg_lab.instruments import LockInBlock
from sims.hf2_server import HF2DataServerTwin
from sims.world import World
from tests.support.twin_params import hf2_twin_settings, paper_gyro_params, paper_wiring, paper_world

SF = 0.06
TABLE_ERROR = 60e-6
STEP_ACCEL = 1e6  # deg/s^2: a step as sharp as one 0.7 ms sample


def bench(setup_edit=None) -> tuple[World, HF2DataServerTwin, HF2LI]:
    cfg = Config(loops=LoopsSection(sense_pi_design="zero_on_pole"))
    world = paper_world()
    twin = HF2DataServerTwin(world, paper_gyro_params(), seed=11, wiring=paper_wiring(), **hf2_twin_settings())
    li = HF2LI(Session("localhost", hf2=True, connection=twin), "dev1234", cfg.lockin)
    setup = lockin_setup(cfg)
    li.configure(setup_edit(setup) if setup_edit else setup)
    li.start_stream()
    return world, twin, li


def poll_for(li: HF2LI, seconds: float) -> LockInBlock:
    blocks = [li.poll(0.5) for _ in range(int(round(seconds / 0.5)))]
    return LockInBlock(
        *(np.concatenate([getattr(b, f) for b in blocks]) for f in LockInBlock.FIELDS),
        pll_locked=all(b.pll_locked for b in blocks),
        samples_lost=sum(b.samples_lost for b in blocks),
    )


def time_constant_s(block: LockInBlock, t_step: float, before: float) -> float:
    """Time from the step to 1 - 1/e of the rate-output change (linear interpolation)."""
    final = float(np.mean(block.rate_output[block.time > block.time[-1] - 0.5]))
    frac = (block.rate_output - before) / (final - before)
    k = int(np.argmax(frac >= 1 - math.exp(-1)))
    t0, t1, f0, f1 = block.time[k - 1], block.time[k], frac[k - 1], frac[k]
    return float(t0 + (1 - math.exp(-1) - f0) * (t1 - t0) / (f1 - f0) - t_step)


def test_pll_locks_and_agc_holds_the_drive_amplitude() -> None:
    _, _, li = bench()
    b = poll_for(li, 1.0)
    assert b.pll_locked and li.pll_locked()
    assert np.allclose(b.drive_frequency, 2200.0, atol=1e-3)
    assert np.allclose(b.drive_amplitude, 0.5, rtol=1e-4)
    assert b.samples_lost == 0


def test_table_step_settles_to_sf_times_rate_with_sense_x_held_at_zero() -> None:
    world, _, li = bench()
    poll_for(li, 1.0)
    world.set_table_rate(5.0, STEP_ACCEL)
    plus = poll_for(li, 2.0)
    world.set_table_rate(-5.0, STEP_ACCEL)
    minus = poll_for(li, 2.0)
    o_plus = float(np.mean(plus.rate_output[plus.time > plus.time[0] + 1.0]))
    o_minus = float(np.mean(minus.rate_output[minus.time > minus.time[0] + 1.0]))
    assert o_plus == pytest.approx(SF * 5.0 * (1 + TABLE_ERROR), rel=1e-3)
    assert (o_plus - o_minus) / 10.0 == pytest.approx(SF * (1 + TABLE_ERROR), rel=1e-3)
    # FTR holds c_y: open loop it would head for -k R_d Omega tau = -6.1 Vrms. With the PI zero on the envelope
    # pole (I = P/tau) the step leaves the slow mode X = -(k R_d Omega / (2 pi f_bw)) exp(-t/tau): -2.78 mV,
    # decaying with tau = 173.6 s (physics.md section 4; loops.rate_zero_offset_hz moves the zero to hide it).
    settled = plus.x_sense[plus.time > plus.time[0] + 1.0]
    slow_mode = -0.8 * 0.5 * math.radians(5.0) / (2 * math.pi * 2.0)
    assert float(np.mean(settled)) == pytest.approx(slow_mode, rel=0.03)
    assert plus.pll_locked and minus.pll_locked


@pytest.mark.parametrize("p_factor", [1.0, 2.0])
def test_rate_loop_settling_follows_the_proportional_gain(p_factor: float) -> None:
    edit = (lambda s: replace(s, rate=replace(s.rate, p=s.rate.p * p_factor))) if p_factor != 1.0 else None
    world, _, li = bench(edit)
    before_block = poll_for(li, 1.0)
    before = float(np.mean(before_block.rate_output[-350:]))
    t_step = before_block.time[-1]  # the step starts with the next poll's first step
    world.set_table_rate(5.0, STEP_ACCEL)
    after = poll_for(li, 1.5)
    tc = time_constant_s(after, t_step, before)
    expected = 1.0 / (2 * math.pi * 2.0 * p_factor)  # 79.6 ms nominal, 39.8 ms with P doubled
    assert tc == pytest.approx(expected, rel=0.05)


def test_forced_pll_unlock_is_reported_then_relocks() -> None:
    _, twin, li = bench()
    li.poll(0.5)
    twin.force_pll_unlock(1.0)
    assert not li.poll(0.5).pll_locked
    assert not li.poll(0.5).pll_locked
    assert not li.pll_locked()  # the nodes report the last block, which ended with the window
    assert li.poll(0.5).pll_locked and li.pll_locked()


def test_auxout_not_in_manual_mode_leaves_the_rate_loop_open() -> None:
    world, twin, li = bench()
    li.poll(0.5)
    twin.set("/dev1234/auxouts/0/outputselect", 0)  # AuxOut 1 shows demod X: the PID no longer drives it
    world.set_table_rate(5.0, STEP_ACCEL)
    b = li.poll(0.5)
    # the AuxOut ramps from the PID's last value to the new one over one sample interval, then reads 0 V, as the
    # AuxIn reports it: + its reading noise (sigma) and rounded to its step (GyroParams defaults)
    p = twin.gyro_params
    assert np.all(np.abs(b.rate_output[2:]) <= 6 * p.auxin_noise_v_rms + p.auxin_lsb_v / 2)
    assert abs(float(np.mean(b.rate_output[2:]))) < 3 * math.hypot(p.auxin_noise_v_rms, p.auxin_lsb_v) / math.sqrt(
        b.rate_output[2:].size
    )
    # open loop: dX/dt = -k R_d Omega (rad/s) = -0.8 * 0.5 * 5 pi/180 = -0.0349 Vrms/s -> ~ -0.017 Vrms at 0.5 s
    assert float(b.x_sense[-1]) == pytest.approx(-0.8 * 0.5 * math.radians(5.0) * 0.5, rel=0.05)
