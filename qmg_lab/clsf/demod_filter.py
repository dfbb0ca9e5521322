"""The lock-in's demodulator low-pass filter, as the host must model it to compare c_y with recorded signals.

The HF2's demodulator filter is a cascade of `order` identical first-order sections of time constant tc
(orders 1-8, 6 dB/octave each; the time constant is set per stage):

    H(s) = 1 / (1 + s tc)^n.

Two exact forms are needed by the CLSF estimator (qmg_lab/clsf/estimator.py):

* The response to a ramp that starts at tau = 0 (unit slope), for inputs that are piecewise linear with
  breakpoints anywhere in time (the integral of the dither square wave, whose edges fall between samples):

      R_n(tau) = tau - n tc + tc e^(-tau/tc) sum_{j<n} (n - j) (tau/tc)^j / j!      (tau >= 0).

  Its steady state tau - n tc is the filter's group delay n tc at low frequency.
* A discrete filter for inputs known only at the sample instants and linear between them (first-order hold):
  the exact FOH discretization of the state-space chain, as second-order sections for scipy.signal.sosfilt.

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

    def ramp_response(self, tau: np.ndarray) -> np.ndarray:
        """R_n(tau) for tau >= 0 (0 for tau < 0): the output for a unit-slope ramp input starting at tau = 0.

        The transient term is evaluated only for tau < 60 tc: beyond, it is below 1e-17 tc for n <= 8."""
        tau = np.asarray(tau, dtype=float)
        if self.tc_s == 0.0:
            return np.maximum(tau, 0.0)
        n, tc = self.order, self.tc_s
        out = np.where(tau > 0.0, tau - n * tc, 0.0)
        near = (tau > 0.0) & (tau < 60.0 * tc)
        x = tau[near] / tc
        acc = np.zeros_like(x)
        term = np.ones_like(x)  # x^j / j!
        for j in range(n):
            acc += (n - j) * term
            term = term * x / (j + 1)
        out[near] += tc * np.exp(-x) * acc
        return out

    def foh_sos(self, dt_s: float) -> np.ndarray | None:
        """Second-order sections of the exact first-order-hold discretization at step dt_s (None: no filter).

        State space of the chain: x' = A x + B u, A = (-I + subdiagonal ones)/tc, B = e_1/tc, y = x_n."""
        if self.tc_s == 0.0:
            return None
        from scipy import signal  # imported here: scipy.signal takes ~0.9 s to import, and `check` needs none of it

        n, tc = self.order, self.tc_s
        a = (-np.eye(n) + np.eye(n, k=-1)) / tc
        b = np.zeros((n, 1))
        b[0, 0] = 1.0 / tc
        c = np.zeros((1, n))
        c[0, -1] = 1.0
        ad, bd, cd, dd, _ = signal.cont2discrete((a, b, c, np.zeros((1, 1))), dt_s, method="foh")
        z, p, k = signal.ss2zpk(ad, bd, cd, dd)
        return signal.zpk2sos(z, p, k)
