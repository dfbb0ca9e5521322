"""The forcer carrier on an HF2LI without MF, through the real zhinst-toolkit Session over the HF2 twin.

Instrument facts the twin holds independently of the driver (sims/hf2_loops.py): output mixer channel 7 runs on
oscillator 2 (index 1) and channel 6 on oscillator 1 (HF2 user manual, External Reference tutorial: Output 2
from "Demodulator 8 Amplitude 2" at "Oscillator 2 frequency"); a PLL enabled on the drive input locks the
oscillator ``plls/n/oscselect`` names. A carrier on an oscillator no PLL locks to the drive is not coherent with
the mode and exerts no mean force, so the rate loop cannot rebalance.

Expected numbers (docs/physics.md, as in test_hf2li_loops.py): FTR output for a table rate Omega is
V = SF * Omega * (1 + e_table), SF = 0.06 V per deg/s, e_table = 60 ppm: 0.3000180 V at +5 deg/s. Without a
coherent forcer the sense mode runs open: dX/dt = -k R_d Omega = -0.8 * 0.5 * (5 pi / 180) = -0.0349 Vrms/s.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import replace

import numpy as np
import pytest
from zhinst.toolkit import Session

from drivers.hf2li import HF2LI
from qmg_lab.campaign.loops import lockin_setup
from qmg_lab.config.schema import Config
from qmg_lab.instruments import InstrumentError, LockInBlock, LockInSetup
from qmg_lab.station import hf2_wiring
from sims.hf2_server import HF2DataServerTwin
from sims.world import World
from tests.support.twin_params import hf2_twin_settings, paper_gyro_params, paper_world

NON_MF = ("PLL", "PID")
SF, TABLE_ERROR, STEP_ACCEL = 0.06, 60e-6, 1e6
OPEN_LOOP_X_SLOPE = -0.8 * 0.5 * math.radians(5.0)  # Vrms/s at +5 deg/s with no force on the sense mode


def non_mf_config(**lockin: object) -> Config:
    cfg = Config()
    return cfg.model_copy(
        update={
            "sim": cfg.sim.model_copy(update={"hf2_options": list(NON_MF)}),
            "lockin": cfg.lockin.model_copy(update=lockin),
        }
    )


def bench(
    cfg: Config, setup_edit: Callable[[LockInSetup], LockInSetup] | None = None
) -> tuple[World, HF2DataServerTwin, HF2LI]:
    world = paper_world()
    twin = HF2DataServerTwin(
        world, paper_gyro_params(), seed=5, wiring=hf2_wiring(cfg), **hf2_twin_settings(options=NON_MF)
    )
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


def test_pll_2_locks_oscillator_2_on_the_drive_input_like_pll_1() -> None:
    cfg = non_mf_config()
    _, twin, li = bench(cfg)
    g, d = twin.getDouble, "/dev1234"
    assert li.state()["carriers"] == {
        "reference_oscillator": 0,
        "drive_oscillator": 0,
        "forcer_oscillator": 1,
        "tracking_plls": [1],
        # the twin's PLL 2 takes over demod 2 (plls/1/demodselect = 1): the sense demod moves to the next one
        "demods": {"drive": 0, "sense": 2},
    }
    for leaf in ("adcselect", "harmonic", "freqcenter", "freqrange", "setpoint", "p", "i", "enable"):
        assert g(f"{d}/plls/1/{leaf}") == g(f"{d}/plls/0/{leaf}"), leaf
    assert twin.getInt(f"{d}/pids/1/inputchannel") == 2 and twin.getInt(f"{d}/demods/2/adcselect") == 1
    b = poll_for(li, 1.0)
    assert b.pll_locked and twin.getInt(f"{d}/plls/1/locked") == 1
    assert twin.getInt(f"{d}/status/flags/binary") & (3 << 20) == 3 << 20  # b20 and b21: PLL 1 and 2 locked
    assert g(f"{d}/oscs/1/freq") == pytest.approx(float(b.drive_frequency[-1]), abs=1e-9)


def test_the_rate_loop_rebalances_with_the_forcer_on_oscillator_2() -> None:
    world, _, li = bench(non_mf_config())
    poll_for(li, 1.0)
    world.set_table_rate(5.0, STEP_ACCEL)
    plus = poll_for(li, 3.0)
    # after 2 s the critically damped loop's step response 1 - e^{-pt}(1 - pt), p = 5.06 rad/s, is within 4e-4
    o_plus = float(np.mean(plus.rate_output[plus.time > plus.time[0] + 2.0]))
    assert o_plus == pytest.approx(SF * 5.0 * (1 + TABLE_ERROR), rel=1e-3)
    assert abs(float(plus.x_sense[-1])) < 0.01  # held near zero


def test_a_driver_that_leaves_oscillator_2_alone_gets_no_rebalance() -> None:
    # the driver is told channel 7 runs on oscillator 1 (PLL 1's), so it neither sets nor locks oscillator 2;
    # the twin runs channel 7 on oscillator 2, as the manual says: the carrier is not coherent with the mode
    cfg = non_mf_config(fixed_channel_oscillators=(0, 0))
    world, twin, li = bench(cfg)
    assert li.state()["carriers"]["tracking_plls"] == [] and twin.getInt("/dev1234/plls/1/enable") == 0
    poll_for(li, 1.0)
    world.set_table_rate(5.0, STEP_ACCEL)
    b = poll_for(li, 0.5)
    assert float(b.x_sense[-1]) == pytest.approx(OPEN_LOOP_X_SLOPE * 0.5, rel=0.05)  # the sense mode runs open
    assert abs(float(np.mean(b.rate_output)) - SF * 5.0) > 0.1  # no rebalance


def test_pll_2_out_of_range_reports_unlocked_and_the_forcer_stops_rebalancing() -> None:
    world, twin, li = bench(non_mf_config())
    poll_for(li, 1.0)
    f0 = twin.getDouble("/dev1234/plls/1/freqcenter")
    twin.set("/dev1234/plls/1/freqcenter", f0 + 100.0)  # range 22 Hz: the drive frequency is out of its reach
    world.set_table_rate(5.0, STEP_ACCEL)
    b = li.poll(0.5)
    assert not b.pll_locked and not li.pll_locked() and twin.getInt("/dev1234/plls/1/locked") == 0
    assert float(b.x_sense[-1]) == pytest.approx(OPEN_LOOP_X_SLOPE * 0.5, rel=0.05)


def test_pll_1_out_of_range_is_reported_unlocked_on_every_block() -> None:
    # the PLL centre 50 Hz above the 2200 Hz resonance with a 22 Hz range: the PLL cannot reach it
    _, twin, li = bench(non_mf_config(), lambda s: replace(s, f0_hz=s.f0_hz + 50.0))
    blocks = [li.poll(0.5) for _ in range(3)]
    assert not any(b.pll_locked for b in blocks) and twin.getInt("/dev1234/plls/0/locked") == 0
    assert not li.pll_locked()


def test_a_carrier_oscillator_no_pll_drives_is_refused_at_connect() -> None:
    cfg = non_mf_config(fixed_channel_oscillators=(0, 3))  # an oscillator neither PLL drives
    twin = HF2DataServerTwin(
        paper_world(), paper_gyro_params(), seed=5, wiring=hf2_wiring(cfg), **hf2_twin_settings(options=NON_MF)
    )
    with pytest.raises(InstrumentError, match=r"oscillator 4 \(index 3.*no PLL drives that oscillator"):
        HF2LI(Session("localhost", hf2=True, connection=twin), "dev1234", cfg.lockin)


def test_with_mf_no_second_pll_is_used() -> None:
    cfg = Config()
    twin = HF2DataServerTwin(paper_world(), paper_gyro_params(), seed=5, wiring=hf2_wiring(cfg), **hf2_twin_settings())
    li = HF2LI(Session("localhost", hf2=True, connection=twin), "dev1234", cfg.lockin)
    li.configure(lockin_setup(cfg))
    carriers = li.state()["carriers"]
    assert carriers["tracking_plls"] == [] and carriers["forcer_oscillator"] == carriers["reference_oscillator"]
    assert twin.getInt("/dev1234/plls/1/enable") == 0
