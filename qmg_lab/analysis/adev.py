"""Allan deviation with confidence intervals, and the gyro noise figures read from it (IEEE Std 952 Annex C).

* Overlapping Allan deviation of *rate* (frequency-type) data: `allantools.oadev(y, rate, data_type="freq")`
  (passing rate data as "phase" is the classic bug: it integrates twice).
* Confidence intervals: equivalent degrees of freedom from Greenhall's algorithm (`allantools.edf_greenhall`,
  white-FM noise alpha = 0, d = 2, overlapping) and the chi-squared interval at 68.3 %
  (`allantools.confidence_interval`): sigma_low/high = sigma sqrt(edf / chi2_{(1 +- 0.683)/2}(edf)).
* Angle random walk: N [deg/sqrt(h)] = sigma(tau = 1 s) [deg/h] / 60 (white rate noise: sigma = N/sqrt(tau)).
* Bias instability: B = min(sigma) / 0.664 (flicker floor sigma = B sqrt(2 ln 2 / pi) = 0.664 B).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import allantools
import numpy as np

BI_FACTOR = 0.664  # sqrt(2 ln2 / pi), IEEE 952 C.1.4


@dataclass(frozen=True)
class AllanResult:
    """Allan deviation at octave-spaced tau (s), in the input's units, with 68.3 % confidence bounds."""

    tau_s: np.ndarray
    dev: np.ndarray
    low: np.ndarray
    high: np.ndarray
    n_samples: int
    rate_hz: float

    def at(self, tau_s: float) -> float:
        """sigma(tau) interpolated log-log (NaN outside the computed range)."""
        if self.tau_s.size == 0 or not self.tau_s[0] <= tau_s <= self.tau_s[-1]:
            return float("nan")
        return float(np.exp(np.interp(np.log(tau_s), np.log(self.tau_s), np.log(self.dev))))

    def bounds_at(self, tau_s: float) -> tuple[float, float, float]:
        """(sigma, its 68.3 % low bound, its high bound) at tau, each interpolated log-log like `at` (NaN outside
        the computed range)."""
        if self.tau_s.size == 0 or not self.tau_s[0] <= tau_s <= self.tau_s[-1]:
            return (float("nan"),) * 3
        x, xp = math.log(tau_s), np.log(self.tau_s)
        sigma, low, high = (float(np.exp(np.interp(x, xp, np.log(v)))) for v in (self.dev, self.low, self.high))
        return sigma, low, high

    def rows(self, scale: float = 1.0) -> list[dict[str, float]]:
        return [
            {"tau_s": float(t), "value": float(d * scale), "low": float(lo * scale), "high": float(hi * scale)}
            for t, d, lo, hi in zip(self.tau_s, self.dev, self.low, self.high, strict=True)
        ]


def overlapping_adev(y: np.ndarray, rate_hz: float, min_clusters: int = 3) -> AllanResult:
    """Overlapping ADEV of evenly sampled rate-type data y at rate_hz, octave taus up to N/min_clusters samples.

    Raises ValueError if y has fewer than 2 * min_clusters samples or rate_hz is not positive.
    """
    y = np.asarray(y, dtype=np.float64)
    y = y[np.isfinite(y)]
    if not rate_hz > 0:
        raise ValueError(f"ADEV needs a positive sample rate, got {rate_hz!r} Hz")
    n = y.shape[0]
    if n < 2 * min_clusters:
        raise ValueError(f"ADEV needs at least {2 * min_clusters} samples, got {n}")
    m_max = max(1, n // min_clusters)
    ms = 2 ** np.arange(int(np.floor(np.log2(m_max))) + 1)
    taus, dev, _err, _ns = allantools.oadev(y, rate=rate_hz, data_type="freq", taus=ms / rate_hz)
    keep = np.isfinite(dev) & (dev > 0)
    taus, dev = np.asarray(taus)[keep], np.asarray(dev)[keep]
    low, high = np.empty_like(dev), np.empty_like(dev)
    for i, (t, d) in enumerate(zip(taus, dev, strict=True)):
        m = int(round(t * rate_hz))
        edf = allantools.edf_greenhall(alpha=0, d=2, m=m, N=n + 1, overlapping=True, modified=False)
        low[i], high[i] = allantools.confidence_interval(d, edf)
    return AllanResult(tau_s=taus, dev=dev, low=low, high=high, n_samples=n, rate_hz=float(rate_hz))


def arw_deg_per_rt_h(result_dph: AllanResult) -> float:
    """Angle random walk from an ADEV of rate in deg/h: sigma(1 s) / 60, deg/sqrt(h)."""
    return result_dph.at(1.0) / 60.0


def bias_instability_deg_per_h(result_dph: AllanResult) -> float:
    """Bias instability B = min(sigma) / 0.664, deg/h (from an ADEV of rate in deg/h), IEEE 952.

    NaN when the data do not resolve the floor: if the smallest deviation is at the longest averaging time the
    curve is still falling (the static segment is too short) and its minimum would understate B.
    """
    dev = result_dph.dev
    if dev.size < 3:
        return float("nan")
    i = int(np.argmin(dev))
    if i == dev.size - 1:
        return float("nan")
    return float(dev[i]) / BI_FACTOR
