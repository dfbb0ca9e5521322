"""Closed-loop scale factor (CLSF): the host-side estimator and gain controller.

The DS345's square wave V_d is added to the FTR command V_r in front of the forcer, so the sense mode sees the
forcer input u = V_r + V_d through the forcer-path gain beta (forcer gain x CLSF gain correction x pickoff gain
/ frequency). Under FTR the sense demodulator's in-phase value X (before the lock-in's filter) obeys
(docs/clsf.md)

    dX/dt = -X/tau + beta u - kappa Omega,                                                          (1)

and the scale factor is SF = SF0 beta0/beta times the pickoff-ratio drift CLSF cannot see. Integrating (1) from
any origin, with m(t) = integral of u and Y = X + (1/tau) integral of X:

    Y(t) = beta m(t) + c - kappa integral(Omega),                                                   (2)

exactly, whatever the loops do. The lock-in's filter H(s) = 1/(1 + s tc)^n is linear and commutes with the
integrals, so the recorded, filtered x_s obeys (2) with Y -> y = x_s + (1/tau) integral(x_s) and m -> H m.
Over one dither period the table rate (held steady: periods near table moves are not used) and the gyro bias are
constant to a very good approximation, so the last term of (2) is a straight line a + b t.

The estimator (one value per dither period, between two rising edges of the recorded dither):

* m = m_d + m_r. m_d, the integral of the square wave, is piecewise linear with its kinks at the dither's edges,
  which the host locates from the recorded dither to a fraction of a sample (qmg_lab/clsf/dither_edges.py); H m_d is
  evaluated exactly at the sample instants from the filter's ramp response (qmg_lab/clsf/demod_filter.py), wherever
  the edges fall. m_r, the integral of the rate output, comes from the AuxIn record of the AuxOut (each value the
  mean over the AuxIn window W that ends at its timestamp, i.e. the value at t_k - W/2), integrated with the
  trapezoid rule through those points, and filtered with the exact first-order-hold discretization of H.
* r = the filtered triangle H m_d, made orthogonal to 1 and t over the period's own samples (least squares).
* rho = sum_k y_k r_k / sum_k (H m)_k r_k.

Sensitivity 1 by construction. Insert (2) into rho: y_k = beta (H m)_k + a + b t_k + n_k, and r is orthogonal to
1 and t on exactly the samples summed, so rho = beta + sum n r / sum (H m) r. r is built from the dither alone,
which no noise source of the loop reaches, so E[rho] = beta and d ln E[rho] / d ln beta = 1 exactly: for any
loop bandwidth (the recorded V_r carries the loop's reaction to the dither, and to a gain change), any filter
(H is applied to m as it was to x_s), any table rate (the ramp it puts into m and y is projected out instead of
being left to cancel against a symmetric triangle), and any number of samples per period, integer or not, on
clocks that share nothing. What remains is the model's own approximation: V_r linear between its recorded
points (the AuxOut is smooth at the scale of a sample interval) and Omega constant over a period.

How this differs from the paper. The paper keeps the dither out of the FTR loop with a notch at the dither
frequency in the FTR path, so the rate output carries no dither and X responds to V_d open loop; it then
demodulates the raw c_y against the triangle (its eq. 8). That needs a notch (and its odd harmonics) in the
lock-in's PID path, which the HF2's PIDs do not offer, and a notch adds phase to the 2 Hz loop. Here the loop is
left alone, the dither is partly rebalanced (23 % at 7 Hz with the default 2 Hz loop), and the host divides by
the response of a plant of gain 1 to the recorded forcer input instead. The cost: the estimate needs the rate
output recorded (an AuxOut looped into an AuxIn) and modelled between samples; its noise includes the rate
output's, which is the loop's own noise, correlated with x_s, so the ratio is a little noisier than a
demodulation of c_y alone (`qmg_lab.clsf.estimator.observe_sensitivity` gives the plain demodulation's 14 %
under-reading for comparison).

    eta = rho / rho_0 - 1                  (rho_0: mean over the first `reference_periods` periods)
    sf_change_estimate = 1 / (1 + eta) - 1  (SF/SF0 - 1, exact to all orders in the gain change)

Correct mode closes a loop on the forcer-path gain through the lock-in (LockIn.set_forcer_gain):
g_c <- g_c exp(-K_i eta) once per period with K_i = T_d / tau_c (an integrating loop of time constant tau_c);
eta then converges to zero and the FTR scale factor is held at SF0 up to the pickoff-ratio drift.

Periods that overlap a hold window (around commanded table moves) or a gap in the stream are not used.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from qmg_lab.clsf.demod_filter import DemodFilter, sos_steady_state
from qmg_lab.clsf.dither_edges import EdgeTracker
from qmg_lab.clsf.kernels import integrate_block
from qmg_lab.clsf.periods import evaluate_periods

MIN_PERIOD_SAMPLES = 8  # a period's window needs at least this many samples
MAX_HELD_SAMPLES = 100_000  # samples kept while no edge has been found
BUF_T, BUF_Y, BUF_MF, BUF_MR = range(4)  # the rows of the sample buffer (ClsfEstimator._append)
SPACING_SAMPLES = 65  # the sample interval is the median of (at most) this many first spacings of a block
NO_SECTIONS = np.empty((0, 6))  # the filter's sections when there is no filter (tc = 0)
NO_HOLDS = np.empty((0, 2))


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
    demod_filter: the lock-in's filter on x_s (order, time constant), as applied (read back from the lock-in).
    auxin_window_s: the AuxIn averaging window W that ends at each sample's timestamp.
    dither_min_step_v: the smallest recorded level step taken for the running dither (half the DS345's Vpp in a
    campaign), so that the AuxIn's noise on a dither that is not running never makes edges.
    """

    tau_s: float
    mode: str = "observe"
    time_constant_s: float = 60.0
    reference_periods: int = 50
    gain_correction: float = 1.0
    rho_ref: float | None = None
    demod_filter: DemodFilter = field(default_factory=DemodFilter)
    auxin_window_s: float = 0.0
    dither_min_step_v: float = 0.0  # a recorded dither step smaller than this is noise, not a running dither
    _ref_acc: list[float] = field(default_factory=list)
    _holds: list[tuple[float, float]] = field(default_factory=list)

    def __post_init__(self) -> None:
        if self.mode not in ("observe", "correct", "off"):
            raise ValueError(f"clsf.mode must be observe, correct or off, not {self.mode!r}")
        if self.tau_s <= 0 or self.time_constant_s <= 0:
            raise ValueError("tau_s and time_constant_s must be positive")
        self.set_stream_timing(self.demod_filter, self.auxin_window_s)

    # ------------------------------------------------------------------ control from the campaign
    def hold(self, t_start: float, t_end: float) -> None:
        """Do not use periods overlapping [t_start, t_end] (a commanded table move and its settling)."""
        self._holds.append((t_start, t_end))

    def release_hold(self, t_end: float) -> None:
        """End open-ended holds (a suspension that is over) at t_end."""
        self._holds = [(h0, t_end if math.isinf(h1) else h1) for h0, h1 in self._holds]

    def reset_buffer(self) -> None:
        """Forget the stream's history (after a gap): integrals, filter state, edges and partial periods."""
        self._buf = np.empty((4, 0))  # rows: t, y, H m_r, m_r (BUF_T, BUF_Y, BUF_MF, BUF_MR)
        self._lo = self._n = 0  # the samples held: the columns _lo:_n of _buf
        self._last: tuple[float, float, float, float, float] | None = None  # t, x, aux, int x, m_r
        self._zi: np.ndarray | None = None
        self._rising = np.empty(0)  # the edges' times, s
        self._falling = np.empty(0)
        self._edges.reset()

    def set_stream_timing(self, demod_filter: DemodFilter, auxin_window_s: float) -> None:
        """The lock-in's filter and AuxIn window as applied (LockIn.stream_timing); forgets the stream history."""
        if not (math.isfinite(auxin_window_s) and auxin_window_s >= 0.0):
            raise ValueError(f"auxin_window_s {auxin_window_s!r} must be >= 0")
        self.demod_filter = demod_filter
        self.auxin_window_s = float(auxin_window_s)
        self._edges = EdgeTracker(window_s=self.auxin_window_s, min_step_v=self.dither_min_step_v)
        self._sos: np.ndarray | None = None  # the filter's FOH sections at the stream's sample interval _sos_dt
        self._sos_dt = 0.0
        self.reset_buffer()

    @property
    def referenced(self) -> bool:
        return self.rho_ref is not None

    # ------------------------------------------------------------------ processing
    def process(
        self, time: np.ndarray, x_sense: np.ndarray, rate_output: np.ndarray, dither: np.ndarray
    ) -> ClsfPeriods:
        """Add a block of samples; return the estimates of every dither period completed by it.

        The gain correction recorded for a period is the one in force while the block was taken (the lock-in's
        gain changes between blocks); correct mode then integrates their eta into the gain for the next block.
        """
        if self.mode == "off" or len(time) == 0:
            return ClsfPeriods.empty()
        t = np.asarray(time, dtype=float)
        if self._last is not None and len(t) and t[0] - self._last[0] > 1.5 * self._sample_dt(t):
            self.reset_buffer()  # a gap the caller did not report
        self._append(t, np.asarray(x_sense, dtype=float), np.asarray(rate_output, dtype=float))
        rising, falling = self._edges.process(t, np.asarray(dither, dtype=float))
        if rising.size:
            self._rising = np.concatenate((self._rising, rising))
        if falling.size:
            self._falling = np.concatenate((self._falling, falling))
        return self._periods()

    def _sample_dt(self, t: np.ndarray) -> float:
        """The sample interval: the median spacing of (at most) the first SPACING_SAMPLES samples, s."""
        if len(t) >= 2:
            return _median(np.diff(t[:SPACING_SAMPLES]))
        return self._sos_dt if self._sos_dt > 0 else 1.0

    def _append(self, t: np.ndarray, x: np.ndarray, aux: np.ndarray) -> None:
        """Extend the buffer by t, y = x + (1/tau) int x, H m_r and m_r (kernels.integrate_block: the trapezoid
        rule; AuxIn values sit at t_k - W/2), the filter's section states carried from block to block (at a first
        block, or after a redesign, the states at rest for the first m_r)."""
        last = self._last  # None before the first block (and after a gap)
        before = (float(t[0]), float(x[0]), float(aux[0]), 0.0, 0.0) if last is None else last
        # the samples' spacings start from the previous block's last time (or, for a first block, a repeat of its
        # first); a first block of 1-2 samples cannot outvote that zero spacing in the median, so its interval
        # comes from its own samples (one sample: the last design, or 1 s; a single sample's filter output is its
        # steady state whatever dt is, and the next block redesigns)
        if last is None and len(t) < 3:
            dt = self._sample_dt(t)
        else:
            dt = _median(np.diff(t[: SPACING_SAMPLES - 1], prepend=before[0]))
        if (self._sos is None and self.demod_filter.tc_s > 0.0) or (
            self._sos is not None and abs(dt - self._sos_dt) > 1e-9 * dt
        ):
            self._sos = self.demod_filter.foh_sos(dt)
            self._sos_dt = dt
            self._zi = None
        sos = NO_SECTIONS if self._sos is None else self._sos
        zi_per_unit = self._zi is None
        if self._zi is None:
            self._zi = sos_steady_state(sos)
        start = self._reserve(t.size)
        self._n = start + t.size
        rows = self._buf[:, start : self._n]
        ix = integrate_block(t, x, aux, before, self.auxin_window_s, self.tau_s, sos, self._zi, zi_per_unit, rows)
        self._last = (float(t[-1]), float(x[-1]), float(aux[-1]), float(ix), float(rows[BUF_MR, -1]))

    def _reserve(self, samples: int) -> int:
        """Room for `samples` more columns after the held ones: those move to the buffer's start (into a buffer
        twice as large when they would fill more than half of it). Returns the column where the new ones go."""
        held = self._n - self._lo
        if self._n + samples > self._buf.shape[1]:
            if 2 * (held + samples) > self._buf.shape[1]:
                grown = np.empty((4, 2 * (held + samples)))
                grown[:, :held] = self._buf[:, self._lo : self._n]
                self._buf = grown
            else:
                self._buf[:, :held] = self._buf[:, self._lo : self._n]
            self._lo, self._n = 0, held
        return self._n

    def _periods(self) -> ClsfPeriods:
        """Evaluate every complete period [R_i, R_(i+1)) whose previous period's edges are known too
        (periods.evaluate_periods: rho of the periods' windows, their mean rate output, holds and failed ratios
        left out).

        The sums run over the samples of [R_i + D, R_(i+1) + D), D = n tc the filter's delay: there the filtered
        triangle is symmetric, so an error in the edges' timing enters the estimate at second order only. rho:
        H m_d at those instants, m_d = integral of the square wave whose alternating edges (rising first) are the
        period's (R_(i-1), F_a, R_i, F_b, R_(i+1)): m_d is taken as lo (t - R_(i-1)) before the first edge (its
        history a whole period earlier has decayed out of the filter); each edge adds a ramp of slope
        +-(hi - lo), whose filtered form is the ramp response."""
        rising, falling = self._rising, self._falling
        lo, hi = self._edges.lo, self._edges.hi
        if rising.size < 3 or self._n == self._lo or lo is None or hi is None:
            self._cap_samples()
            return ClsfPeriods.empty()
        filt = self.demod_filter
        holds = np.array(self._holds) if self._holds else NO_HOLDS
        res = evaluate_periods(
            rising,
            falling,
            self._buf[:, self._lo : self._n],
            (lo, hi),
            filt.order,
            filt.tc_s,
            MIN_PERIOD_SAMPLES,
            holds,
        )
        if res.done < 0:  # no window complete in the buffer
            self._cap_samples()
            return ClsfPeriods.empty()
        self._rising = rising[res.done :]  # forget what the periods up to `done` no longer need
        self._falling = res.falling_needed
        self._lo += res.first_needed
        t0, t1, rho, rate = res.kept
        if res.usable == 0:
            return ClsfPeriods.empty()
        t_end = self._buf[BUF_T, self._n - 1]
        self._holds = [h for h in self._holds if h[1] >= t_end - 10.0]
        if self.rho_ref is None:
            need = self.reference_periods - len(self._ref_acc)
            self._ref_acc.extend(rho[:need].tolist())
            rho, rate, t1, t0 = rho[need:], rate[need:], t1[need:], t0[need:]
            if len(self._ref_acc) < self.reference_periods:
                return ClsfPeriods.empty()
            self.rho_ref = float(np.mean(self._ref_acc))
        eta = rho / self.rho_ref - 1.0
        gain = np.full(eta.size, self.gain_correction)  # the gain in force while the block was taken
        if self.mode == "correct" and eta.size:
            self.gain_correction *= math.exp(-float(np.sum((t1 - t0) * eta)) / self.time_constant_s)
        return ClsfPeriods(
            time=t1, eta=eta, sf_change_estimate=1.0 / (1.0 + eta) - 1.0, gain_correction=gain, rate_output_mean=rate
        )

    def _cap_samples(self) -> None:
        """While no edge is known, keep at most the last MAX_HELD_SAMPLES samples."""
        if self._rising.size == 0 and self._n - self._lo > MAX_HELD_SAMPLES:
            self._lo = self._n - MAX_HELD_SAMPLES


def _median(v: np.ndarray) -> float:
    """The median of a short array (np.median's value, without its general machinery: a few spacings per block)."""
    v = np.sort(v)
    m = v.size // 2
    return float(v[m] if v.size % 2 else 0.5 * (v[m - 1] + v[m]))


def observe_sensitivity(loop_bandwidth_hz: float, dither_hz: float, harmonics: int = 199) -> float:
    """d ln(D_x)/d ln(G) for the paper's plain demodulation (D_x alone), first-order loop, square-wave dither.

    With L = w_bw/s and the n-th odd harmonic of the square wave |Omega_n|^2 ~ 1/n^2,
    D_x(G) ~ sum_n |Omega_n|^2 G / ((n w_d)^2 + (G w_bw)^2), so the sensitivity is
    1 - sum_n w_n 2 w_bw^2 / ((n w_d)^2 + w_bw^2) with weights w_n ~ |Omega_n|^2 / ((n w_d)^2 + w_bw^2).
    Reported for comparison (0.856 for 2 Hz / 7 Hz, docs/clsf.md); the estimator above does not need it.
    """
    wb, wd = 2 * math.pi * loop_bandwidth_hz, 2 * math.pi * dither_hz
    n = np.arange(1, 2 * harmonics, 2, dtype=np.float64)
    weight = (1.0 / n**2) / ((n * wd) ** 2 + wb**2)
    return float(1.0 - np.sum(weight * 2 * wb**2 / ((n * wd) ** 2 + wb**2)) / np.sum(weight))
