"""The whole-SF calibration end to end on the twins (CLI in a subprocess: run, characterize sf-model, analyze
--sf-model), with the random sources off so that only the deterministic physics acts.

* Exactness: with only the pickoff ratio's parts on (front end lagging by 300 s, transducer, quadratic), the model
  fitted on a characterisation run recovers the twin's known ratio law on another run: its change of ln r over the
  evaluated run's pairs equals ln(G_py/G_px) computed from the twin's parameters at the recorded die temperature and
  its lag (the board), and the calibrated SF then follows /truth.
* Budget against twin (qmg_lab/budget/calibrated.py): the calibrated SF's residual against the table steps lands
  within 30 % of the prediction plus 3 ppm. With the default critically damped sense PIs the prediction is ~0 (no
  source leaves more than 0.02 ppm), so what the twin shows is the noise QUIET leaves on: the AuxIn's reading
  noise and quantisation in the CLSF estimate, white at q = 16 ppm sqrt(s) (qmg_lab.budget.noise), 1.5 ppm over a
  pair's 2 x 55 s; the residual against pair 0 must then stay within the 3 ppm floor plus 3 sqrt(2) of that
  (9.5 ppm); with the zero-on-pole PIs
  ([loops] sense_pi_design) the mode split's loop tail in the table steps leaves a residual the budget must size,
  for the default sources together and for the split alone. The shares of a combined run depend on the lag the fit
  picks for all sources together, so a share cannot be run alone in the twin; the sources alone are run instead.
"""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest

from qmg_lab.budget.calibrated import calibrated_accuracy
from qmg_lab.budget.noise import noise_budget
from qmg_lab.budget.sweep import DETERMINISTIC_OFF, sim_lines
from qmg_lab.clsf.pickoff_model import first_order_lag
from qmg_lab.config.schema import parse_config

ROOT = Path(__file__).resolve().parents[2]
QUIET = {
    "arw_deg_per_rt_h": 0.0,
    "bias_instability_deg_per_h": 0.0,
    "pickoff_noise_vrms_per_rt_hz": 0.0,
    "forcer_noise_v_per_rt_hz": 0.0,
}
PICKOFF = {
    "pickoff_electronics_tempco_ppm_per_c": 40.0,
    "pickoff_transducer_tempco_ppm_per_c": 20.0,
    "pickoff_ratio_tempco2_ppm_per_c2": 0.5,
    "frontend_thermal_tau_s": 300.0,
}
# on the sense axis (theta_w = 0): the budget's tail model has no drive-sense stiffness coupling
# (docs/accuracy-budget.md, "A limit found"); the same source as tests/integration/test_sweep_budget.py
SPLIT = {"freq_mismatch_hz": 0.05, "freq_mismatch_tempco_hz_per_c": 0.01, "stiffness_axis_deg": 0.0}
REL_TOL, PPM_FLOOR = 0.30, 3.0

pytestmark = pytest.mark.slow


SHORTER = {
    # the paper campaign at 1 degC/min: 8 step pairs
    "paper_campaign.toml": (
        ("chamber_ramp_c_per_min = 0.25", "chamber_ramp_c_per_min = 1.0"),
        ("chamber_soak_s = 300.0", "chamber_soak_s = 60.0"),
        ("chamber_end_hold_s = 600.0", "chamber_end_hold_s = 300.0"),
    ),
    # the characterisation at 0.25 degC/min: 14 step pairs
    "sf_characterisation.toml": (("chamber_ramp_c_per_min = 0.1", "chamber_ramp_c_per_min = 0.25"),),
}


AGC_LINE = "agc_zero_offset_hz = 0.05"  # a [loops] line of both configurations


def _config(name: str, sim: dict[str, float], design: str = "critically_damped") -> str:
    text = (ROOT / "configs" / name).read_text(encoding="utf-8")
    for old, new in (*SHORTER[name], (AGC_LINE, f'{AGC_LINE}\nsense_pi_design = "{design}"')):
        assert old in text
        text = text.replace(old, new, 1)
    return text + sim_lines(sim)  # [sim] is the files' last section


def qmg(*args: str) -> str:
    proc = subprocess.run(
        [sys.executable, "-m", "qmg_lab", *args], check=False, capture_output=True, text=True, cwd=ROOT, timeout=1800
    )
    if proc.returncode != 0:
        raise AssertionError(f"qmg-lab {' '.join(args)} exited {proc.returncode}:\n{proc.stdout}\n{proc.stderr}")
    return proc.stdout


def _calibrate(
    tmp: Path, sim: dict[str, float], design: str = "critically_damped"
) -> tuple[dict, dict, Path, str, str]:
    char_text = _config("sf_characterisation.toml", sim, design)
    eval_text = _config("paper_campaign.toml", sim, design)
    (tmp / "char.toml").write_text(char_text, encoding="utf-8")
    (tmp / "eval.toml").write_text(eval_text, encoding="utf-8")
    qmg("run", str(tmp / "char.toml"), "--sim", "-o", str(tmp / "char.h5"), "-q")
    qmg("characterize", "sf-model", str(tmp / "char.h5"), "-o", str(tmp / "model.json"))
    (tmp / "char.h5").unlink()
    qmg("run", str(tmp / "eval.toml"), "--sim", "-o", str(tmp / "eval.h5"), "-q")
    result = json.loads(qmg("analyze", str(tmp / "eval.h5"), "--sf-model", str(tmp / "model.json"), "--json"))
    model = json.loads((tmp / "model.json").read_text(encoding="utf-8"))
    return result, model, tmp / "eval.h5", char_text, eval_text


def test_known_ratio_recovered_and_calibrated_sf_follows_truth(tmp_path: Path) -> None:
    sim = {**QUIET, **DETERMINISTIC_OFF, **PICKOFF}
    result, model, run, _, eval_text = _calibrate(tmp_path, sim)
    cfg = parse_config(eval_text)
    s = cfg.sim
    with h5py.File(run, "r") as f:  # an outside reader: the twin's die temperature and the drive frequency
        t = f["truth/time"][::1800]
        die = f["truth/temperature"][::1800]
        freq = f["lockin/drive_frequency"][::1800]
    board = first_order_lag(t, die, s.frontend_thermal_tau_s)  # the twin's board: one first-order lag of the die
    d, d_fe = die - s.reference_temperature_c, board - s.reference_temperature_c
    known = np.log(
        1.0
        + s.pickoff_transducer_tempco_ppm_per_c * 1e-6 * d
        + s.pickoff_ratio_tempco2_ppm_per_c2 * 1e-6 * d * d
        + s.pickoff_electronics_tempco_ppm_per_c * 1e-6 * d_fe
    )
    x = freq - model["anchor_hz"]
    fitted = (
        model["linear_per_hz"] * x
        + model["quadratic_per_hz2"] * x * x
        + model["lagged_per_hz"] * first_order_lag(t, x, model["lag_tau_s"])
    )
    span_ppm = (known.max() - known.min()) * 1e6
    err_ppm = ((fitted - fitted[0]) - (known - known[0])) * 1e6
    worst = float(np.max(np.abs(err_ppm[t > 60.0])))
    cal = result["calibrated_sf"]
    figures = f"span {span_ppm:.0f} ppm, worst {worst:.2f} ppm, model {model}, calibrated {cal}"
    assert span_ppm > 200.0, figures  # the ratio moves by hundreds of ppm over the run: what CLSF alone misses
    assert worst < 0.02 * span_ppm, figures  # the law recovered to 2 % of its swing
    assert cal["clsf_vs_truth_ppm"] > 100.0, figures
    assert cal["vs_truth_ppm"] < 0.05 * cal["clsf_vs_truth_ppm"], figures


@pytest.mark.parametrize(
    ("case", "design"),
    [
        ("defaults", "critically_damped"),  # every deterministic source at its default: the budget predicts ~0
        ("defaults", "zero_on_pole"),  # the same with the split's loop tail in the table steps
        ("mode_split", "zero_on_pole"),  # that tail's source alone
    ],
)
def test_calibrated_residual_lands_on_the_budget(case: str, design: str, tmp_path: Path) -> None:
    sim = {**QUIET} if case == "defaults" else {**QUIET, **DETERMINISTIC_OFF, **SPLIT}
    result, _, _, char_text, eval_text = _calibrate(tmp_path, sim, design)
    budget = calibrated_accuracy(parse_config(eval_text), parse_config(char_text))
    measured = result["calibrated_sf"]["accuracy_vs_table_ppm"]
    figures = f"twin {measured:.2f} ppm, budget {budget.to_json()}"
    if design == "critically_damped":
        cfg = parse_config(eval_text)
        q = math.sqrt(sum(src.white_ppm_rt_s**2 for src in noise_budget(cfg, sim_blocks=True).sources))
        sigma_pair = q / math.sqrt(2.0 * (cfg.plan.dwell_s - cfg.plan.settle_s))
        assert budget.total_ppm < 0.1, figures
        assert measured <= budget.total_ppm + PPM_FLOOR + 3 * math.sqrt(2) * sigma_pair, figures
    else:
        assert budget.total_ppm > 2 * PPM_FLOOR, figures
        assert measured == pytest.approx(budget.total_ppm, rel=REL_TOL, abs=PPM_FLOOR), figures
