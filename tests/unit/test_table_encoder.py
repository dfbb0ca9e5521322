"""The rate table's encoder from the twin's world to the analysis: the 1291BR twin's A/B word sampled on the HF2's
sample grid (sims/table_twin.TableEncoder), decoded and timed by qmg_lab/analysis/encoder.py.

Bounds come from the quantisation: a transition placed at the middle of its sample interval is off by at most
dt/2, so the slope over a window of length T is off by at most 1.5 dt / T of itself (encoder.py: the worst case,
which a count period commensurate with the sample grid, 5 deg/s here, can approach). The plateau starts with the
motion (a ramp from rest whose lag behind the final line, Omega^2 / (2 a), is under PLATEAU_TOL_COUNTS, belongs to
it) and no later than PLATEAU_TOL_COUNTS + 1 counts after the ramp's end.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from qmg_lab.analysis.encoder import PLATEAU_TOL_COUNTS, decode_quadrature, plateau, rate_over
from sims.table_twin import TableEncoder
from tests.support.twin_params import paper_world

FS = 1800.0
DT = 1.0 / FS
LINES = 3600


def _record(world, encoder: TableEncoder, seconds: float) -> tuple[np.ndarray, np.ndarray]:
    """The DIO words the HF2 twin would stream: one per sample, at the end of each step (sims/hf2_server.py)."""
    n = int(round(seconds * FS))
    inputs = world.advance(n, DT)
    return inputs.t + DT, encoder.dio_word(inputs.table_angle_deg + inputs.table_rate_dps * DT)


@pytest.mark.parametrize("rate_dps", [5.0, -5.0, 1.3])
def test_encoder_rate_and_plateau_within_the_quantisation_bound(rate_dps: float) -> None:
    world = paper_world(table_rate_scale_error_ppm=60.0, table_rate_ripple_ppm=0.0)
    enc = TableEncoder(world, lines_per_rev=LINES, a_bit=3, b_bit=5)
    t_a, w_a = _record(world, enc, 2.0)  # at rest
    accel = 300.0
    t_cmd = float(world.t)
    world.set_table_rate(rate_dps, accel)
    t_b, w_b = _record(world, enc, 40.0)
    track = decode_quadrature(np.concatenate([t_a, t_b]), np.concatenate([w_a, w_b]), 3, 5, LINES)
    assert track.skipped == 0
    delivered = rate_dps * (1 + 60e-6)  # the servo's rate: the command times the table's scale error
    win = (t_cmd + 5.0, t_cmd + 40.0)
    bound = 1.5 * DT / (win[1] - win[0])
    assert abs(rate_over(track, *win) / delivered - 1) < bound
    p = plateau(track, t_cmd, t_cmd + 40.0)
    assert p is not None
    ramp_end = t_cmd + abs(rate_dps) / accel
    assert t_cmd <= p.start_s <= ramp_end + (PLATEAU_TOL_COUNTS + 1) / (track.counts_per_deg * abs(rate_dps))
    assert p.end_s <= t_cmd + 40.0 and p.end_s > t_cmd + 40.0 - 2 / (track.counts_per_deg * abs(rate_dps)) - DT


def test_encoder_reads_the_servo_angle_not_the_rippled_table_angle() -> None:
    """With a once-per-revolution ripple r, the table turns at (1 + r sin(theta + phi)) times the encoder's rate:
    over a whole number of revolutions both agree; over a half turn from theta = 0 the table has turned
    r (180/pi) * 2 deg more than the encoder counted (the integral of r sin over [0, 180 deg])."""
    r_ppm = 1000.0
    world = paper_world(table_rate_scale_error_ppm=0.0, table_rate_ripple_ppm=r_ppm, table_ripple_phase_deg=0.0)
    enc = TableEncoder(world, lines_per_rev=LINES, a_bit=0, b_bit=1)
    world.set_table_rate(30.0, 1e6)
    t, w = _record(world, enc, 12.0)  # 360 deg
    track = decode_quadrature(t, w, 0, 1, LINES)
    angle_half = r_ppm * 1e-6 * (180 / math.pi) * 2
    i = np.searchsorted(t, 6.0)
    counted_half = track.count[np.searchsorted(track.time_s, t[i]) - 1] / track.counts_per_deg
    # the servo's (ripple-free) angle after 6 s at 30 deg/s is 180 deg; the table's is angle_half more
    assert counted_half == pytest.approx(180.0, abs=2 / track.counts_per_deg)
    assert angle_half > 2 / track.counts_per_deg  # the test resolves the eccentricity
    counted_full = track.count[-1] / track.counts_per_deg
    assert counted_full == pytest.approx(360.0, abs=2 / track.counts_per_deg)


def test_a_skipped_state_is_counted_not_decoded_as_a_step_back() -> None:
    words = np.array([0b00, 0b01, 0b11, 0b10, 0b01, 0b11], dtype=np.float64)  # 10 -> 01: both bits changed
    track = decode_quadrature(np.arange(6) * DT, words, 1, 0, LINES)
    assert track.skipped == 1
    assert list(track.count) == [1, 2, 3, 4]
