"""FTR characterization from run files: bandwidth (sine steps), settling (rate step), linearity (level steps).

Procedures (IEEE Std 1431; docs/physics.md sections 7-8):

* Bandwidth. For a sine step at f with table-rate amplitude A, least squares on the settled window fits
  O(t) = a cos(2 pi f t) + b sin(2 pi f t) + c + sum_h [dither harmonics at h f_d, h = 1, 3, 5] to the rate output,
  and the same sinusoid to the reference rate (the twin's /truth/rate if present, else the command
  A sin(2 pi f (t - t_start)) — phase zero at the step start, an assumption stated in the result).
  H(f) = (O amplitude / SF) / reference amplitude, phase = angle(O) - angle(reference).
  The -3 dB bandwidth is where 20 log10|H| crosses -3.01 dB, interpolated linearly in (log f, dB).
* Settling. Response to a rate step: rate output smoothed by a centred moving average over one dither period
  (nulls the dither and its harmonics); settling time = last time |O - O_final| > 2 % |O_final - O_initial|,
  measured from the step start (the table command). O_final: mean of the second half of the step;
  O_initial: mean of the last second before it.
* Linearity. Least-squares O_i = SF Omega_i + B over the level steps; nonlinearity = max|residual| / (SF FS) and
  RMS residual / (SF FS), FS = max|Omega_i|; asymmetry = (SF+ - SF-)/SF with SF+- fitted on the Omega >= 0 and
  Omega <= 0 levels.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class BodePoint:
    frequency_hz: float
    amplitude_ratio: float
    gain_db: float
    phase_deg: float


def fit_sinusoid(t: np.ndarray, y: np.ndarray, f_hz: float, nuisance_hz: tuple[float, ...] = ()) -> complex:
    """Complex amplitude a - i b of y ~ a cos(2 pi f t) + b sin(2 pi f t) + c (+ nuisance sinusoids).

    |result| is the amplitude, angle(result) the phase of a cos(wt + phi) model (phi = atan2(-b, a)).
    """
    cols = [np.cos(2 * np.pi * f_hz * t), np.sin(2 * np.pi * f_hz * t), np.ones_like(t)]
    for fn in nuisance_hz:
        if abs(fn - f_hz) > 1e-6:
            cols += [np.cos(2 * np.pi * fn * t), np.sin(2 * np.pi * fn * t)]
    coef, *_ = np.linalg.lstsq(np.column_stack(cols), y, rcond=None)
    return complex(coef[0], -coef[1])


def bandwidth_3db(points: list[BodePoint]) -> float:
    """First frequency where the gain falls through -3.01 dB (linear in log f), NaN if it never does."""
    pts = sorted(points, key=lambda p: p.frequency_hz)
    target = -10 * math.log10(2.0)
    for p0, p1 in itertools.pairwise(pts):
        if p0.gain_db >= target > p1.gain_db:
            x0, x1 = math.log(p0.frequency_hz), math.log(p1.frequency_hz)
            return math.exp(x0 + (target - p0.gain_db) * (x1 - x0) / (p1.gain_db - p0.gain_db))
    return float("nan")


def moving_average(y: np.ndarray, n: int) -> np.ndarray:
    """Centred boxcar of n samples (edges: shorter windows)."""
    if n <= 1:
        return y.astype(np.float64, copy=True)
    c = np.concatenate([[0.0], np.cumsum(y, dtype=np.float64)])
    half = n // 2
    idx = np.arange(y.shape[0])
    lo = np.clip(idx - half, 0, y.shape[0])
    hi = np.clip(idx - half + n, 0, y.shape[0])
    return (c[hi] - c[lo]) / (hi - lo)


def settling_time_s(t: np.ndarray, y: np.ndarray, t_step: float, t_end: float, band: float = 0.02) -> float:
    """2 % settling time of y after a step commanded at t_step (y already free of the dither)."""
    before = (t >= t_step - 1.0) & (t < t_step)
    after = (t >= t_step) & (t <= t_end)
    if before.sum() < 2 or after.sum() < 4:
        return float("nan")
    y0 = float(np.mean(y[before]))
    ta, ya = t[after], y[after]
    y1 = float(np.mean(ya[ta >= 0.5 * (t_step + t_end)]))
    tol = band * abs(y1 - y0)
    outside = np.nonzero(np.abs(ya - y1) > tol)[0]
    if outside.size == 0:
        return 0.0
    last = outside[-1]
    return float(ta[min(last + 1, ta.shape[0] - 1)] - t_step)


@dataclass(frozen=True)
class Linearity:
    sf_v_per_dps: float
    bias_v: float
    nonlinearity_max_pct_fs: float
    nonlinearity_rms_pct_fs: float
    asymmetry_ppm: float
    full_scale_dps: float
    residuals_v: np.ndarray


def linearity(rates_dps: np.ndarray, outputs_v: np.ndarray) -> Linearity:
    """Fit O = SF Omega + B; nonlinearity in % of SF x FS; asymmetry (SF+ - SF-)/SF in ppm."""
    r, o = np.asarray(rates_dps, float), np.asarray(outputs_v, float)
    if r.shape[0] < 2 or np.ptp(r) == 0:
        raise ValueError("linearity needs at least two distinct rates")
    sf, bias = np.polyfit(r, o, 1)
    resid = o - (sf * r + bias)
    fs = float(np.max(np.abs(r)))

    def side(mask: np.ndarray) -> float:
        return float(np.polyfit(r[mask], o[mask], 1)[0]) if np.unique(r[mask]).shape[0] >= 2 else float("nan")

    asym = (side(r >= 0) - side(r <= 0)) / sf
    return Linearity(
        sf_v_per_dps=float(sf),
        bias_v=float(bias),
        nonlinearity_max_pct_fs=float(100 * np.max(np.abs(resid)) / abs(sf * fs)),
        nonlinearity_rms_pct_fs=float(100 * np.sqrt(np.mean(resid**2)) / abs(sf * fs)),
        asymmetry_ppm=float(asym * 1e6),
        full_scale_dps=fs,
        residuals_v=resid,
    )
