"""qmg_lab/analysis/table_noise.py against its equation on a made-up Allan deviation: white rate noise,
sigma_A(tau) = s1 / sqrt(tau) (deg/h), whose log-log interpolation between octaves is exact, so
var_i = (s1^2/T+ + s1^2/T-) / (3600 (Omega+ - Omega-))^2 and the prediction is 1e6 sqrt(mean_(i >= 1) var_i + var_0)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from qmg_lab.analysis.adev import AllanResult
from qmg_lab.analysis.table_noise import PairWindows, table_step_noise

S1 = 1.2  # deg/h at 1 s (ARW 0.02 deg/sqrt(h))
TAUS = 2.0 ** np.arange(-2, 8)


def _adev(low_factor: float = 0.8, high_factor: float = 1.3) -> AllanResult:
    dev = S1 / np.sqrt(TAUS)
    return AllanResult(TAUS, dev, low_factor * dev, high_factor * dev, n_samples=2000, rate_hz=7.0)


def test_unequal_windows_and_rates_follow_the_equation() -> None:
    pairs = [
        PairWindows((10.0, 65.0), (75.0, 130.0), 5.0, -5.0),
        PairWindows((140.0, 180.0), (190.0, 250.0), 5.0, -5.0),
        PairWindows((260.0, 315.0), (325.0, 380.0), 20.0, -20.0),
    ]

    def var(p: PairWindows, s: float) -> float:
        t_plus, t_minus = np.diff(p.window_plus_s)[0], np.diff(p.window_minus_s)[0]
        return float((s**2 / t_plus + s**2 / t_minus) / (3600 * (p.rate_plus_dps - p.rate_minus_dps)) ** 2)

    got = table_step_noise(pairs, _adev())
    assert got is not None
    for value, s in ((got.rms_ppm, S1), (got.rms_ppm_low, 0.8 * S1), (got.rms_ppm_high, 1.3 * S1)):
        expected = 1e6 * math.sqrt((var(pairs[1], s) + var(pairs[2], s)) / 2 + var(pairs[0], s))
        assert value == pytest.approx(expected, rel=1e-9)
    assert got.pair0_ppm == pytest.approx(1e6 * math.sqrt(var(pairs[0], S1)), rel=1e-9)


def test_equal_pairs_give_sigma_over_omega() -> None:
    """sqrt(2) sigma_A/(2 Omega) per pair, sqrt(2) again against pair 0: sigma_A(T)/Omega."""
    pairs = [PairWindows((0.0, 55.0), (60.0, 115.0), 5.0, -5.0)] * 25
    got = table_step_noise(pairs, _adev())
    assert got is not None
    assert got.rms_ppm == pytest.approx(1e6 * S1 / math.sqrt(55.0) / 3600 / 5.0, rel=1e-9)
    assert got.pair0_ppm == pytest.approx(got.rms_ppm / math.sqrt(2), rel=1e-9)


def test_no_prediction_without_two_pairs_or_the_adev_at_the_windows_length() -> None:
    one = [PairWindows((0.0, 55.0), (60.0, 115.0), 5.0, -5.0)]
    assert table_step_noise(one, _adev()) is None
    too_long = [PairWindows((0.0, 500.0), (510.0, 1010.0), 5.0, -5.0)] * 3  # 500 s > the ADEV's longest tau
    assert table_step_noise(too_long, _adev()) is None
