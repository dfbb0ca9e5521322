"""The table steps' own noise as a judge, predicted by `analyze` from the run's gyro noise
(qmg_lab/analysis/table_noise.py), against the twin's [sim] noise values.

A short twin campaign (tests/support/campaigns.py's plan with a 120 s soak: 8 s windows, 4 pairs at +-5 deg/s) with
every deterministic accuracy source off (qmg_lab.budget.sweep.DETERMINISTIC_OFF), the pickoff, forcer and AuxIn
noise off and the AuxIn ideal, so the only random source is the gyro's rate noise: white of ARW N and flicker of
bias instability B ([sim]). Its Allan deviation at a window length T is, to first order (IEEE 952: the -1/2 line
and the flicker floor added in power),
    sigma_m^2(T) = (60 N)^2 / T + (0.664 B)^2        (deg/h; N in deg/sqrt(h), T in s)
and the truth check's expected RMS, with each pair's windows and rates as analysed,
    sqrt(mean_(i >= 1) var_i + var_0),   var_i = (sigma_m^2(T+) + sigma_m^2(T-)) / (3600 (Omega+ - Omega-))^2.
`analyze` reads sigma from the run's own ADEV of the soak; the model's figure must lie within that estimate's
confidence: the 68 % bounds widened to twice their half-widths (about 95 % for the chi-squared interval).
With the gyro noise off too no random source is left. What `analyze` still reads is the static segment's own
floor: /clsf/rate_output_mean is a mean over whole samples of each dither period, and the DS345 and the HF2 share
no clock, so each period's cut of the dither leaking through the rate loop moves by a fraction of a sample. The
error is bounded and telescopes from period to period, so its Allan deviation falls as 1/tau (on this twin about
0.35 deg/h s / tau: 0.044 deg/h at 8 s against the gyro's 0.445). The check: that floor adds less than 1.2 % to the
noise-on figure in quadrature, i.e. the noise-off prediction is below 0.15 of the noise-on model (0.15^2 / 2).
"""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from qmg_lab.analysis.compute import AnalysisResult, analyze
from qmg_lab.budget.sweep import DETERMINISTIC_OFF, sim_lines
from qmg_lab.config.schema import Config
from sims.gyro_params import NOISE_OFF
from tests.support.campaigns import SHORT_TOML, run_inprocess

QUIET_ELSE = {
    "pickoff_noise_vrms_per_rt_hz": 0.0,
    "forcer_noise_v_per_rt_hz": 0.0,
    "auxin_noise_v_rms": 0.0,
    "auxin_bits": 0,
    **DETERMINISTIC_OFF,
}


def _run(tmp_path: Path, sim: dict[str, float]) -> tuple[AnalysisResult, Config]:
    text = SHORT_TOML.replace("chamber_soak_s = 20.0", "chamber_soak_s = 120.0") + "[sim]\nseed = 11\n"
    out = run_inprocess(tmp_path, text + sim_lines(sim))
    assert out.error is None
    return analyze(out.path), out.cfg


def _model_ppm(res: AnalysisResult, cfg: Config) -> float:
    n, b = cfg.sim.arw_deg_per_rt_h, cfg.sim.bias_instability_deg_per_h

    def sigma2(window: tuple[float, float]) -> float:
        return (60 * n) ** 2 / (window[1] - window[0]) + (0.664 * b) ** 2

    var = [
        (sigma2(p.window_plus_s) + sigma2(p.window_minus_s)) / (3600 * (p.rate_plus_dps - p.rate_minus_dps)) ** 2
        for p in res.pairs
    ]
    return 1e6 * math.sqrt(sum(var[1:]) / len(var[1:]) + var[0])


def test_predicted_table_step_noise_is_the_gyro_noise_models(tmp_path: Path) -> None:
    res, cfg = _run(tmp_path, QUIET_ELSE)
    assert res.n_step_pairs == 4
    model = _model_ppm(res, cfg)
    pred, low, high = res.table_step_noise_ppm, res.table_step_noise_ppm_low, res.table_step_noise_ppm_high
    assert pred is not None and low is not None and high is not None and res.table_step_noise_pair0_ppm is not None
    assert low - (pred - low) <= model <= high + (high - pred), (low, pred, high, model)
    # the reference's share: one pair's variance of the mean square (equal windows here: half of it, to 1 %)
    assert res.table_step_noise_pair0_ppm**2 / pred**2 == pytest.approx(0.5, rel=0.01)
    assert res.to_json()["table_step_noise_ppm"] == pred

    off, _ = _run(tmp_path / "off", {**QUIET_ELSE, **NOISE_OFF})
    assert off.n_step_pairs == 4
    assert off.table_step_noise_ppm is not None and off.table_step_noise_ppm < 0.15 * model
