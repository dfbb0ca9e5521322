"""Which dither periods of the estimator's sample buffer can be evaluated, and their results (numpy).

A period is [R_i, R_(i+1)) between two rising edges of the recorded dither; the estimator sums over the samples
of [R_i + D, R_(i+1) + D), D = n tc the demodulator filter's delay (qmg_lab/clsf/estimator.py).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from qmg_lab.clsf.kernels import period_ratios


@dataclass(frozen=True)
class PeriodWindows:
    """The periods of a buffer that can be evaluated (complete_periods)."""

    done: int  # the last i whose window [R_i + D, R_(i+1) + D) ends within the samples, or -1
    edges: np.ndarray  # (periods, 5): R_(i-1), F_a, R_i, F_b, R_(i+1) of each usable period, s
    k0: np.ndarray  # the windows' first sample index
    k1: np.ndarray  # and the index after their last


def complete_periods(
    rising: np.ndarray, falling: np.ndarray, t: np.ndarray, delay_s: float, min_samples: int
) -> PeriodWindows:
    """The periods [R_i, R_(i+1)) of the edge lists that can be evaluated on the sample times t (sorted).

    Complete: the window [R_i + D, R_(i+1) + D) ends within t. Usable: complete, exactly two falling edges
    F_a < R_i < F_b between R_(i-1) and R_(i+1), the window starting within t, and at least min_samples samples
    in it."""
    none = PeriodWindows(-1, np.empty((0, 5)), np.empty(0, dtype=np.int64), np.empty(0, dtype=np.int64))
    if rising.size < 3 or t.size == 0:
        return none
    r_prev, r0, r1 = rising[:-2], rising[1:-1], rising[2:]
    complete = r1 + delay_s <= t[-1]
    if not complete.any():
        return none
    done = int(np.flatnonzero(complete)[-1]) + 1  # the index i of R_i in `rising`
    fa = np.searchsorted(falling, r_prev, side="right")  # the first falling edge after R_(i-1)
    fb = np.searchsorted(falling, r1, side="left")  # the first at or after R_(i+1)
    usable = complete & (fb - fa == 2) & (r0 + delay_s >= t[0])
    if falling.size >= 2:
        fc = np.minimum(fa, falling.size - 2)
        usable &= (falling[fc] < r0) & (falling[fc + 1] > r0)
    else:
        usable[:] = False
    k0 = np.searchsorted(t, r0 + delay_s, side="left")
    k1 = np.searchsorted(t, r1 + delay_s, side="left")
    usable &= k1 - k0 >= min_samples
    f = fa[usable]
    edges = np.column_stack(
        (r_prev[usable], falling[f], r0[usable], falling[np.minimum(f + 1, falling.size - 1)], r1[usable])
    )
    return PeriodWindows(done, edges, k0[usable].astype(np.int64), k1[usable].astype(np.int64))


@dataclass(frozen=True)
class PeriodResults:
    """evaluate_periods' answer."""

    done: int  # as PeriodWindows.done
    usable: int  # the number of usable periods
    first_needed: int  # the first sample still needed (an index into the rows given)
    falling_needed: np.ndarray  # the falling edges still needed
    kept: np.ndarray  # rows R_i, R_(i+1), rho, mean rate output of the periods kept


def evaluate_periods(
    rising: np.ndarray,
    falling: np.ndarray,
    rows: np.ndarray,
    levels: tuple[float, float],
    order: int,
    tc_s: float,
    min_samples: int,
    holds: np.ndarray,
) -> PeriodResults:
    """The estimator's periods on its sample rows (t, y, H m_r, m_r): complete_periods with the filter's delay
    D = n tc, their ratios (kernels.period_ratios) and mean rate outputs.

    Mean rate output over [R_i, R_(i+1)]: the integral m_r interpolated linearly at both ends,
    (m_r(R_(i+1)) - m_r(R_i)) / (R_(i+1) - R_i). Kept: a finite rho and no overlap with any hold [h0, h1] (a row
    of holds: h0 <= R_(i+1) and R_i <= h1). Still needed once the periods up to `done` are evaluated (done >= 0):
    the rising edges from index done on (the next period's history edge R_done), the falling edges after R_done,
    and the samples from two before the first at or after R_(done+1) + D on."""
    t, y, mf, mr = rows
    delay_s = order * tc_s
    w = complete_periods(rising, falling, t, delay_s, min_samples)
    if w.done < 0:
        return PeriodResults(-1, 0, 0, falling, np.empty((4, 0)))
    first_needed = max(0, int(np.searchsorted(t, rising[w.done + 1] + delay_s, side="left")) - 2)
    falling_needed = falling[falling > rising[w.done]]
    rho = period_ratios(t, y, mf, w.edges, w.k0, w.k1, levels[0], levels[1], order, tc_s)
    r0, r1 = w.edges[:, 2], w.edges[:, 4]
    rate = (np.interp(r1, t, mr) - np.interp(r0, t, mr)) / (r1 - r0)
    held = ((holds[:, 0] <= r1[:, None]) & (r0[:, None] <= holds[:, 1])).any(axis=1)
    ok = np.isfinite(rho) & ~held
    return PeriodResults(w.done, r0.size, first_needed, falling_needed, np.stack((r0[ok], r1[ok], rho[ok], rate[ok])))
