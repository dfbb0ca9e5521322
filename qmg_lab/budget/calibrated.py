"""Predicted residual of the whole-SF calibration (CLSF + the drive-frequency pickoff model), source by source.

The method (qmg_lab/clsf/pickoff_model.py) fits ln r = a1 x + a2 x^2 + b L_tau[x] + k to a characterisation run's
y_i = ln(1 + e_i) - ln(1 + c_i) and applies it to the evaluated run: c_cal,i = (1 + c_i) exp(M_i - M_0) - 1, so to
first order its residual against the table steps is

    c_cal,i - e_i = (c_i - e_i) + (M_i - M_0),     M_i = the model's mean over pair i's windows.

Both runs' c_i - e_i come from the accuracy budget (qmg_lab/budget/sweep.py `pair_errors`, per source, signed), and
the drive frequency from the twin's law f_x(T) = omega_x(T)/2 pi at the predicted die temperature
(gyro_temperature_c on a 1 s grid). The characterisation fit is the method's own (`fit_pickoff_model`): its lag tau
is chosen on the sum of all sources; at that tau the fit is linear in y, so each source's share of the residual is
the residual of the fit to that source's y alone, and the shares add to the total (terms_ppm: RMS over pairs
1..n-1 of each share). The budget is deterministic: the noise of the twin (ARW, bias instability, table steps'
noise) is not in it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from qmg_lab.budget.sweep import ACCURACY_SOURCES, PPM, PairErrors, gyro_temperature_c, pair_errors
from qmg_lab.clsf.pickoff_model import PickoffRatioModel, fit_pickoff_model, window_means
from qmg_lab.config.schema import Config


@dataclass(frozen=True)
class CalibratedBudget:
    """Predicted residual of the calibrated SF against the evaluated run's table steps (ppm)."""

    terms_ppm: dict[str, float]
    total_ppm: float
    pair_errors_ppm: tuple[float, ...]
    clsf_total_ppm: float  # the CLSF-only accuracy of the same run (sweep_accuracy's total)
    lag_tau_s: float

    def to_json(self) -> dict[str, Any]:
        return {
            "terms_ppm": dict(self.terms_ppm),
            "total_ppm": self.total_ppm,
            "pair_errors_ppm": list(self.pair_errors_ppm),
            "clsf_total_ppm": self.clsf_total_ppm,
            "lag_tau_s": self.lag_tau_s,
        }


def drive_frequency_hz(cfg: Config, temp_c: np.ndarray) -> np.ndarray:
    """f_x(T) = sqrt(w^2 + w dw cos 2 theta_w)/2 pi: the drive resonance the PLL holds (sims/gyro_params.py)."""
    s = cfg.sim
    d = temp_c - s.reference_temperature_c
    w = 2.0 * math.pi * s.f0_hz * (1.0 + s.frequency_tempco_ppm_per_c * 1e-6 * d)
    dw = 2.0 * math.pi * (s.freq_mismatch_hz + s.freq_mismatch_tempco_hz_per_c * d)
    return np.sqrt(w * w + w * dw * math.cos(2.0 * math.radians(s.stiffness_axis_deg))) / (2.0 * math.pi)


def _frequency_track(cfg: Config, pe: PairErrors) -> tuple[np.ndarray, np.ndarray]:
    t_end = max(b for wins in pe.windows_s for _, b in wins) + 1.0
    t = np.arange(0.0, t_end, 1.0)
    return t, drive_frequency_hz(cfg, gyro_temperature_c(cfg, t, pe.ramp_start_s))


def _rms(x: np.ndarray) -> float:
    return float(np.sqrt(np.mean(x**2))) if x.size else float("nan")


def calibrated_accuracy(cfg: Config, characterisation: Config) -> CalibratedBudget:
    """The calibrated SF's predicted residual on the run of `cfg`, its model fitted on the run of `characterisation`."""
    ev, ch = pair_errors(cfg), pair_errors(characterisation)
    if ev.rows_ppm.shape[1] < 2 or ch.rows_ppm.shape[1] < 6:
        nan = float("nan")
        return CalibratedBudget(dict.fromkeys(ACCURACY_SOURCES, nan), nan, (), nan, nan)
    t_ch, f_ch = _frequency_track(characterisation, ch)
    t_ev, f_ev = _frequency_track(cfg, ev)
    y = -ch.rows_ppm / PPM  # y_i = ln(1 + e_i) - ln(1 + c_i) ~ -(c_i - e_i), per source
    tau = fit_pickoff_model(t_ch, f_ch, ch.windows_s, y.sum(axis=0)).model.lag_tau_s
    shares = np.empty_like(ev.rows_ppm)
    for k in range(y.shape[0]):
        model = fit_pickoff_model(t_ch, f_ch, ch.windows_s, y[k], tau_grid_s=(tau,)).model
        shares[k] = ev.rows_ppm[k] + _model_changes_ppm(model, t_ev, f_ev, ev.windows_s)
    total = shares.sum(axis=0)
    terms = {n: _rms(r[1:]) for n, r in zip(ACCURACY_SOURCES, shares, strict=True)}
    clsf_total = _rms(ev.rows_ppm.sum(axis=0)[1:])
    return CalibratedBudget(terms, _rms(total[1:]), tuple(float(v) for v in total), clsf_total, tau)


def _model_changes_ppm(
    model: PickoffRatioModel, t: np.ndarray, f: np.ndarray, windows: list[list[tuple[float, float]]]
) -> np.ndarray:
    """(M_i - M_0) in ppm: the model's change of ln r between pair 0 and pair i (its mean over the windows)."""
    m = window_means(t, model.log_ratio(t, f)[np.newaxis, :], windows)[:, 0]
    return (m - m[0]) * PPM
