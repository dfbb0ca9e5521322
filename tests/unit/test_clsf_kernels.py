"""The CLSF estimator's per-block computations against independent numpy references written here from their
equations: the period ratios (qmg_lab/clsf/kernels.py), the periods' selection and bookkeeping
(qmg_lab/clsf/periods.py) and the sample buffer's integrals and filter (ClsfEstimator._append).

Floating-point results are compared to derived bounds, never bit for bit: the references sum in another order
(math.fsum, numpy's pairwise sums) and call other code (numpy's exp, scipy's filters)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import signal

from qmg_lab.clsf.demod_filter import DemodFilter
from qmg_lab.clsf.estimator import BUF_MF, BUF_MR, BUF_T, BUF_Y, ClsfEstimator
from qmg_lab.clsf.kernels import period_ratios
from qmg_lab.clsf.periods import complete_periods, evaluate_periods

RNG = np.random.default_rng(20131)
EPS = np.finfo(float).eps
SIGNS = np.array([1.0, -1.0, 1.0, -1.0, 1.0])


def _spread(n: int) -> np.ndarray:
    return RNG.standard_normal(n) * 10.0 ** RNG.uniform(-3.0, 3.0, n)


def _ramp(tau: np.ndarray, order: int, tc: float) -> np.ndarray:
    """R_n(tau) = tau - n tc + tc e^(-tau/tc) sum_(j<n) (n - j) (tau/tc)^j / j! for tau > 0, else 0 (the closed form
    of the filter's ramp response; math.factorial, no cut-off of the transient)."""
    tau = np.asarray(tau, dtype=float)
    if tc == 0.0:
        return np.maximum(tau, 0.0)
    x = np.maximum(tau, 0.0) / tc
    poly = sum((order - j) * x**j / math.factorial(j) for j in range(order))
    return np.where(tau > 0.0, tau - order * tc + tc * np.exp(-x) * poly, 0.0)


def _window_edges(t: np.ndarray, tc: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Three windows k0 <= k < k1 of t and five edges each, anywhere: before the window, inside it, on a sample,
    after it."""
    k0 = np.array([3, 600, 1200])
    k1 = np.array([300, 900, 1999])
    edges = np.array(
        [
            [t[1] - 1e-5, t[100], t[150] + 1e-4, t[299] + 2e-4, t[400]],
            [t[500], t[650] - 3e-5, t[700], t[800] + tc, t[899]],
            [t[1100], t[1300] + 1e-7, t[1500], t[1700], t[1998] + 1e-3],
        ]
    )
    return k0, k1, edges


def _ratio_and_bound(
    t: np.ndarray, y: np.ndarray, mf: np.ndarray, e: np.ndarray, lo: float, hi: float, order: int, tc: float
) -> tuple[float, float]:
    """rho of one window by period_ratios' equations, its sums correctly rounded (math.fsum), and a bound on the
    difference from any evaluation that rounds each operation and sums in any order.

    Each computed quantity of the chain (H m_d, the means, t', v', the slope, r, the products) carries a relative
    error of a few eps of the magnitudes it is formed from, and a sum of n terms adds n eps times the sum of their
    magnitudes. The numerator and the denominator then differ from the exact ones by at most
    c n eps sum_k |a_k| (|v'_k| + |b| (|t'_k| + |mean t|) + |mean v|) with a_k = y_k or (H m)_k: the magnitudes
    that enter r_k and its product. c = 8 covers the ramps' exp and polynomial (4 eps of |tau| + 2 n tc each), the
    means, the slope and the product; relative to |num| and |den| this bounds rho's relative error."""
    n = t.size
    md = lo * (t - e[0] - order * tc) + (hi - lo) * sum(
        s * _ramp(t - ej, order, tc) for s, ej in zip(SIGNS, e, strict=True)
    )
    mt, mv = math.fsum(t) / n, math.fsum(md) / n
    tcen, vcen = t - mt, md - mv
    stt = math.fsum(tcen * tcen)
    slope = math.fsum(tcen * vcen) / stt if stt > 0 else 0.0
    r = vcen - slope * tcen
    hm = mf + md
    num, den = math.fsum(y * r), math.fsum(hm * r)
    size = np.abs(vcen) + abs(slope) * (np.abs(tcen) + abs(mt)) + abs(mv) + (hi - lo) * 2 * order * tc
    err_num = 8 * n * EPS * float(np.sum(np.abs(y) * size))
    err_den = 8 * n * EPS * float(np.sum(np.abs(hm) * size))
    rho = num / den
    return rho, abs(rho) * (err_num / abs(num) + err_den / abs(den))


@pytest.mark.parametrize(("order", "tc"), [(1, 1e-4), (4, 1e-3), (8, 1e-3), (1, 0.0)])
def test_period_ratios_are_their_equations(order: int, tc: float) -> None:
    t = 12.0 + np.arange(2000) / 1800.0
    k0, k1, edges = _window_edges(t, tc)
    y = np.cumsum(_spread(t.size))
    mf = np.cumsum(_spread(t.size))
    got = period_ratios(t, y, mf, edges, k0, k1, -0.3, 0.29, order, tc)
    for p, (a, b) in enumerate(zip(k0, k1, strict=True)):
        rho, bound = _ratio_and_bound(t[a:b], y[a:b], mf[a:b], edges[p], -0.3, 0.29, order, tc)
        assert abs(got[p] - rho) <= bound, (p, got[p], rho, bound)
        assert bound < 1e-6 * abs(rho)  # the bound itself is tight enough to mean something


def test_period_ratio_is_the_gain_of_a_signal_that_follows_the_forcer_input() -> None:
    # y = beta H m + a + b t with H m_r = 0: the line is projected out and rho = beta, to the rounding bound
    t = np.arange(2000) / 1800.0
    k0, k1, edges = _window_edges(t, 1e-4)
    lo, hi, beta = -0.3, 0.3, 0.0137
    hm = np.zeros(t.size)
    for a, b, e in zip(k0, k1, edges, strict=True):
        ramps = sum(s * _ramp(t[a:b] - ej, 1, 1e-4) for s, ej in zip(SIGNS, e, strict=True))
        hm[a:b] = lo * (t[a:b] - e[0] - 1e-4) + (hi - lo) * ramps
    y = beta * hm + 0.02 - 0.5 * t
    got = period_ratios(t, y, np.zeros(t.size), edges, k0, k1, lo, hi, 1, 1e-4)
    for p, (a, b) in enumerate(zip(k0, k1, strict=True)):
        _, bound = _ratio_and_bound(t[a:b], y[a:b], np.zeros(b - a), edges[p], lo, hi, 1, 1e-4)
        assert abs(got[p] - beta) <= bound + 2 * EPS * beta  # plus the rounding of beta H m itself


Row = tuple[tuple[float, ...], int, int]


def _complete_periods_loop(
    rising: np.ndarray, falling: np.ndarray, t: np.ndarray, delay: float, min_samples: int
) -> tuple[int, list[Row]]:
    """complete_periods' docstring as a loop over the periods."""
    done = -1
    rows: list[Row] = []
    for i in range(1, rising.size - 1):
        r_prev, r0, r1 = rising[i - 1], rising[i], rising[i + 1]
        if r1 + delay > t[-1]:
            continue
        done = i
        inside = falling[(falling > r_prev) & (falling < r1)]
        if inside.size != 2 or not (inside[0] < r0 < inside[1]) or r0 + delay < t[0]:
            continue
        a, b = np.searchsorted(t, r0 + delay), np.searchsorted(t, r1 + delay)
        if b - a >= min_samples:
            rows.append(((r_prev, inside[0], r0, inside[1], r1), int(a), int(b)))
    return done, rows


def test_complete_periods_are_the_usable_windows() -> None:
    t = 3.0 + np.arange(2 * 1800) / 1800.0
    period = 1.0 / 7.0003
    rising = 2.95 + period * np.arange(16)
    falling = rising + 0.5 * period + 1e-4
    falling = np.delete(falling, 6)  # a period without its falling edge
    falling = np.sort(np.append(falling, rising[9] + 0.1 * period))  # and one with three
    w = complete_periods(rising, falling, t, 2e-4 * 2, 8)
    done, rows = _complete_periods_loop(rising, falling, t, 2e-4 * 2, 8)
    assert w.done == done
    assert [(tuple(e), a, b) for e, a, b in zip(w.edges, w.k0, w.k1, strict=True)] == rows  # selections: exact
    assert 5 < len(rows) < done - 2  # some periods usable, some not
    empty = complete_periods(rising[:2], falling, t, 0.0, 8)
    assert empty.done == -1 and empty.edges.shape == (0, 5)


def test_evaluate_periods_keeps_the_finite_unheld_periods_and_says_what_is_still_needed() -> None:
    t = 3.0 + np.arange(2 * 1800) / 1800.0
    period = 1.0 / 7.0003
    rising = 3.0013 + period * np.arange(14)
    falling = rising + 0.5 * period + 1e-4
    rate_v, offset_vs = 0.3217, 5.0
    rows = np.stack((t, np.cumsum(_spread(t.size)), np.cumsum(_spread(t.size)), offset_vs + rate_v * t))
    rows[1, 1000] = np.nan  # the period around sample 1000 has no finite rho
    order, tc, lo, hi = 2, 2e-4, -0.3, 0.3
    holds = np.array([[rising[5] + 0.01, rising[5] + 0.02], [rising[9] - 0.01, rising[9] + 0.001]])
    res = evaluate_periods(rising, falling, rows, (lo, hi), order, tc, 8, holds)
    w = complete_periods(rising, falling, t, order * tc, 8)
    rho = period_ratios(t, rows[1], rows[2], w.edges, w.k0, w.k1, lo, hi, order, tc)
    held = np.zeros(w.edges.shape[0], dtype=bool)
    for h0, h1 in holds:
        held |= (h0 <= w.edges[:, 4]) & (w.edges[:, 2] <= h1)
    ok = np.isfinite(rho) & ~held
    assert (res.done, res.usable) == (w.done, w.edges.shape[0])
    assert res.usable > ok.sum() + 2 > 2  # some periods held, one not finite, others kept
    r0, r1, kept_rho, rate = res.kept
    np.testing.assert_array_equal(r0, w.edges[ok, 2])  # selections of the same numbers: exact
    np.testing.assert_array_equal(r1, w.edges[ok, 4])
    np.testing.assert_array_equal(kept_rho, rho[ok])  # the same kernel on the same rows: the same numbers
    # m_r = offset + rate t: the mean rate output over any period is the rate, to the roundings of interpolating
    # two values near offset + rate t (a few eps of them) divided by a period's length
    mag = offset_vs + rate_v * t[-1]
    assert np.all(np.abs(rate - rate_v) <= 8 * EPS * mag / period)
    # still needed: falling edges after R_done, samples from two before R_(done+1) + D
    np.testing.assert_array_equal(res.falling_needed, falling[falling > rising[res.done]])
    assert res.first_needed == np.searchsorted(t, rising[res.done + 1] + order * tc) - 2


@pytest.mark.parametrize(
    ("order", "window"), [(0, 0.0), (1, 2.5e-6), (2, 0.0), (3, 1e-4), (4, 2.5e-6), (5, 0.0), (8, 1e-4)]
)
def test_the_buffer_is_the_trapezoid_integrals_and_the_filtered_rate_integral(order: int, window: float) -> None:
    """ClsfEstimator._append (kernels.integrate_block) over blocks of several sizes against the whole record done
    at once in numpy: the
    trapezoid integrals (module docstring of qmg_lab/clsf/estimator.py) as np.cumsum, the filter as scipy's sosfilt
    from the state at rest. Bound: each running sum's terms are rounded within eps of their size and a sum of k
    terms adds k eps sum |terms|, so at sample k both differ by at most 2 k eps sum_(i<=k) |term_i|; the filter is
    a stable linear map whose output moves by at most its l1 gain sum |h| times that (taken <= 4 for these
    FOH sections: their step responses do not overshoot), plus its own roundings (a few eps of the output times
    the number of samples its memory spans, within the same margin)."""
    n, tau = 5000, 173.6
    t = 50.0 + np.arange(n) / 1800.0  # a steady stream: one filter design (a new sample interval redesigns it)
    x, aux = RNG.standard_normal(n), 0.3 + 0.01 * RNG.standard_normal(n)
    filt = DemodFilter(max(order, 1), 3e-4 if order else 0.0)
    est = ClsfEstimator(tau_s=tau)
    est.set_stream_timing(filt, window)
    for a, b in ((0, 3), (3, 900), (900, 901), (901, 902), (902, 4000), (4000, n)):
        est._append(t[a:b], x[a:b], aux[a:b])
    buf = est._buf[:, est._lo : est._n]
    h = np.diff(np.concatenate(([t[0]], t)))  # the first block repeats its first sample: h_0 = 0
    shift = np.divide(0.5 * window, h, out=np.zeros(n), where=h > 0)
    x_prev, a_prev = np.concatenate(([x[0]], x[:-1])), np.concatenate(([aux[0]], aux[:-1]))
    dx = 0.5 * h * (x + x_prev)
    dm = h * (0.5 * (aux + a_prev) + (aux - a_prev) * shift)
    ix, mr = np.cumsum(dx), np.cumsum(dm)
    k = np.arange(1, n + 1)
    bound_ix = 2 * k * EPS * np.cumsum(np.abs(dx))
    bound_mr = 2 * k * EPS * np.cumsum(np.abs(dm))
    np.testing.assert_array_equal(buf[BUF_T], t)  # the times as given
    assert np.all(np.abs(buf[BUF_MR] - mr) <= bound_mr)
    assert np.all(np.abs(buf[BUF_Y] - (x + ix / tau)) <= bound_ix / tau + 2 * EPS * np.abs(x + ix / tau))
    if order == 0:
        np.testing.assert_array_equal(buf[BUF_MF], buf[BUF_MR])  # no filter: the same array's values
        return
    assert est._sos_dt == pytest.approx(1 / 1800.0, rel=1e-9)  # one design, at the stream's sample interval
    sos = filt.foh_sos(est._sos_dt)
    mf = signal.sosfilt(sos, mr, zi=signal.sosfilt_zi(sos) * mr[0])[0]
    assert np.all(np.abs(buf[BUF_MF] - mf) <= 4 * (bound_mr + 16 * EPS * np.abs(mr)))
