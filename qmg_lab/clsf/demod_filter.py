"""The lock-in's demodulator low-pass filter, as the host must model it to compare c_y with recorded signals.

The HF2's demodulator filter is a cascade of `order` identical first-order sections of time constant tc
(orders 1-8, 6 dB/octave each; the time constant is set per stage):

    H(s) = 1 / (1 + s tc)^n.

Two exact forms are needed by the CLSF estimator (qmg_lab/clsf/estimator.py):

* The response to a ramp that starts at tau = 0 (unit slope), for inputs that are piecewise linear with
  breakpoints anywhere in time (the integral of the dither square wave, whose edges fall between samples):

      R_n(tau) = tau - n tc + tc e^(-tau/tc) sum_{j<n} (n - j) (tau/tc)^j / j!      (tau >= 0).

  Its steady state tau - n tc is the filter's group delay n tc at low frequency (evaluated by
  qmg_lab/clsf/kernels.ramp_response, inside the estimator's compiled loop).
* A discrete filter for inputs known only at the sample instants and linear between them (first-order hold):
  the exact FOH discretization of the state-space chain, as second-order sections (the layout of
  scipy.signal.sosfilt; run by qmg_lab/clsf/kernels.sosfilt), in closed form with numpy alone (see
  DemodFilter.foh_sos), and the sections' steady state for a constant input (sos_steady_state).

tc = 0 means no filter (H = 1).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class DemodFilter:
    """H(s) = 1/(1 + s tc)^order; order 1-8, tc >= 0 s (0: no filter)."""

    order: int = 1
    tc_s: float = 0.0

    def __post_init__(self) -> None:
        if not 1 <= int(self.order) <= 8:
            raise ValueError(f"demodulator filter order {self.order!r} must be 1..8")
        if not (math.isfinite(self.tc_s) and self.tc_s >= 0.0):
            raise ValueError(f"demodulator filter time constant {self.tc_s!r} s must be >= 0")

    @property
    def delay_s(self) -> float:
        """Low-frequency group delay n tc, s."""
        return self.order * self.tc_s

    def gain(self, f_hz: float | np.ndarray) -> np.ndarray:
        """|H(j 2 pi f)| = (1 + (2 pi f tc)^2)^(-n/2)."""
        w = 2 * np.pi * np.asarray(f_hz, dtype=float) * self.tc_s
        return (1.0 + w * w) ** (-0.5 * self.order)

    def bandwidth_3db_hz(self) -> float:
        """f_3dB = sqrt(2^(1/n) - 1) / (2 pi tc) (inf without a filter)."""
        if self.tc_s == 0.0:
            return math.inf
        return math.sqrt(2.0 ** (1.0 / self.order) - 1.0) / (2 * math.pi * self.tc_s)

    def foh_sos(self, dt_s: float) -> np.ndarray | None:
        """Second-order sections of the exact first-order-hold discretization at step dt_s (None: no filter).

        The chain's state space: x' = A x + B u, y = x_n, with A = (N - I)/tc (N the subdiagonal shift),
        B = e_1/tc. With a = dt/tc and p = e^(-a), the FOH equivalent (the block-matrix exponential of
        scipy.signal.cont2discrete(method="foh")) is, in closed form (foh_state_space):

            Ad = p E,  E = e^(a N) = sum_(j<n) a^j N^j / j!   (lower-triangular Toeplitz),
            bd = F + Ad G,  dd = G_(n-1),  F_j = int_0^1 e^(A dt s) B dt s ds,  G_j = int_0^1 e^(A dt s) B dt (1-s) ds.

        With M = E - I (nilpotent), (zI - Ad)^-1 = sum_(m<n) p^m M^m / (z - p)^(m+1), so

            H(z) = dd + sum_(m<n) p^m g_m / (z - p)^(m+1),  g_m = e_n' M^m bd,

        exactly: n poles at p (placed exactly, where a numerical design scatters a repeated pole by eps^(1/n)), and
        the zeros at z = p + w for the roots w of dd w^n + sum_m p^m g_m w^(n-1-m) (every coefficient positive,
        so no cancellation). Sections: the gain dd in the first; complex zeros in conjugate pairs, real zeros in
        ascending pairs, each over (z - p)^2; an odd order ends with a first-order section (zero coefficients
        padded)."""
        if self.tc_s == 0.0:
            return None
        n = self.order
        a = dt_s / self.tc_s
        if not (math.isfinite(a) and a > 0.0):
            raise ValueError(f"sample interval {dt_s!r} s must be > 0")
        p, e_col, f, g = foh_state_space(n, a)
        bd = f + p * _toeplitz_times(e_col, g)
        dd = float(g[n - 1])
        m_col = e_col.copy()
        m_col[0] = 0.0  # M = E - I
        coeffs = [dd]
        v = bd
        for m in range(n):  # g_m = e_n' M^m bd
            coeffs.append(p**m * float(v[n - 1]))
            v = _toeplitz_times(m_col, v)
        zeros = p + np.roots(np.asarray(coeffs))
        return _sections(zeros, p, dd)


def foh_state_space(order: int, a: float) -> tuple[float, np.ndarray, np.ndarray, np.ndarray]:
    """(p, E's first column, F, G) of the chain's FOH discretization at a = dt/tc (DemodFilter.foh_sos).

    e^(A dt s) B dt = a e^(-a s) sum_j (a s)^j / j! e_(j+1), so with P(k, a) = e^(-a) sum_(i>=k) a^i / i! (the
    regularized lower incomplete gamma function):

        F_j = int_0^1 ... s ds     = e^(-a) sum_(i>j) a^i / i! (j + 1)/(i + 1),
        G_j = int_0^1 ... (1-s) ds = e^(-a) sum_(i>j) a^i / i! (i - j)/(i + 1),

    series of positive terms, summed until the terms stop counting (a <= 700; beyond, e^(-a) = 0 to double
    precision and P = 1: F_j = (j + 1)/a, G_j = 1 - (j + 1)/a)."""
    n = int(order)
    j = np.arange(n, dtype=float)
    fact = np.cumprod(np.concatenate(([1.0], np.arange(1.0, n))))
    e_col = a**j / fact
    if a > 700.0:
        return 0.0, e_col, (j + 1.0) / a, 1.0 - (j + 1.0) / a
    f = np.zeros(n)
    g = np.zeros(n)
    term = math.exp(-a)  # e^(-a) a^i / i!, i = 0
    i = 0
    while True:
        i += 1
        term *= a / i
        k = j < i  # the sums over i > j
        f[k] += term * (j[k] + 1.0) / (i + 1.0)
        g[k] += term * (i - j[k]) / (i + 1.0)
        if i > a + n and term < 1e-18 * min(f[n - 1], g[n - 1]):
            break
    return math.exp(-a), e_col, f, g


def _toeplitz_times(col: np.ndarray, v: np.ndarray) -> np.ndarray:
    """T v for the lower-triangular Toeplitz matrix T of first column col: (T v)_i = sum_(k<=i) col_(i-k) v_k."""
    return np.convolve(col, v)[: v.shape[0]]


def _sections(zeros: np.ndarray, pole: float, gain: float) -> np.ndarray:
    """Sections b(z)/a(z) of gain * prod(z - zeros) / (z - pole)^len(zeros), rows [b0 b1 b2 1 a1 a2]."""
    real = np.sort(zeros[np.abs(zeros.imag) <= 1e-12 * np.maximum(1.0, np.abs(zeros))].real)
    upper = zeros[zeros.imag > 1e-12 * np.maximum(1.0, np.abs(zeros))]  # one of each conjugate pair
    quads = [[1.0, -2.0 * z.real, abs(z) ** 2] for z in upper]
    quads += [[1.0, -(real[k] + real[k + 1]), real[k] * real[k + 1]] for k in range(0, real.size - 1, 2)]
    rows = [[*q, 1.0, -2.0 * pole, pole * pole] for q in quads]
    if real.size % 2:
        rows.append([1.0, -float(real[-1]), 0.0, 1.0, -pole, 0.0])
    sos = np.array(rows)
    sos[0, :3] *= gain
    return sos


def sos_steady_state(sos: np.ndarray) -> np.ndarray:
    """The sections' states (n_sections x 2) at rest under a unit constant input (scipy.signal.sosfilt_zi).

    Section s, transposed direct form II (y = b0 u + z0; z0 <- b1 u - a1 y + z1; z1 <- b2 u - a2 y), with its
    input u and its DC gain k = (b0 + b1 + b2)/(1 + a1 + a2), output y = k u: z1 = (b2 - a2 k) u and
    z0 = (b1 + b2 - (a1 + a2) k) u; u is the product of the DC gains of the sections before it."""
    zi = np.empty((sos.shape[0], 2))
    u = 1.0
    for s, (b0, b1, b2, _, a1, a2) in enumerate(sos):
        k = (b0 + b1 + b2) / (1.0 + a1 + a2)
        zi[s, 0] = (b1 + b2 - (a1 + a2) * k) * u
        zi[s, 1] = (b2 - a2 * k) * u
        u *= k
    return zi
