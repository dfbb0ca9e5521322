"""The CLSF estimator's compiled (numba) loops: the per-period ratios rho over the sample buffer, and a block's
integrals run through the demodulator filter's sections.

Everything else of the estimator is numpy (qmg_lab/clsf/estimator.py, qmg_lab/clsf/periods.py,
qmg_lab/clsf/dither_edges.py). The ratios are compiled because each dither period needs the filter's ramp response
at every sample for five edges, its own least-squares line and four sums: about 25 numpy calls per period on
arrays of a few hundred samples, where the call overhead would cost several times the arithmetic (14 periods per
2 s block). The sections are a recursion, which numpy cannot vectorise (scipy.signal.sosfilt would do, but
importing scipy.signal costs a campaign process about 0.4 s of start-up), and the integrals feeding them are two
running sums, formed in the same loop.

Compiled with cache=True (the first run in a fresh environment compiles it once; later runs load it from the cache).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

#: beyond this many time constants the ramp response's transient e^(-x) sum_(j<n) (n - j) x^j / j! is below
#: 1e-17 tc for n <= 8 and is left out
TRANSIENT_TCS = 60.0


@njit(cache=True)
def integrate_block(
    t: np.ndarray,
    x: np.ndarray,
    aux: np.ndarray,
    before: tuple[float, float, float, float, float],
    window_s: float,
    tau_s: float,
    sos: np.ndarray,
    zi: np.ndarray,
    zi_per_unit: bool,
    out: np.ndarray,
) -> float:
    """A block's rows of the estimator's sample buffer into out (4 x n): t, y, H m_r, m_r; returns int x at the
    block's last sample. before: t, x, aux, int x and m_r at the sample before t[0] (for a first block, t[0], x[0],
    aux[0], 0, 0).

    With h_k = t_k - t_(k-1), the trapezoid rule (AuxIn values sit at t_k - W/2, so the line through two readings
    is shifted by s_k = W / (2 h_k), 0 where h_k = 0):
        int x_k = int x_(k-1) + h_k (x_k + x_(k-1)) / 2
        m_r,k   = m_r,(k-1) + h_k ((a_k + a_(k-1)) / 2 + (a_k - a_(k-1)) s_k)
        y_k     = x_k + int x_k / tau
    H m_r: m_r through the second-order sections sos (rows b0 b1 b2 1 a1 a2; none: H m_r = m_r) from their states
    zi (n_sections x 2, updated in place; zi_per_unit: zi holds the states at rest per unit input, and starts at
    those times the first m_r), each section over the block in transposed direct form II (scipy.signal.sosfilt's
    recursion): y = b0 u + z0; z0 <- b1 u - a1 y + z1; z1 <- b2 u - a2 y."""
    t_prev, x_prev, a_prev, ix, mr = before
    for k in range(t.size):
        h = t[k] - t_prev
        shift = 0.5 * window_s / h if h > 0 else 0.0
        ix += 0.5 * h * (x[k] + x_prev)
        mr += h * (0.5 * (aux[k] + a_prev) + (aux[k] - a_prev) * shift)
        out[0, k] = t[k]
        out[1, k] = x[k] + ix / tau_s
        out[2, k] = mr
        out[3, k] = mr
        t_prev, x_prev, a_prev = t[k], x[k], aux[k]
    if zi_per_unit and t.size:
        zi *= out[3, 0]
    for s in range(sos.shape[0]):
        b0, b1, b2, a1, a2 = sos[s, 0], sos[s, 1], sos[s, 2], sos[s, 4], sos[s, 5]
        z0, z1 = zi[s, 0], zi[s, 1]
        for k in range(t.size):
            u = out[2, k]
            v = b0 * u + z0
            z0 = b1 * u - a1 * v + z1
            z1 = b2 * u - a2 * v
            out[2, k] = v
        zi[s, 0], zi[s, 1] = z0, z1
    return ix


@njit(cache=True)
def _ramp(x: float, order: int, tc_s: float) -> float:
    """R_n at one tau = x (ramp_response)."""
    if x <= 0.0:
        return 0.0
    if tc_s == 0.0:
        return x
    if x >= TRANSIENT_TCS * tc_s:
        return x - order * tc_s
    u = x / tc_s
    acc = 0.0
    term = 1.0  # u^j / j!
    for j in range(order):
        acc += (order - j) * term
        term = term * u / (j + 1)
    return x - order * tc_s + tc_s * math.exp(-u) * acc


@njit(cache=True)
def ramp_response(tau: np.ndarray, order: int, tc_s: float) -> np.ndarray:
    """R_n(tau), the response of H(s) = 1/(1 + s tc)^n to a unit ramp starting at tau = 0 (demod_filter.py):
    tau - n tc + tc e^(-tau/tc) sum_(j<n) (n - j) (tau/tc)^j / j! for 0 < tau < 60 tc, tau - n tc beyond, 0 for
    tau <= 0; max(tau, 0) without a filter (tc = 0)."""
    out = np.empty(tau.size)
    for i in range(tau.size):
        out[i] = _ramp(tau[i], order, tc_s)
    return out


@njit(cache=True)
def period_ratios(
    t: np.ndarray,
    y: np.ndarray,
    mf: np.ndarray,
    edges: np.ndarray,
    k0: np.ndarray,
    k1: np.ndarray,
    lo: float,
    hi: float,
    order: int,
    tc_s: float,
) -> np.ndarray:
    """rho = sum y r / sum (H m) r per period (the estimator's docstring) over its window k0[p] <= k < k1[p] of
    the sample rows t, y, H m_r; edges[p]: the period's (R_(i-1), F_a, R_i, F_b, R_(i+1)); lo, hi: the dither's
    recorded levels; the lock-in's filter 1/(1 + s tc)^order.

    H m_d = lo (t - e_0 - n tc) + (hi - lo) sum_j s_j R_n(t - e_j), signs s = (+, -, +, -, +) (each edge adds a
    ramp of slope +-(hi - lo)); r = H m_d minus its least-squares line a + b t over the window: with means over
    it, t' = t - mean t, v' = H m_d - mean H m_d, b = sum t' v' / sum t'^2 (0 if sum t'^2 = 0), r = v' - b t'.
    H m = H m_r + H m_d. NaN where sum (H m) r = 0. (Three passes over a window, H m_d kept between them.)"""
    rho = np.empty(k0.size)
    step = hi - lo
    longest = 0
    for p in range(k0.size):
        longest = max(longest, k1[p] - k0[p])
    md = np.empty(longest)
    for p in range(k0.size):
        a, n = k0[p], k1[p] - k0[p]
        e = edges[p]
        st = 0.0
        sv = 0.0
        for i in range(n):
            tk = t[a + i]
            ramps = _ramp(tk - e[0], order, tc_s) - _ramp(tk - e[1], order, tc_s) + _ramp(tk - e[2], order, tc_s)
            ramps += _ramp(tk - e[4], order, tc_s) - _ramp(tk - e[3], order, tc_s)
            v = lo * (tk - e[0] - order * tc_s) + step * ramps
            md[i] = v
            st += tk
            sv += v
        mt, mv = st / n, sv / n
        stt = 0.0
        stv = 0.0
        for i in range(n):
            tc = t[a + i] - mt
            stt += tc * tc
            stv += tc * (md[i] - mv)
        slope = stv / stt if stt > 0 else 0.0
        num = 0.0
        den = 0.0
        for i in range(n):
            r = (md[i] - mv) - slope * (t[a + i] - mt)
            num += y[a + i] * r
            den += (mf[a + i] + md[i]) * r
        rho[p] = num / den if den != 0.0 else np.nan
    return rho
