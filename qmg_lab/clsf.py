"""Closed-loop scale factor (CLSF): the host-side estimator and gain controller.

The DS345's square wave V_d is added to the FTR command V_r in front of the forcer, so the sense mode sees the
forcer input u = V_r + V_d through the forcer-path gain G (forcer gain x CLSF gain correction x pickoff gain /
frequency). Under FTR the sense demodulator obeys (reference/physics.md section 2, qmg_lab/loops.py)

    dX/dt = -X/tau + b G u - k R_d Omega,

and the scale factor is SF = SF0 G0/G times the pickoff-ratio drift CLSF cannot see.

Per whole dither period (rising edge to rising edge of the *recorded* dither) the estimator forms

    r   = zero-mean triangle: the integral of the zero-mean recorded square wave (paper eq. 8: Theta_r-mod),
    D_x = sum (X - mean X) r              the raw c_y demodulated against the triangle (the paper's CLSF output),
    m   = the plant's response to the recorded u over the period: m[k+1] = m[k] + dt u[k] (the decay 1/tau
          is left out: over one period it changes rho by a constant ~T/tau that rho_0 cancels, whereas a leaky
          integral restarted each period would give a steady rate output a curvature the triangle sees),
    D_m = sum (m - mean m) r              the same demodulation of what a plant of gain 1 would have done,

and rho = D_x / D_m estimates b G. Because D_m contains the rate loop's own reaction to the dither (the rate
output is recorded), rho is exactly proportional to G: an estimator that used the dither alone (D_x against a
fixed level) under-reads a gain change by 14 % with a 2 Hz loop and a 7 Hz dither (physics.md section 3). Slow
rates (a linear ramp in m and X over one period) are orthogonal to the symmetric triangle and drop out.

    eta = rho / rho_0 - 1                  (rho_0: mean over the first `reference_periods` periods)
    sf_change_estimate = 1 / (1 + eta) - 1  (SF/SF0 - 1, exact to all orders in the gain change)

Correct mode closes a loop on the forcer-path gain through the lock-in (LockIn.set_forcer_gain):
g_c <- g_c exp(-K_i eta) once per period with K_i = T_d / tau_c (an integrating loop of time constant tau_c);
eta then converges to zero and the FTR scale factor is held at SF0 up to the pickoff-ratio drift.

Periods that overlap a hold window (around commanded table moves) or contain lost samples are not used.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np


@dataclass
class ClsfPeriods:
    """Per-period results of one processed block (arrays of equal length)."""

    time: np.ndarray  # end of each period, s
    eta: np.ndarray
    sf_change_estimate: np.ndarray
    gain_correction: np.ndarray  # the gain in force during the period
    rate_output_mean: np.ndarray  # rate output averaged over the whole period, V (dither-free)

    def __len__(self) -> int:
        return int(self.time.shape[0])

    @classmethod
    def empty(cls) -> ClsfPeriods:
        e = np.empty(0)
        return cls(e, e.copy(), e.copy(), e.copy(), e.copy())


@dataclass
class ClsfEstimator:
    """Streams lock-in samples in, whole-dither-period CLSF estimates out.

    tau_s: the sense mode's decay time (2Q/omega). mode: "observe" | "correct" | "off".
    time_constant_s: correct mode's loop time constant. reference_periods: periods averaged for rho_0.
    """

    tau_s: float
    mode: str = "observe"
    time_constant_s: float = 60.0
    reference_periods: int = 50
    gain_correction: float = 1.0
    rho_ref: float | None = None
    _ref_acc: list[float] = field(default_factory=list)
    _buf_t: np.ndarray = field(default_factory=lambda: np.empty(0))
    _buf_x: np.ndarray = field(default_factory=lambda: np.empty(0))
    _buf_u: np.ndarray = field(default_factory=lambda: np.empty(0))
    _buf_d: np.ndarray = field(default_factory=lambda: np.empty(0))
    _holds: list[tuple[float, float]] = field(default_factory=list)

    def __post_init__(self) -> None:
        if self.mode not in ("observe", "correct", "off"):
            raise ValueError(f"clsf.mode must be observe, correct or off, not {self.mode!r}")
        if self.tau_s <= 0 or self.time_constant_s <= 0:
            raise ValueError("tau_s and time_constant_s must be positive")

    # ------------------------------------------------------------------ control from the campaign
    def hold(self, t_start: float, t_end: float) -> None:
        """Do not use periods overlapping [t_start, t_end] (a commanded table move and its settling)."""
        self._holds.append((t_start, t_end))

    def release_hold(self, t_end: float) -> None:
        """End open-ended holds (a suspension that is over) at t_end."""
        self._holds = [(h0, t_end if math.isinf(h1) else h1) for h0, h1 in self._holds]

    def reset_buffer(self) -> None:
        """Forget partial-period samples (after a gap in the stream)."""
        self._buf_t = self._buf_x = self._buf_u = self._buf_d = np.empty(0)

    @property
    def referenced(self) -> bool:
        return self.rho_ref is not None

    # ------------------------------------------------------------------ processing
    def process(self, time: np.ndarray, x_sense: np.ndarray, rate_output: np.ndarray,
                dither: np.ndarray) -> ClsfPeriods:
        """Add a block of samples; return the estimates of every dither period completed by it.

        All periods of the block are evaluated at once. The gain correction recorded for them is the one in force
        while the block was taken (the lock-in's gain changes between blocks); correct mode then integrates
        their eta into the gain for the next block.
        """
        if self.mode == "off":
            return ClsfPeriods.empty()
        t = np.concatenate((self._buf_t, time))
        x = np.concatenate((self._buf_x, x_sense))
        u = np.concatenate((self._buf_u, rate_output + dither))
        d = np.concatenate((self._buf_d, dither))
        edges = _rising_edges(d)
        if len(edges) < 2:
            keep = edges[0] if len(edges) else max(0, len(t) - 100000)
            self._buf_t, self._buf_x, self._buf_u, self._buf_d = t[keep:], x[keep:], u[keep:], d[keep:]
            return ClsfPeriods.empty()
        first, last = int(edges[0]), int(edges[-1])
        dt = float(np.median(np.diff(t[first:last + 1])))
        rho, rate = _period_gains(x[first:last], u[first:last], d[first:last], edges[:-1] - first, dt)
        t0, t1 = t[edges[:-1]], t[edges[1:] - 1] + dt
        ok = np.isfinite(rho) & ~self._held_mask(t0, t1)
        rho, rate, t1, t0 = rho[ok], rate[ok], t1[ok], t0[ok]
        self._buf_t, self._buf_x, self._buf_u, self._buf_d = t[last:], x[last:], u[last:], d[last:]
        self._holds = [h for h in self._holds if h[1] >= t[last]]
        if self.rho_ref is None:
            need = self.reference_periods - len(self._ref_acc)
            self._ref_acc.extend(rho[:need].tolist())
            rho, rate, t1, t0 = rho[need:], rate[need:], t1[need:], t0[need:]
            if len(self._ref_acc) < self.reference_periods:
                return ClsfPeriods.empty()
            self.rho_ref = float(np.mean(self._ref_acc))
        eta = rho / self.rho_ref - 1.0
        gain = np.full(eta.shape, self.gain_correction)
        if self.mode == "correct" and eta.size:
            self.gain_correction *= math.exp(-float(np.sum((t1 - t0) * eta)) / self.time_constant_s)
        return ClsfPeriods(time=t1, eta=eta, sf_change_estimate=1.0 / (1.0 + eta) - 1.0, gain_correction=gain,
                           rate_output_mean=rate)

    def _held_mask(self, t0: np.ndarray, t1: np.ndarray) -> np.ndarray:
        held = np.zeros(t0.shape, dtype=bool)
        for h0, h1 in self._holds:
            held |= (h0 <= t1) & (t0 <= h1)
        return held


def _rising_edges(d: np.ndarray) -> np.ndarray:
    """Indices k where the recorded square wave crosses its mid-level upward (d[k-1] < mid <= d[k])."""
    if d.size < 3:
        return np.empty(0, dtype=np.int64)
    hi, lo = float(np.max(d)), float(np.min(d))
    if hi - lo <= 1e-9 * max(1.0, abs(hi)):
        return np.empty(0, dtype=np.int64)
    mid = 0.5 * (hi + lo)
    above = d >= mid
    return np.flatnonzero(above[1:] & ~above[:-1]) + 1


def _segment_mean(v: np.ndarray, starts: np.ndarray, lengths: np.ndarray) -> np.ndarray:
    return np.add.reduceat(v, starts) / lengths


def _period_gains(x: np.ndarray, u: np.ndarray, d: np.ndarray, starts: np.ndarray,
                  dt: float) -> tuple[np.ndarray, np.ndarray]:
    """rho = D_x / D_m and the mean rate output of each period [starts[j], starts[j+1]) (the last to the end).

    Per period: r = midpoint-rule integral of the zero-mean recorded square wave, made zero-mean (symmetric about
    the period's centre); m = running integral of the forcer input u = V_r + V_d; D_x = sum x r, D_m = sum m r
    (r is zero-mean, so x's and m's means drop out). Segmented cumulative sums make it one pass for all periods.
    """
    n = x.size
    lengths = np.diff(np.append(starts, n)).astype(np.float64)
    seg = np.repeat(np.arange(starts.size), np.diff(np.append(starts, n)))
    dz = d - _segment_mean(d, starts, lengths)[seg]
    c = np.cumsum(dz)
    r = c - (c[starts] - dz[starts])[seg] - 0.5 * dz
    r -= _segment_mean(r, starts, lengths)[seg]
    udt = u * dt
    mc = np.cumsum(udt)
    m = mc - udt - (mc[starts] - udt[starts])[seg]
    d_x = np.add.reduceat(x * r, starts)
    d_m = np.add.reduceat(m * r, starts)
    with np.errstate(divide="ignore", invalid="ignore"):
        rho = np.where((lengths >= 8) & (d_m != 0.0), d_x / d_m, np.nan)
    rate = _segment_mean(u - d, starts, lengths)
    return rho, rate


def observe_sensitivity(loop_bandwidth_hz: float, dither_hz: float, harmonics: int = 199) -> float:
    """d ln(D_x)/d ln(G) for the paper's plain demodulation (D_x alone), first-order loop, square-wave dither.

    With L = w_bw/s and the n-th odd harmonic of the square wave |Omega_n|^2 ~ 1/n^2,
    D_x(G) ~ sum_n |Omega_n|^2 G / ((n w_d)^2 + (G w_bw)^2), so the sensitivity is
    1 - sum_n w_n 2 w_bw^2 / ((n w_d)^2 + w_bw^2) with weights w_n ~ |Omega_n|^2 / ((n w_d)^2 + w_bw^2).
    Reported for comparison with physics.md (0.856 for 2 Hz / 7 Hz); the estimator above does not need it.
    """
    wb, wd = 2 * math.pi * loop_bandwidth_hz, 2 * math.pi * dither_hz
    n = np.arange(1, 2 * harmonics, 2, dtype=np.float64)
    weight = (1.0 / n**2) / ((n * wd) ** 2 + wb**2)
    return float(1.0 - np.sum(weight * 2 * wb**2 / ((n * wd) ** 2 + wb**2)) / np.sum(weight))
