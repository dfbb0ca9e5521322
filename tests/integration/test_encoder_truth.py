"""The table-step truth on the HF2's clock: the paper campaign through the real CLI, its step windows and table rates
taken from the table encoder recorded on the HF2 DIO (/lockin/table_encoder), judged against the twin's /truth.

Expected figures come from the model, not from earlier runs:
* Noise off and every deterministic accuracy source off (qmg_lab.budget.sweep.DETERMINISTIC_OFF), the table-step
  SF equals the truth up to the recording's own quantisation and the window cut: the AuxIn reading of the rate
  output is rounded to q = 2 R / 2^bits, an error of sigma q/sqrt(12) per sample, so a window mean over N samples
  carries q / sqrt(12 N) (taken as independent: the dither leak sweeps the output across many steps); a pair's SF
  (O+ - O-)/(2 Omega) carries sqrt(2) of that over 2 Omega SF, and e_i - t_i two pairs' (sqrt 2 more). The whole-
  dither-period cut moves a window's centre by at most half a dither period against the truth's window, where the
  SF moves at most |dSF/dt| (twice the fastest change from pair to pair of /truth). Bound: 5 sigma + that.
* The encoder's rate of each window is the servo's rate, the command times (1 + table_rate_scale_error_ppm), to
  1.5 dt / T (qmg_lab/analysis/encoder.py, the worst case of the transition-time quantisation).
* The paper campaign as shipped: the truth check is the budget's own table-step error (SweepAccuracy.
  table_errors_ppm: the loop tails of the mode split and the damping, the forcer cubic, the table ripple; with the
  default critically damped sense PIs 0.01 ppm) plus the gyro noise in the windows: per window sigma_w^2 = N^2/T +
  (0.664 B)^2 (ARW N, bias-instability floor B), per pair SF sigma_w / (sqrt 2 Omega), per e_i - t_i sqrt 2 of that
  (11.6 ppm); expected sqrt(model^2 + sigma^2), within the budget's first-order 15 % of the model plus 30 % of sigma
  (the RMS of 24 pairs scatters by 1/sqrt(48) = 14 %, and the flicker floor's 0.664 B is the Allan deviation's, a
  first-order stand-in for the difference of two window means).
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

from qmg_lab.budget.sweep import DETERMINISTIC_OFF, sim_lines, sweep_accuracy
from qmg_lab.config.schema import Config, parse_config
from sims.gyro_params import NOISE_OFF

ROOT = Path(__file__).resolve().parents[2]
PAPER = ROOT / "configs" / "paper_campaign.toml"

pytestmark = pytest.mark.slow


def _qmg(*args: str) -> dict:
    proc = subprocess.run(
        [sys.executable, "-m", "qmg_lab", *args], capture_output=True, text=True, cwd=ROOT, timeout=900
    )
    assert proc.returncode == 0, f"qmg-lab {' '.join(args)} exited {proc.returncode}:\n{proc.stdout}\n{proc.stderr}"
    return json.loads(proc.stdout) if "--json" in args else {}


def _campaign(tmp: Path, sim: dict[str, object]) -> tuple[Path, Config]:
    text = PAPER.read_text(encoding="utf-8") + sim_lines(sim)  # [sim] is the file's last section
    cfg_path = tmp / "campaign.toml"
    cfg_path.write_text(text, encoding="utf-8")
    out = tmp / "run.h5"
    _qmg("run", str(cfg_path), "--sim", "-o", str(out), "-q")
    return out, parse_config(text, str(cfg_path))


def test_encoder_timed_steps_equal_the_truth_with_noise_and_sources_off(tmp_path: Path) -> None:
    noise_off = {k: v for k, v in NOISE_OFF.items() if k != "auxout_bits"} | {"auxin_noise_v_rms": 0.0}
    run, cfg = _campaign(tmp_path, {**DETERMINISTIC_OFF, **noise_off})
    res = _qmg("analyze", str(run), "--json")
    pairs = res["pairs"]
    assert any("from the table encoder: 50 of 50 moving steps" in n for n in res["notes"])
    assert len(pairs) == 25
    with h5py.File(run, "r") as f:
        fs = 1.0 / float(np.median(np.diff(f["lockin/time"][:1000])))
    s = cfg.sim
    q = 2 * s.auxin_range_v / 2**s.auxin_bits
    dt = 1.0 / fs
    truth_ppm = np.array([p["truth_change_ppm"] for p in pairs])
    t_mid = np.array([p["t_mid_s"] for p in pairs])
    sf_rate = 2e-6 * float(np.max(np.abs(np.diff(truth_ppm) / np.diff(t_mid))))  # 1/s, twice the fastest pair-to-pair
    for p in pairs:
        for key, (a, b) in (("rate_plus_dps", p["window_plus_s"]), ("rate_minus_dps", p["window_minus_s"])):
            commanded = math.copysign(cfg.plan.table_rate_dps, p[key])
            assert abs(p[key] / (commanded * (1 + s.table_rate_scale_error_ppm * 1e-6)) - 1) <= 1.5 * dt / (b - a)
    n = min(b - a for p in pairs for a, b in (p["window_plus_s"], p["window_minus_s"])) * fs
    sigma_pair = math.sqrt(2) * q / math.sqrt(12 * n) / (2 * cfg.plan.table_rate_dps * s.sf_true_v_per_dps)
    bound_ppm = (5 * math.sqrt(2) * sigma_pair + sf_rate * 0.5 / cfg.dither.frequency_hz) * 1e6
    worst = max(abs(p["true_change_ppm"] - p["truth_change_ppm"]) for p in pairs)
    assert worst <= bound_ppm, f"table steps off the truth by {worst:.2f} ppm, bound {bound_ppm:.2f} ppm"


def test_paper_campaign_truth_check_is_the_budgets_table_error(tmp_path: Path) -> None:
    run, cfg = _campaign(tmp_path, {})
    res = _qmg("analyze", str(run), "--json")
    assert any("from the table encoder" in n for n in res["notes"])
    model = np.array(sweep_accuracy(cfg).table_errors_ppm)
    assert model.size == res["n_step_pairs"]
    model_rms = float(np.sqrt(np.mean(model**2)))
    s = cfg.sim
    t_win = cfg.plan.dwell_s - cfg.plan.settle_s
    arw = s.arw_deg_per_rt_h / 60.0  # deg/sqrt(s)
    floor = 0.664 * s.bias_instability_deg_per_h / 3600.0  # deg/s
    sigma_w = math.sqrt(arw**2 / t_win + floor**2)
    sigma_ppm = math.sqrt(2) * sigma_w / (math.sqrt(2) * cfg.plan.table_rate_dps) * 1e6
    expected = math.sqrt(model_rms**2 + sigma_ppm**2)
    assert abs(res["truth_check_rms_ppm"] - expected) <= 0.15 * model_rms + 0.3 * sigma_ppm
