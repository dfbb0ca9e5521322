"""The paper's figures beside what qmg-lab gets on the simulated twins: the table of docs/paper-comparison.md.

Runs, each as a user would (`python -m qmg_lab ...`):
  1. configs/paper_campaign.toml --sim      (Figs. 4-6: CLSF accuracy over the 25 -> 35 degC sweep)
  2. configs/clsf_adev.toml --sim           (Fig. 7: CLSF precision in correct mode, 3 h)
  3. characterize bandwidth / linearity     (Figs. 3 and 2)
and analyses the files with `qmg-lab analyze --json`; `qmg-lab budget configs/clsf_adev.toml --json --sim` gives
the noise budget's prediction for the precision rows, and `qmg-lab budget configs/paper_campaign.toml` the sweep's
accuracy and linearity. Prints a Markdown table (or --json).

    python benchmarks/paper_comparison.py [--json]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

import allantools
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from qmg_lab.storage.reader import read_run  # noqa: E402 - imported after sys.path points at this checkout


def qmg(*args: str) -> str:
    proc = subprocess.run([sys.executable, "-m", "qmg_lab", *args], cwd=ROOT, capture_output=True, text=True)
    if proc.returncode != 0:
        raise SystemExit(f"qmg-lab {' '.join(args)} failed ({proc.returncode}):\n{proc.stderr}")
    return proc.stdout


def adev_at(values: np.ndarray, rate_hz: float, taus: list[float]) -> list[float]:
    t, ad, _, _ = allantools.oadev(values, rate=rate_hz, data_type="freq", taus=np.array(taus))
    return [float(np.interp(x, t, ad)) for x in taus]


def one_second_means(t: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Means of v over consecutive whole seconds of t (any sample rate; partial seconds at the ends dropped)."""
    sec = np.floor(t - t[0]).astype(np.int64)
    counts = np.bincount(sec)
    sums = np.bincount(sec, weights=v)
    full = counts >= 0.9 * np.median(counts)
    return (sums / np.maximum(counts, 1))[full]


def self_calibrated_sf_adev(path: Path) -> tuple[list[float], list[float]]:
    """ADEV (relative) at 60 s and 2000 s after the soak: of the twin's actual SF under CLSF correction (1 s
    means of /truth) and of the CLSF estimate itself (one value per dither period)."""
    run = read_run(path, select=("truth/time", "truth/scale_factor", "clsf/time", "clsf/sf_change_estimate"))
    kinds = list(run.steps["kind"])
    t0 = float(run.steps["t_end"][kinds.index("soak")])
    tt, sf = run.groups["truth"]["time"], run.groups["truth"]["scale_factor"]
    ct, est = run.groups["clsf"]["time"], run.groups["clsf"]["sf_change_estimate"]
    keep = tt >= t0
    per_s = one_second_means(tt[keep], sf[keep])
    k = ct >= t0
    rate = 1.0 / float(np.median(np.diff(ct[k])))
    return adev_at(per_s / per_s.mean() - 1, 1.0, [60.0, 2000.0]), adev_at(est[k], rate, [60.0, 2000.0])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="qmg-paper-") as d:
        tmp = Path(d)
        sweep, adev = tmp / "paper.h5", tmp / "adev.h5"
        qmg("run", "configs/paper_campaign.toml", "--sim", "-o", str(sweep), "-q")
        a = json.loads(qmg("analyze", str(sweep), "--json"))
        qmg("run", "configs/clsf_adev.toml", "--sim", "-o", str(adev), "-q")
        b = json.loads(qmg("analyze", str(adev), "--json"))
        truth_adev, est_adev = self_calibrated_sf_adev(adev)
        bud = json.loads(qmg("budget", "configs/clsf_adev.toml", "--json", "--sim"))
        acc = json.loads(qmg("budget", "configs/paper_campaign.toml", "--json", "--sim"))["accuracy"]
        bw = json.loads(qmg("characterize", "bandwidth", "configs/paper_campaign.toml", "--sim", "--json"))
        lin = json.loads(qmg("characterize", "linearity", "configs/paper_campaign.toml", "--sim", "--json"))
    est_b, sf_b = bud["adev_ppm"], bud["adev_self_calibrated_sf_ppm"]
    rows = [
        (
            "CLSF accuracy, RMS over 25 -> 35 degC (Fig. 6b)",
            "350 ppm",
            f"{a['clsf_accuracy_rms_ppm']:.0f} ppm",
            f"{acc['total_ppm']:.0f} ppm",
        ),
        (
            "  same, mean removed",
            "-",
            f"{a['clsf_accuracy_rms_ppm_mean_removed']:.0f} ppm",
            f"{acc['total_mean_removed_ppm']:.0f} ppm",
        ),
        ("Dominant accuracy source over the sweep", "-", "-", str(acc["dominant_accuracy_source"])),
        (
            "True SF change over the sweep (Fig. 6a)",
            "~1000 ppm/degC class",
            f"{a['sf_true_change_ppm']:.0f} ppm p-p",
            "-",
        ),
        (
            "Table-step SF vs the twin's truth (encoder-timed)",
            "-",
            f"{a['truth_check_rms_ppm']:.0f} ppm RMS",
            f"{np.sqrt(np.mean(np.square(acc['table_errors_ppm']))):.0f} ppm RMS (without noise)",
        ),
        (
            "CLSF precision at 60 s, correct mode (Fig. 7)",
            "30 ppm",
            f"{truth_adev[0] * 1e6:.1f} ppm (actual SF), {est_adev[0] * 1e6:.1f} ppm (estimate)",
            f"{sf_b['60']:.1f} ppm (actual SF), {est_b['60']:.1f} ppm (estimate)",
        ),
        (
            "CLSF precision at 2000 s, correct mode (Fig. 7)",
            "1 ppm",
            f"{truth_adev[1] * 1e6:.2f} ppm (actual SF), {est_adev[1] * 1e6:.2f} ppm (estimate)",
            f"{sf_b['2000']:.2f} ppm (actual SF), {est_b['2000']:.2f} ppm (estimate)",
        ),
        ("Dominant CLSF noise source at 60 s", "-", "-", str(bud["dominant_at_60s"])),
        ("FTR bandwidth (Fig. 3)", "2 Hz", f"{bw['bandwidth_hz']:.2f} Hz", "-"),
        ("FTR settling time, 2 %", "0.5 s", f"{bw['settling_time_s']:.2f} s", "-"),
        (
            "Linearity over +-5 deg/s (Fig. 2)",
            "0.5 % FS RMS",
            f"{lin['nonlinearity_rms_pct_fs']:.4f} % FS RMS",
            f"{acc['nonlinearity_rms_pct_fs']:.4f} % FS RMS (without noise)",
        ),
        ("Nominal scale factor", "0.06 V/(deg/s)", f"{lin['sf_v_per_dps']:.5f} V/(deg/s)", "-"),
        ("Angle random walk", "0.02 deg/sqrt(h)", f"{b['arw_deg_per_rt_h']:.4f} deg/sqrt(h)", "-"),
    ]
    if args.json:
        print(json.dumps({r[0].strip(): {"paper": r[1], "qmg_lab_sim": r[2], "budget": r[3]} for r in rows}))
        return
    print("| quantity | paper | qmg-lab on the twins | budget predicts |")
    print("|---|---|---|---|")
    for r in rows:
        print(f"| {r[0].strip()} | {r[1]} | {r[2]} | {r[3]} |")


if __name__ == "__main__":
    main()
