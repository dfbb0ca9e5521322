"""Pairing the drive and sense demodulators' samples (drivers/hf2li.py, module docstring: pairing).

The tolerance is half a sample period, T / 2 with T = clockbase / rate: at the HF2's 210 MHz clockbase and
1800 Sa/s, T = 116 667 ticks (the rate the twin applies: whole ticks) and the tolerance 58 333.5 ticks. The twin
offsets every demodulator's timestamps but the first by ``timestamp_offset_ticks`` ([sim]
hf2_timestamp_offset_ticks) and drops samples from one demodulator on request, through the real zhinst-toolkit
Session.
"""

from __future__ import annotations

import numpy as np
import pytest
from zhinst.toolkit import Session

from drivers.hf2li import HF2LI, pair_nearest
from qmg_lab.campaign.loops import lockin_setup
from qmg_lab.config.schema import Config
from qmg_lab.station import hf2_wiring
from sims.hf2_server import HF2DataServerTwin
from tests.support.twin_params import hf2_twin_settings, paper_gyro_params, paper_world

CLOCKBASE = 210e6
T = round(CLOCKBASE / 1800.0)  # ticks per sample: the twin applies 1800 Sa/s as a whole number of clock ticks
RATE = CLOCKBASE / T
PER_POLL = 900  # round(0.5 s * 1800 Sa/s)


def streaming(offset_ticks: int) -> tuple[HF2DataServerTwin, HF2LI]:
    cfg = Config()
    twin = HF2DataServerTwin(
        paper_world(),
        paper_gyro_params(),
        seed=9,
        wiring=hf2_wiring(cfg),
        timestamp_offset_ticks=offset_ticks,
        **hf2_twin_settings(),
    )
    li = HF2LI(Session("localhost", hf2=True, connection=twin), "dev1234", cfg.lockin)
    li.configure(lockin_setup(cfg))
    li.start_stream()
    return twin, li


def test_nearest_pairs_within_half_a_period_and_none_beyond() -> None:
    drive = np.arange(10, dtype=np.int64) * 1000
    i_d, i_s = pair_nearest(drive, drive + 499, 500.0)  # in order: all pair, no search
    assert isinstance(i_d, slice) and isinstance(i_s, slice)
    i_d, i_s = pair_nearest(drive, drive + 500, 500.0)  # exactly half a period: not nearer than the tolerance
    assert len(i_d) == len(i_s) == 0
    i_d, i_s = pair_nearest(drive, drive[[0, 1, 2, 5, 6, 9]] - 300, 500.0)  # samples missing in the sense stream
    assert list(i_d) == [0, 1, 2, 5, 6, 9] and list(i_s) == [0, 1, 2, 3, 4, 5]
    i_d, i_s = pair_nearest(drive[[0, 3, 4]], drive + 900, 500.0)  # 0.9 T late: each pairs with the next one
    assert list(i_d) == [1, 2] and list(i_s) == [2, 3]


@pytest.mark.parametrize("offset", [30_000, -30_000, 58_000])
def test_offset_timestamps_pair_completely_and_the_offset_is_reported(offset: int) -> None:
    assert abs(offset) < T / 2
    twin, li = streaming(offset)
    twin.run_unobserved(0.01)  # the instrument has run a while (timestamps count ticks since it started)
    assert li.state()["demod_timestamp_offset_ticks"] == offset  # before the stream: demods/n/sample
    blocks = [li.poll(0.5) for _ in range(3)]
    assert [len(b) for b in blocks] == [PER_POLL] * 3 and sum(b.samples_lost for b in blocks) == 0
    t = np.concatenate([b.time for b in blocks])
    assert np.allclose(np.diff(t), 1 / RATE, rtol=0, atol=1e-12)
    assert li.demod_timestamp_offset() == offset  # from the stream's pairs


@pytest.mark.parametrize(("offset", "demod"), [(30_000, 1), (30_000, 0), (0, 1)])
def test_samples_missing_from_one_demodulator_are_counted_lost(offset: int, demod: int) -> None:
    twin, li = streaming(offset)
    li.poll(0.5)
    twin.drop_samples(7, demod=demod)
    b = li.poll(0.5)
    assert b.samples_lost == 7 and len(b) == PER_POLL - 7
    assert li.poll(0.5).samples_lost == 0


def test_a_sample_whose_partner_comes_with_the_next_poll_waits_for_it() -> None:
    # 0.9 T late: each sense sample pairs with the drive sample after it, which for the last sense sample of a
    # block arrives with the next poll; it is held back, not lost
    offset = int(0.9 * T)
    _, li = streaming(offset)
    blocks = [li.poll(0.5) for _ in range(4)]
    assert sum(b.samples_lost for b in blocks) == 0
    assert [len(b) for b in blocks] == [PER_POLL - 1, PER_POLL, PER_POLL, PER_POLL]
    t = np.concatenate([b.time for b in blocks])
    assert np.allclose(np.diff(t), 1 / RATE, rtol=0, atol=1e-12)
    assert li.demod_timestamp_offset() == offset - T  # sense minus the (next) drive sample


def test_a_block_where_nothing_pairs_is_empty_and_counts_every_sample_lost() -> None:
    # the drive demodulator's stream delivers nothing for one poll: no sense sample has a partner
    twin, li = streaming(30_000)
    li.poll(0.5)
    twin.unsubscribe("/dev1234/demods/0/sample")
    b = li.poll(0.5)
    assert len(b) == 0 and b.samples_lost == PER_POLL
    twin.subscribe("/dev1234/demods/0/sample")
    after = li.poll(0.5)
    assert len(after) == PER_POLL and after.samples_lost == 0  # the lost ones are not counted twice
