"""One rule judges every SF-change series: qmg_lab.analysis.compute.series_accuracy.

* Known answer: a series s(t) = A t read over two windows per pair whose sample times are symmetric about
  100 i + 15 s has the pair mean s_i = A (100 i + 15), so c_i = (1 + s_i)/(1 + s_0) - 1; table changes
  e_i = c_i + delta_i and truth t_i = c_i + 2 ppm give RMS(c - e) = RMS(delta over pairs 1..n-1), its mean-removed
  RMS, and RMS(c - t) = 2 ppm; no truth (NaN) gives None.
* The calibrated SF of `analyze --sf-model` (qmg_lab.analysis.calibrated_sf.evaluate) is judged by that rule: with
  a model whose ln-ratio is constant over the run (a constant drive frequency), 1 + s_cal = (1 + s) exp(m - m_ref)
  equals the CLSF estimate, so its figures equal the ones `analyze` gives the CLSF estimate itself.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from qmg_lab.analysis.calibrated_sf import evaluate
from qmg_lab.analysis.compute import StepPair, analyze, series_accuracy
from qmg_lab.clsf.pickoff_model import PickoffRatioModel
from tests.support.synthetic_runs import write_sweep

A_PER_S = 2e-6  # slope of the synthetic series, 1/s
DELTA_PPM = np.array([0.0, 3.0, -4.0, 5.0, 0.0])


def _pairs(truth: bool = True) -> tuple[list[StepPair], np.ndarray]:
    c = np.array([(1 + A_PER_S * (100 * i + 15)) / (1 + A_PER_S * 15) - 1 for i in range(5)]) * 1e6
    pairs = [
        StepPair(
            index_plus=2 * i,
            index_minus=2 * i + 1,
            t_mid_s=100 * i + 15,
            temperature_c=25.0,
            sf_v_per_dps=0.06,
            bias_v=0.0,
            true_change_ppm=float(c[i] + DELTA_PPM[i]),
            truth_change_ppm=float(c[i] + 2.0) if truth else float("nan"),
            window_plus_s=(100.0 * i, 100.0 * i + 10),
            window_minus_s=(100.0 * i + 20, 100.0 * i + 30),
        )
        for i in range(5)
    ]
    return pairs, c


def test_series_accuracy_known_answer() -> None:
    pairs, c = _pairs()
    t = np.arange(0.0, 500.0, 0.5)
    acc = series_accuracy(pairs, t, A_PER_S * t)
    d = -DELTA_PPM[1:]
    assert acc.n_pairs == 5
    assert acc.change_ppm == pytest.approx(list(c), abs=1e-6)
    assert acc.rms_vs_table_ppm == pytest.approx(math.sqrt(np.mean(d**2)), abs=1e-6)
    assert acc.rms_vs_table_ppm_mean_removed == pytest.approx(math.sqrt(np.mean((d - d.mean()) ** 2)), abs=1e-6)
    assert acc.rms_vs_truth_ppm == pytest.approx(2.0, abs=1e-6)
    no_truth, _ = _pairs(truth=False)
    assert series_accuracy(no_truth, t, A_PER_S * t).rms_vs_truth_ppm is None


def test_calibrated_sf_is_judged_by_the_same_rule_as_the_clsf_estimate(tmp_path: Path) -> None:
    path = tmp_path / "sweep.h5"
    write_sweep(path)  # drive frequency held at 2200 Hz
    result = analyze(path)
    model = PickoffRatioModel(
        anchor_hz=2199.0,
        linear_per_hz=3e-3,  # m = 3e-3 over the whole run: exp(m - m_ref) = 1
        quadratic_per_hz2=0.0,
        lagged_per_hz=0.0,
        lag_tau_s=0.0,
        residual_rms_ppm=0.0,
        n_pairs=8,
        x_range_hz=(0.0, 2.0),
    )
    cal = evaluate(path, model, result)
    assert result.clsf_accuracy_rms_ppm is not None and math.isfinite(result.clsf_accuracy_rms_ppm)
    assert cal.accuracy_vs_table_ppm == pytest.approx(result.clsf_accuracy_rms_ppm, rel=1e-9)
    assert cal.clsf_accuracy_vs_table_ppm == pytest.approx(result.clsf_accuracy_rms_ppm, rel=1e-12)
    assert cal.vs_truth_ppm == pytest.approx(result.clsf_vs_truth_rms_ppm, rel=1e-9)
    assert cal.pair_changes_ppm == pytest.approx([p.clsf_change_ppm for p in result.pairs], abs=1e-6)
