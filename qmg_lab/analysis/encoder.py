"""The rate table's own measure of its motion, on the HF2's clock: its encoder's A/B quadrature pair recorded in
/lockin/table_encoder (the HF2 DIO input word of each demodulator sample; docs/wiring.md, docs/hdf5.md).

* Decoding. The pair (A, B) steps through the Gray sequence 00, 01, 11, 10 as the count rises (falls in reverse).
  Between two samples the state index q = gray^-1(A, B) changes by dq = ((q_k - q_(k-1) + 1) mod 4) - 1, i.e.
  -1, 0 or +1 count; dq = 2 (both bits changed) is a skipped state: the table moved more than one count in a
  sample interval, so the count is lost there (counted in `EncoderTrack.skipped`; the encoder is too fine for
  the demod rate: 4 L Omega / 360 must stay below the sample rate).
* Transition instants. A count change seen at sample k happened in (t_(k-1), t_k]; it is placed at the middle,
  t_k - dt/2, an error uniform in +-dt/2 (sigma dt/sqrt(12)) independent from one transition to the next.
* Plateau of a step (`plateau`): the table's constant-rate motion, found from the counts alone. The count is fitted
  by a line over the middle half of the step's host-timed span; the plateau is the longest run of transitions
  around the middle whose residual from that line stays within `PLATEAU_TOL_COUNTS`, and the line is refitted
  over it. Its ends are the first and the last transition of that run: the table's own start and end of the
  dwell, on the HF2's clock, whatever the host's timestamps of the commands.
* Rate over a window (`rate_over`): the least-squares slope of count against transition time over the window,
  times 360 / (4 L) deg per count. The counts are exact; with transition times off by u_i, |u_i| <= dt/2, over a
  window of length T (x_i = t_i - mean, spread evenly), the slope is off by sum x_i u_i / sum x_i^2 of itself,
  at most (dt/2) sum|x_i| / sum x_i^2 = 1.5 dt / T (2.4e-5 for a 35 s window at 1800 Sa/s). Errors independent
  from one transition to the next (a count period incommensurate with the sample interval) give the much smaller
  sigma = dt / (T sqrt n) for n transitions; a count period that is a whole number of samples (5 deg/s with a
  3600-line encoder at 1800 Sa/s: 9 samples) correlates them and approaches the worst case.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

#: transitions whose count is within this many counts of the step's line belong to its constant-rate plateau:
#: 1 count of quantisation, the +-dt/2 timing (0.06 count at 200 counts/s, 1800 Sa/s) and margin; the 300 deg/s^2
#: reversal from -5 to +5 deg/s leaves the line by (10 deg/s)^2 / (8 * 300 deg/s^2) = 0.04 deg = 1.7 counts of a
#: 3600-line encoder at its end, so the plateau starts within a few ms of the end of the acceleration
PLATEAU_TOL_COUNTS = 3.0
#: a plateau needs at least this many transitions (else the step had no usable table motion)
MIN_TRANSITIONS = 8

_GRAY_INDEX = np.array([0, 1, 3, 2], dtype=np.int64)  # (A << 1 | B) -> position in the sequence 00, 01, 11, 10


@dataclass(frozen=True)
class EncoderTrack:
    """The decoded encoder: the instant of each count change (s, the file's time axis) and the count after it."""

    time_s: np.ndarray
    count: np.ndarray
    skipped: int  # sample intervals in which both A and B changed (a count lost)
    counts_per_deg: float


@dataclass(frozen=True)
class Plateau:
    """A step's constant-rate motion seen by the encoder: its first and last transition (s) and its rate (deg/s)."""

    start_s: float
    end_s: float
    rate_dps: float


def decode_quadrature(
    time_s: np.ndarray, dio_word: np.ndarray, a_bit: int, b_bit: int, lines_per_rev: int
) -> EncoderTrack:
    """The counts of the A/B pair on DIO bits a_bit, b_bit of `dio_word` (module docstring)."""
    t = np.asarray(time_s, dtype=np.float64)
    word = np.asarray(dio_word, dtype=np.float64).astype(np.int64)
    state = ((word >> a_bit) & 1) << 1 | ((word >> b_bit) & 1)
    q = _GRAY_INDEX[state]
    dq = np.mod(np.diff(q) + 1, 4) - 1  # -1, 0, +1; 2 (both bits changed) is a skipped state
    skipped = int(np.count_nonzero(dq == 2))
    dq[dq == 2] = 0
    k = np.flatnonzero(dq) + 1
    dt = np.diff(t)
    return EncoderTrack(
        time_s=t[k] - 0.5 * dt[k - 1],
        count=np.cumsum(dq)[k - 1],
        skipped=skipped,
        counts_per_deg=4.0 * lines_per_rev / 360.0,
    )


def _line(t: np.ndarray, c: np.ndarray) -> tuple[float, float, float]:
    """Least-squares c = c0 + s (t - tm): (tm, c0, s)."""
    tm = float(np.mean(t))
    x = t - tm
    s = float(np.dot(x, c - np.mean(c)) / np.dot(x, x))
    return tm, float(np.mean(c)), s


def plateau(track: EncoderTrack, t_start: float, t_end: float) -> Plateau | None:
    """The constant-rate plateau of the table motion within the host-timed step [t_start, t_end] (module
    docstring); None if the table hardly moved (fewer than MIN_TRANSITIONS transitions in its middle half)."""
    t, c = track.time_s, track.count
    i0, i1 = np.searchsorted(t, [t_start, t_end])
    ts, cs = t[i0:i1], c[i0:i1].astype(np.float64)
    q0, q1 = t_start + 0.25 * (t_end - t_start), t_end - 0.25 * (t_end - t_start)
    mid = (ts >= q0) & (ts <= q1)
    if np.count_nonzero(mid) < MIN_TRANSITIONS:
        return None
    tm, c0, s = _line(ts[mid], cs[mid])
    ok = np.abs(cs - (c0 + s * (ts - tm))) <= PLATEAU_TOL_COUNTS
    centre = int(np.searchsorted(ts, 0.5 * (q0 + q1)))
    centre = min(max(centre, 0), ts.shape[0] - 1)
    bad = np.flatnonzero(~ok)
    lo = bad[bad < centre]
    hi = bad[bad > centre]
    a = int(lo[-1]) + 1 if lo.size else 0
    b = int(hi[0]) - 1 if hi.size else ts.shape[0] - 1
    if b - a + 1 < MIN_TRANSITIONS:
        return None
    _, _, s = _line(ts[a : b + 1], cs[a : b + 1])
    return Plateau(start_s=float(ts[a]), end_s=float(ts[b]), rate_dps=s / track.counts_per_deg)


def rate_over(track: EncoderTrack, t0: float, t1: float) -> float:
    """The table's mean rate over [t0, t1] from the encoder: the slope of count against time (module docstring),
    deg/s; NaN with fewer than MIN_TRANSITIONS transitions in the window."""
    i0, i1 = np.searchsorted(track.time_s, [t0, t1])
    if i1 - i0 < MIN_TRANSITIONS:
        return math.nan
    _, _, s = _line(track.time_s[i0:i1], track.count[i0:i1].astype(np.float64))
    return s / track.counts_per_deg
