"""How good the table steps can be as a judge: the noise the gyro's own rate noise puts into the table-step SF
changes e_i, predicted from the run's Allan deviation (qmg-lab analyze's "table-step noise (predicted)").

A pair's SF is (O+ - O-)/(Omega+ - Omega-), O+- the rate output's means over its two windows of lengths T+ and T-
(qmg_lab/analysis/compute.py). The gyro's rate noise adds n+ - n- to O+ - O- (in deg/s, divided by SF), n the noise's
mean over a window. The Allan variance is defined as half the mean square difference of two adjacent means over
tau, sigma_A^2(tau) = E[(n_(k+1) - n_k)^2]/2, so for two windows of one length T, E[(n+ - n-)^2] = 2 sigma_A^2(T);
for unequal lengths, sigma_A^2(T+) + sigma_A^2(T-) (exact for white rate noise, whose means are independent;
first order for the flicker floor, over which sigma_A is flat). A pair's relative SF error is therefore
    eps_i = (n+ - n-)/(Omega+ - Omega-),   var_i = (sigma_A^2(T+) + sigma_A^2(T-)) / (Omega+ - Omega-)^2
            (= sqrt(2) sigma_A(T) / (2 Omega) in standard deviation for equal windows at +-Omega).
The steps are judged as changes against pair 0: e_i - t_i = (1 + eps_i)/(1 + eps_0) - 1 ~ eps_i - eps_0, and the
truth check is RMS(e_i - t_i) over pairs 1..n-1. Its expected square is
    E[RMS^2] = mean_(i >= 1) var_i + var_0,
the pairs' own noise plus the reference's: eps_0 is one draw that sits in every e_i, so it does not average down
with more pairs. For equal pairs the two halves are equal and the RMS is sqrt(2) times one pair's noise,
sigma_A(T)/Omega; pair 0's share (`pair0_ppm`) is sqrt(var_0). One run's RMS scatters about this: by its draw of
eps_0 (between one pair's noise, eps_0 = 0, and more) and by 1/sqrt(2 (n - 1)) for the rest.

sigma_A(T) is the overlapping ADEV of the run's dither-free rate output over its static (hold or soak) segment,
read at each window's length (log-log interpolation between octaves, qmg_lab/analysis/adev.py); its 68 % bounds
give the prediction's. The windows are the analysis's (the rate-output mean spans their whole dither periods, at
most one period shorter: < 0.3 % of T at 55 s).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from qmg_lab.analysis.adev import AllanResult

PPM = 1e6
SECONDS_PER_HOUR = 3600.0


@dataclass(frozen=True)
class PairWindows:
    """One step pair's two analysis windows (s) and the table's rates over them (deg/s)."""

    window_plus_s: tuple[float, float]
    window_minus_s: tuple[float, float]
    rate_plus_dps: float
    rate_minus_dps: float


@dataclass(frozen=True)
class TableStepNoise:
    """The predicted RMS(e_i - t_i) over pairs 1..n-1 from the gyro's noise (module docstring), ppm, with the
    68 % bounds of the ADEV it reads, and pair 0's share sqrt(var_0)."""

    rms_ppm: float
    rms_ppm_low: float
    rms_ppm_high: float
    pair0_ppm: float


def table_step_noise(pairs: list[PairWindows], gyro_adev_dph: AllanResult) -> TableStepNoise | None:
    """E[RMS(e_i - t_i)]^(1/2) = sqrt(mean_(i >= 1) var_i + var_0), var_i = (sigma_A^2(T+) + sigma_A^2(T-)) /
    (Omega+ - Omega-)^2, sigma_A from the gyro's ADEV in deg/h (module docstring); None with fewer than two pairs
    or a window length outside the ADEV's taus (the static segment is too short to read it)."""
    if len(pairs) < 2:
        return None
    variances: list[list[float]] = []  # per pair: var at the ADEV's value, its low and its high bound (fraction^2)
    for p in pairs:
        span_dps = p.rate_plus_dps - p.rate_minus_dps
        sigmas = [gyro_adev_dph.bounds_at(t1 - t0) for t0, t1 in (p.window_plus_s, p.window_minus_s)]
        if not span_dps > 0 or not all(math.isfinite(x) for s in sigmas for x in s):
            return None
        variances.append([sum((s[k] / SECONDS_PER_HOUR) ** 2 for s in sigmas) / span_dps**2 for k in range(3)])

    def rms(k: int) -> float:
        rest = [v[k] for v in variances[1:]]
        return PPM * math.sqrt(sum(rest) / len(rest) + variances[0][k])

    return TableStepNoise(rms(0), rms(1), rms(2), PPM * math.sqrt(variances[0][0]))
