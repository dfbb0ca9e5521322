"""The CLSF estimator's compiled kernels (qmg_lab/clsf/kernels.py) against the numpy and scipy forms they replace.

Each kernel promises the same operations in the same order as a vectorised form, so the comparisons are exact
(bit for bit), on data spread over six decades so that any change of summation order would show. The line fits
are checked against the least-squares equations as well.
"""

from __future__ import annotations

from fractions import Fraction

import numpy as np
import pytest
from scipy import signal

from qmg_lab.clsf import kernels
from qmg_lab.clsf.demod_filter import DemodFilter, sos_steady_state

RNG = np.random.default_rng(20131)


def _spread(n: int) -> np.ndarray:
    return RNG.standard_normal(n) * 10.0 ** RNG.uniform(-3.0, 3.0, n)


def test_pairwise_sum_is_numpys_sum_bit_for_bit() -> None:
    # below 8 terms, one block (<= 128 terms), and one to ten levels of halving
    work = kernels.pairwise_workspace()
    for n in [*range(0, 300), 463, 464, 465, 911, 912, 913, 1807, 1808, 1809, 3600, 100_003]:
        a = _spread(n + 5)
        assert kernels.pairwise_sum(a, 5, n, work) == np.sum(a[5 : 5 + n]), n


def test_reduceat_sum_is_numpys_reduceat_bit_for_bit() -> None:
    a = _spread(4000)
    starts = np.array([0, 1, 9, 137, 394, 651, 1900, 3999])
    expected = np.add.reduceat(a, starts)
    ends = np.append(starts[1:], a.size)
    work = kernels.pairwise_workspace()
    got = [kernels.reduceat_sum(a, int(s), int(e - s), work) for s, e in zip(starts, ends, strict=True)]
    np.testing.assert_array_equal(got, expected)


@pytest.mark.parametrize("count", [2, 3, 64, 65, 300])
def test_median_spacing_is_the_median_of_the_first_spacings(count: int) -> None:
    t = np.cumsum(RNG.uniform(0.5, 1.5, 300)) / 1800.0
    assert kernels.median_spacing(t[:count], 65) == np.median(np.diff(t[:count][:65]))


@pytest.mark.parametrize("order", [1, 2, 3, 4, 5, 8])
def test_sosfilt_inplace_is_scipys_sosfilt_bit_for_bit(order: int) -> None:
    sos = DemodFilter(order, 3e-4).foh_sos(1 / 1800)
    x = np.cumsum(_spread(3600))
    zi0 = signal.sosfilt_zi(sos) * x[0]
    expected, zf = signal.sosfilt(sos, x, zi=zi0)
    got, zi = x.copy(), zi0.copy()
    kernels.sosfilt_inplace(sos, got, zi)
    np.testing.assert_array_equal(got, expected)
    np.testing.assert_array_equal(zi, zf)


@pytest.mark.parametrize("count", [1, 2, 3, 64, 65, 300])
def test_median_spacing_after_a_time_is_the_median_of_the_first_spacings(count: int) -> None:
    t = np.cumsum(RNG.uniform(0.5, 1.5, 301)) / 1800.0
    expected = np.median(np.diff(t[: count + 1][:65]))
    assert kernels.median_spacing_after(float(t[0]), t[1 : count + 1], 65) == expected


@pytest.mark.parametrize(("order", "window"), [(0, 0.0), (1, 2.5e-6), (2, 0.0), (3, 1e-4), (4, 2.5e-6), (8, 1e-4)])
def test_integrate_block_is_the_trapezoid_integrals_and_scipys_sosfilt(order: int, window: float) -> None:
    n, offset, tau = 3600, 37, 173.6
    t = 50.0 + np.cumsum(RNG.uniform(0.5, 1.5, n)) / 1800.0
    x, aux = _spread(n), _spread(n)
    for before in ((float(t[0]), float(x[0]), float(aux[0]), 0.0, 0.0), (49.9995, 0.3, -0.2, 1.5, 2.5)):
        t_prev, x_prev, a_prev, ix0, mr0 = before
        h = np.diff(np.concatenate(([t_prev], t)))  # a first block repeats its first sample: h_0 = 0
        shift = np.divide(0.5 * window, h, out=np.zeros(n), where=h > 0)
        ix = ix0 + np.cumsum(0.5 * h * (x + np.concatenate(([x_prev], x[:-1]))))
        a_before = np.concatenate(([a_prev], aux[:-1]))
        mr = mr0 + np.cumsum(h * (0.5 * (aux + a_before) + (aux - a_before) * shift))
        sos = DemodFilter(order, 3e-4).foh_sos(1 / 1800) if order else np.empty((0, 6))
        zi = sos_steady_state(sos)
        mf, zf = signal.sosfilt(sos, mr, zi=zi * mr[0]) if order else (mr, zi)
        buf = np.full((4, n + 2 * offset), np.nan)
        ix_end = kernels.integrate_block(t, x, aux, before, window, tau, sos, zi, True, buf, offset)
        np.testing.assert_array_equal(buf[:, offset : offset + n], [t, x + ix / tau, mf, mr])
        np.testing.assert_array_equal(zi, zf)  # the sections' states at the block's end
        assert ix_end == ix[-1]
        assert np.isnan(buf[:, :offset]).all() and np.isnan(buf[:, offset + n :]).all()
        # the next block continues the same states (zi_per_unit False)
        more = np.full((4, n), np.nan)
        kernels.integrate_block(
            t + 2.0, x, aux, (t[-1], x[-1], aux[-1], ix[-1], mr[-1]), window, tau, sos, zi, False, more, 0
        )
        if order:
            np.testing.assert_array_equal(more[2], signal.sosfilt(sos, more[3], zi=zf)[0])


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


@pytest.mark.parametrize(("order", "tc"), [(1, 1e-4), (4, 1e-3), (8, 1e-3), (1, 0.0)])
def test_ramp_column_is_the_filters_ramp_response(order: int, tc: float) -> None:
    t = np.arange(2000) / 1800.0
    k0, k1, edges = _window_edges(t, tc)
    filt = DemodFilter(order, tc)
    for a, b, row in zip(k0, k1, edges, strict=True):
        for e in row:
            got = np.full(b - a + 3, np.nan)
            kernels.ramp_column(t[a:b], e, order, tc, got)
            # Both forms evaluate R_n(tau) = tau - n tc + tc e^(-tau/tc) acc with acc <= n e^(tau/tc), so every term
            # is at most |tau| + n tc in size. Each side's exp is within 1 ulp (numpy's own SIMD exp need not be
            # the C library's), and the sum takes three roundings: 4 eps times that magnitude bounds the difference.
            tau = t[a:b] - e
            bound = 4 * np.finfo(float).eps * (np.abs(tau) + 2 * order * tc)
            assert np.all(np.abs(got[: b - a] - filt.ramp_response(tau)) <= bound)
            assert np.isnan(got[b - a :]).all()  # nothing written beyond the window


def _exact_signed_sum(r: np.ndarray, step: float) -> float:
    """signed_ramp_sum's definition in exact rational arithmetic: each rounding written out (round = float())."""
    p = [float(Fraction(x) * Fraction(s * step)) for x, s in zip(r[:4], (1.0, -1.0, 1.0, -1.0), strict=True)]
    inner = (p[0] + p[2]) + (p[1] + p[3])
    return float(Fraction(r[4]) * Fraction(step) + Fraction(inner))  # the fused multiply-add: one rounding


def test_signed_ramp_sum_rounds_as_defined_and_as_a_matrix_vector_product() -> None:
    rows = _spread(5 * 4000).reshape(4000, 5)
    rows[RNG.random(rows.shape) < 0.2] = 0.0  # ramps that have not started
    step = 0.6123456789
    got = np.array([kernels.signed_ramp_sum(*r, step) for r in rows])
    np.testing.assert_array_equal(got, [_exact_signed_sum(r, step) for r in rows])
    # any BLAS's order of the same five products is within a few roundings of their magnitude
    product = rows @ (np.array([1.0, -1.0, 1.0, -1.0, 1.0]) * step)
    magnitude = np.abs(rows) @ np.full(5, step)
    assert np.all(np.abs(got - product) <= 4 * np.finfo(float).eps * magnitude)


def _ratios_by_equations(
    rows: tuple[np.ndarray, np.ndarray, np.ndarray],
    edges: np.ndarray,
    windows: tuple[np.ndarray, np.ndarray],
    levels: tuple[float, float],
    filt: DemodFilter,
) -> np.ndarray:
    """period_ratios' docstring in numpy, window by window (its sums are np.add.reduceat's); rows: t, y, H m_r."""
    t, y, mf = rows
    k0, k1 = windows
    lo, hi = levels
    rho = []
    for a, b, e in zip(k0, k1, edges, strict=True):
        ramps = np.stack([filt.ramp_response(t[a:b] - ej) for ej in e], axis=1)
        md = lo * (t[a:b] - e[0] - filt.delay_s) + np.array([_exact_signed_sum(r, hi - lo) for r in ramps])
        tc = t[a:b] - np.add.reduceat(t[a:b], [0])[0] / (b - a)
        vc = md - np.add.reduceat(md, [0])[0] / (b - a)
        stt = np.add.reduceat(tc * tc, [0])[0]
        slope = np.add.reduceat(tc * vc, [0])[0] / stt if stt > 0 else 0.0
        r = vc - tc * slope
        den = np.add.reduceat((mf[a:b] + md) * r, [0])[0]
        rho.append(np.add.reduceat(y[a:b] * r, [0])[0] / den if den != 0.0 else np.nan)
    return np.array(rho)


@pytest.mark.parametrize(("order", "tc"), [(1, 1e-4), (4, 1e-3), (8, 1e-3), (1, 0.0)])
def test_period_ratios_are_their_equations(order: int, tc: float) -> None:
    t = 12.0 + np.arange(2000) / 1800.0
    k0, k1, edges = _window_edges(t, tc)
    y = np.cumsum(_spread(t.size))
    mf = np.cumsum(_spread(t.size))
    filt = DemodFilter(order, tc)
    got = kernels.period_ratios(t, y, mf, edges, k0, k1, -0.3, 0.29, order, tc)
    np.testing.assert_array_equal(got, _ratios_by_equations((t, y, mf), edges, (k0, k1), (-0.3, 0.29), filt))


def test_period_ratio_is_the_gain_of_a_signal_that_follows_the_forcer_input() -> None:
    # y = beta H m + a + b t with H m_r = 0: the line is projected out and rho = beta (to rounding)
    t = np.arange(2000) / 1800.0
    k0, k1, edges = _window_edges(t, 1e-4)
    lo, hi, beta = -0.3, 0.3, 0.0137
    filt = DemodFilter(1, 1e-4)
    hm = np.zeros(t.size)
    for a, b, e in zip(k0, k1, edges, strict=True):
        ramps = np.stack([filt.ramp_response(t[a:b] - ej) for ej in e], axis=1)
        hm[a:b] = lo * (t[a:b] - e[0] - filt.delay_s) + ramps @ (np.array([1.0, -1.0, 1.0, -1.0, 1.0]) * (hi - lo))
    y = beta * hm + 0.02 - 0.5 * t
    got = kernels.period_ratios(t, y, np.zeros(t.size), edges, k0, k1, lo, hi, 1, 1e-4)
    np.testing.assert_allclose(got, beta, rtol=1e-12)


def test_interp_sorted_is_numpys_interp() -> None:
    xp = np.cumsum(RNG.uniform(1e-4, 1e-3, 500)) + 12.0
    fp = np.cumsum(_spread(500))
    x = np.concatenate((RNG.uniform(xp[0] - 0.01, xp[-1] + 0.01, 200), xp[[0, 1, 250, -1]]))
    got = [kernels.interp_sorted(float(v), xp, fp) for v in x]
    np.testing.assert_array_equal(got, np.interp(x, xp, fp))


def test_line_fits_are_the_least_squares_lines() -> None:
    j = np.arange(40, dtype=float) * 2.0 + np.repeat([0.0, 1.0], 20)  # uneven index steps
    t = 3.0 + 0.142857 * j + 1e-5 * RNG.standard_normal(j.size)
    # line_at: the least-squares line through all pairs, at new indices
    slope, icpt = np.polyfit(j[:32], t[:32], 1)
    at = np.array([j[31] + 1.0, j[31] + 5.0])
    np.testing.assert_allclose(kernels.line_at(t[:32], j[:32], at), icpt + slope * at, rtol=0, atol=1e-12)
    # rolling_line_fit: each point from the 10th on, from the line through it and the (up to) 7 points before
    fit = kernels.rolling_line_fit(t, j, 10, 8)
    for i in range(10, j.size):
        s, c = np.polyfit(j[i - 7 : i + 1], t[i - 7 : i + 1], 1)
        assert fit[i - 10] == pytest.approx(c + s * j[i], abs=1e-12)
    # fewer than 4 points in a window: the point itself
    np.testing.assert_array_equal(kernels.rolling_line_fit(t[:3], j[:3], 0, 8), t[:3])


def test_evaluate_periods_keeps_the_finite_unheld_periods_and_says_what_is_still_needed() -> None:
    t = 3.0 + np.arange(2 * 1800) / 1800.0
    period = 1.0 / 7.0003
    rising = 3.0013 + period * np.arange(14)
    falling = rising + 0.5 * period + 1e-4
    buf = np.stack((t, np.cumsum(_spread(t.size)), np.cumsum(_spread(t.size)), np.cumsum(_spread(t.size))))
    buf[1, 1000] = np.nan  # the period around sample 1000 has no finite rho
    order, tc, lo, hi = 2, 2e-4, -0.3, 0.3
    holds = np.array([[rising[5] + 0.01, rising[5] + 0.02], [rising[9] - 0.01, rising[9] + 0.001]])
    falling_in = falling.copy()  # the kernel moves the falling edges still needed to the front
    padded = np.full((4, t.size + 50), np.nan)  # the samples held are columns 20:20 + n of the buffer
    padded[:, 20 : 20 + t.size] = buf
    done, usable, first_needed, falling_needed, (r0, r1, rho, rate) = kernels.evaluate_periods(
        rising, falling_in, padded, (20, 20 + t.size), lo, hi, order, tc, 8, holds
    )
    # the same from the parts, with the estimator's earlier numpy bookkeeping
    done_p, edges, k0, k1 = kernels.complete_periods(rising, falling, t, order * tc, 8)
    rho_p = kernels.period_ratios(t, buf[1], buf[2], edges, k0, k1, lo, hi, order, tc)
    rate_p = kernels.mean_rates(edges, t, buf[3])
    held = np.zeros(edges.shape[0], dtype=bool)
    for h0, h1 in holds:
        held |= (h0 <= edges[:, 4]) & (edges[:, 2] <= h1)
    ok = np.isfinite(rho_p) & ~held
    assert (done, usable) == (done_p, edges.shape[0])
    assert usable > ok.sum() + 2 > 2  # some periods held, one not finite, others kept
    np.testing.assert_array_equal(r0, edges[ok, 2])
    np.testing.assert_array_equal(r1, edges[ok, 4])
    np.testing.assert_array_equal(rho, rho_p[ok])
    np.testing.assert_array_equal(rate, rate_p[ok])
    # still needed: rising edges from `done` on, falling edges after R_done, samples from two before R_(done+1) + D
    np.testing.assert_array_equal(falling_in[:falling_needed], falling[falling > rising[done]])
    assert first_needed == np.searchsorted(t, rising[done + 1] + order * tc) - 2


def test_period_estimates_are_the_numpy_expressions() -> None:
    rho = 0.0137 * (1.0 + 1e-3 * _spread(500))
    eta, sf_change, gain = kernels.period_estimates(rho, 0.01371, 1.0025)
    np.testing.assert_array_equal(eta, rho / 0.01371 - 1.0)
    np.testing.assert_array_equal(sf_change, 1.0 / (1.0 + (rho / 0.01371 - 1.0)) - 1.0)
    np.testing.assert_array_equal(gain, np.full(rho.size, 1.0025))
