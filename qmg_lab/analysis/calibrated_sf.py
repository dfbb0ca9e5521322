"""The whole scale factor, self-calibrated: CLSF corrected by the pickoff-ratio model (qmg_lab/clsf/pickoff_model.py).

Two uses, kept apart so that no table step of an evaluated run enters its own estimate:

* `characterise(run_file)`: the model from a characterisation run. Its table step pairs (qmg_lab/analysis/compute.py)
  give y_i = ln(1 + e_i) - ln(1 + c_i); the fit regresses y on the drive frequency's features over the same windows.
* `evaluate(run_file, model, result)`: the calibrated SF of another run, 1 + s_cal = (1 + s) exp(m - m_ref), and
  only then its judgement: against the run's table steps (accuracy RMS over pairs 1..n-1, as the CLSF accuracy of
  `analyze`) and, on a twin, against /truth. The estimate uses /clsf/sf_change_estimate and /lockin/drive_frequency
  alone; the table steps enter `accuracy_vs_table_ppm` and nothing else.

Both series, the calibrated one and the CLSF estimate it starts from, are judged by one rule:
qmg_lab.analysis.compute.series_accuracy, the function `analyze` judges the CLSF estimate by (its windows are the
encoder-timed step windows of `analyze`'s pairs).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from qmg_lab.analysis.adev import overlapping_adev
from qmg_lab.analysis.compute import AnalysisResult, StepPair, analyze, series_accuracy, stored_config
from qmg_lab.analysis.reductions import analysis_settle_s
from qmg_lab.clsf.pickoff_model import PickoffRatioModel, binned, fit_pickoff_model
from qmg_lab.storage.reader import RunData, read_run

PPM = 1e6
WARN_ACCURACY_PPM = 100.0  # the bound across variants: above it `analyze` names the broken assumption
WARN_RESIDUAL_PPM = 25.0  # a characterisation residual above this: the model's form does not fit the device
RANGE_MARGIN = 0.1  # of the characterised span: how far outside it an evaluated run may go before a warning


@dataclass(frozen=True)
class CalibratedSF:
    """The calibrated SF of one run beside the CLSF-only one (ppm; NaN where not available)."""

    pair_changes_ppm: list[float]  # calibrated SF change of each step pair, against pair 0
    accuracy_vs_table_ppm: float
    accuracy_vs_table_ppm_mean_removed: float
    vs_truth_ppm: float | None
    clsf_accuracy_vs_table_ppm: float
    clsf_vs_truth_ppm: float | None
    adev_2000s_error_ppm: float | None  # ADEV at 2000 s of the calibrated SF's error against /truth
    clsf_adev_2000s_error_ppm: float | None  # the same for the CLSF estimate
    warnings: list[str] = field(default_factory=list)

    def to_json(self) -> dict[str, Any]:
        def clean(v: Any) -> Any:
            if isinstance(v, float):
                return v if math.isfinite(v) else None
            if isinstance(v, list):
                return [clean(u) for u in v]
            return v

        return {k: clean(v) for k, v in self.__dict__.items()}


def _drive_frequency(run: RunData) -> tuple[np.ndarray, np.ndarray]:
    lk = run.groups["lockin"]
    if "drive_frequency" not in lk or lk["time"].shape[0] == 0:
        raise ValueError(f"{run.path}: no /lockin/drive_frequency: the drive resonance thermometer needs it")
    return binned(lk["time"], lk["drive_frequency"])


def _pair_windows(run: RunData, settle_s: float, pairs: list[StepPair]) -> list[list[tuple[float, float]]]:
    s = run.steps
    ends = {int(i): (float(a), float(b)) for i, a, b in zip(s["index"], s["t_start"], s["t_end"], strict=True)}
    return [[(ends[i][0] + settle_s, ends[i][1]) for i in (p.index_plus, p.index_minus)] for p in pairs]


def _load(run_file: str | Path) -> tuple[RunData, float]:
    run = read_run(run_file, select=["lockin/drive_frequency", "clsf", "truth"])
    cfg, _ = stored_config(run)
    return run, analysis_settle_s(cfg)


def characterise(run_file: str | Path, result: AnalysisResult | None = None) -> PickoffRatioModel:
    """The pickoff-ratio model from a characterisation run's table steps (module docstring). ValueError if the run
    cannot give one (no pairs, no drive frequency, too few pairs)."""
    res = analyze(run_file) if result is None else result
    pairs = [p for p in res.pairs if math.isfinite(p.true_change_ppm) and math.isfinite(p.clsf_change_ppm)]
    if len(pairs) < 6:
        raise ValueError(f"{run_file}: {len(pairs)} complete +-rate step pairs; the model needs at least 6")
    run, settle = _load(run_file)
    cfg, _ = stored_config(run)
    t, f = _drive_frequency(run)
    y = np.array([math.log1p(p.true_change_ppm / PPM) - math.log1p(p.clsf_change_ppm / PPM) for p in pairs])
    temps = [p.temperature_c for p in pairs]
    source = {
        "run_file": str(Path(run_file).resolve()),
        "campaign": cfg.campaign.name,
        "seed": cfg.sim.seed if res.mode != "hardware" else None,
        "mode": res.mode,
        "chamber_c": [float(np.nanmin(temps)), float(np.nanmax(temps))],
        "ramp_c_per_min": cfg.plan.chamber_ramp_c_per_min,
        "clsf_mode": cfg.clsf.mode,
    }
    return fit_pickoff_model(t, f, _pair_windows(run, settle, pairs), y, source=source).model


def calibrated_series(run: RunData, model: PickoffRatioModel, reference_periods: int) -> tuple[np.ndarray, np.ndarray]:
    """(time, s_cal) at the CLSF periods: 1 + s_cal = (1 + s) exp(m - m_ref), m_ref the mean of m over the first
    `reference_periods` periods (CLSF's own reference). The SF series an outside evaluation takes."""
    clsf = run.groups.get("clsf")
    if clsf is None or clsf["time"].shape[0] == 0:
        raise ValueError(f"{run.path}: no CLSF periods")
    t, f = _drive_frequency(run)
    m = np.interp(clsf["time"], t, model.log_ratio(t, f))
    m_ref = float(np.mean(m[: max(1, reference_periods)]))
    return clsf["time"], (1.0 + clsf["sf_change_estimate"]) * np.exp(m - m_ref) - 1.0


def _truth_error_adev(run: RunData, t_k: np.ndarray, s_k: np.ndarray) -> float | None:
    """ADEV at 2000 s (ppm) of (1 + s_k)/(SF_truth(t_k)/SF_truth(t_0)) - 1: an estimate's actual error on a twin."""
    truth = run.groups.get("truth")
    if truth is None or truth["time"].shape[0] == 0 or t_k.size < 8:
        return None
    tb, sfb = binned(truth["time"], truth["scale_factor"])
    tr = np.interp(t_k, tb, sfb)
    err = (1.0 + s_k) / (tr / tr[0]) - 1.0
    rate = 1.0 / float(np.median(np.diff(t_k)))
    value = overlapping_adev(err * PPM, rate).at(2000.0)
    return value if math.isfinite(value) else None


def evaluate(run_file: str | Path, model: PickoffRatioModel, result: AnalysisResult) -> CalibratedSF:
    """The calibrated SF of a run (its own CLSF and drive frequency, the model from another run), judged against
    its table steps and its /truth (module docstring)."""
    run, _ = _load(run_file)
    cfg, _ = stored_config(run)
    warnings: list[str] = []
    t_k, s_cal = calibrated_series(run, model, cfg.clsf.reference_periods)
    _, f = _drive_frequency(run)
    clsf = run.groups["clsf"]  # calibrated_series found it
    cal = series_accuracy(result.pairs, t_k, s_cal)
    est = series_accuracy(result.pairs, clsf["time"], clsf["sf_change_estimate"])
    acc = cal.rms_vs_table_ppm
    clsf_adev = _truth_error_adev(run, t_k, clsf["sf_change_estimate"])
    # the model's assumptions, checked on what the run shows (the table only judges: it never enters s_cal)
    x_lo, x_hi = model.x_range_hz
    span = max(x_hi - x_lo, 1e-9)
    x = f - model.anchor_hz
    if x.size and (x.min() < x_lo - RANGE_MARGIN * span or x.max() > x_hi + RANGE_MARGIN * span):
        warnings.append(
            f"drive frequency outside the characterised range ({x.min():+.4f} .. {x.max():+.4f} Hz against "
            f"{x_lo:+.4f} .. {x_hi:+.4f} Hz from {model.anchor_hz:.4f} Hz): the die temperature leaves the model's "
            "range, or f0 moved between the runs (ageing, charging, another device), so the thermometer's offset "
            "is unknown"
        )
    if model.residual_rms_ppm > WARN_RESIDUAL_PPM:
        warnings.append(
            f"the model fitted its characterisation run to {model.residual_rms_ppm:.0f} ppm RMS: the pickoff ratio "
            "is not a function of the die temperature plus one lagging front end with a quadratic part"
        )
    if model.lag_tau_s >= 0.99 * 4000.0:
        warnings.append(f"fitted front-end lag {model.lag_tau_s:.0f} s at the fit's limit: the lag is not resolved")
    if math.isfinite(acc) and acc > WARN_ACCURACY_PPM:
        warnings.append(
            f"calibrated SF off the table steps by {acc:.0f} ppm RMS (> {WARN_ACCURACY_PPM:.0f}): an assumption of "
            "the drive-frequency thermometer is broken (the characterisation run's temperature path did not "
            "exercise the front end's lag as this run does, a pickoff part that follows neither the die nor one "
            "lagging board, or f0 moved for a reason other than temperature)"
        )
    return CalibratedSF(
        pair_changes_ppm=list(cal.change_ppm),
        accuracy_vs_table_ppm=acc,
        accuracy_vs_table_ppm_mean_removed=cal.rms_vs_table_ppm_mean_removed,
        vs_truth_ppm=cal.rms_vs_truth_ppm,
        clsf_accuracy_vs_table_ppm=est.rms_vs_table_ppm,
        clsf_vs_truth_ppm=est.rms_vs_truth_ppm,
        adev_2000s_error_ppm=_truth_error_adev(run, t_k, s_cal),
        clsf_adev_2000s_error_ppm=clsf_adev,
        warnings=warnings,
    )
