"""The table steps' own noise as a judge: `truth check RMS` of the paper campaign on the twins, seed by seed, at the
paper's table rate and at a faster one, beside the figure `analyze` predicts from the run's own gyro noise and the
model's figure from the [sim] noise values.

For each (table rate, seed) it writes configs/paper_campaign.toml with `[sim] seed` and `[plan] table_rate_dps`
set (tomlkit, the rest of the file as shipped) under --dir, runs `python -m qmg_lab run CONFIG --sim -o RUN.h5 -q`
and `python -m qmg_lab analyze RUN.h5 --json`, and reads `truth_check_rms_ppm` (RMS over pairs 1..n-1 of e_i - t_i,
the table-step SF change against the twin's /truth) and `table_step_noise_ppm` (the same RMS predicted from the
run's own Allan deviation of the dither-free rate output, qmg_lab/analysis/compute.py). The model's figure:
a window of T = dwell_s - settle_s seconds averages the gyro's noise to
    sigma_w^2 = N^2 / T + (0.664 B)^2        (N the ARW in deg/s/sqrt(Hz), B the bias instability, [sim])
a pair's SF change carries sqrt(2) sigma_w / (2 Omega) (two window means), and e_i - t_i, referred to pair 0,
sqrt(2) of that again: sigma_w / Omega. Printed per run: the truth check, the predicted figure with its 68 % bounds,
the truth check with its mean over pairs 1..n-1 removed (pair 0's draw eps_0, common to every e_i, taken out)
beside its prediction sqrt(predicted^2 - pair 0's share^2) ("pairs own"), and the model; per rate the seeds' mean
and RMS of each.

    python benchmarks/truth_check_noise.py [--seeds 1 2 3 4 5] [--fast-seeds 1 2 3] [--fast-rate 20] [--json]
        [--dir /tmp/truth_check_noise] [--reuse]

--reuse analyses the run files already in --dir (from an earlier call with the same arguments) instead of
running the campaigns again. Run by hand, not by CI (each campaign takes 10-60 s of wall time).
"""

from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from qmg_lab.config.edit import with_values  # noqa: E402 - imported after sys.path points at this checkout
from qmg_lab.config.schema import Config, parse_config  # noqa: E402

PAPER = ROOT / "configs" / "paper_campaign.toml"
#: IEEE 952's flicker floor: the Allan deviation's minimum is 0.664 B
FLICKER_FLOOR = 0.664


def model_ppm(cfg: Config) -> float:
    """sigma_w / Omega in ppm (module docstring), from the configuration's [sim] noise and [plan] windows."""
    s = cfg.sim
    n_dps_rt_hz = s.arw_dps_per_rt_hz if s.arw_dps_per_rt_hz is not None else s.arw_deg_per_rt_h / 60.0
    window_s = cfg.plan.dwell_s - cfg.plan.settle_s
    sigma_w_dps = math.sqrt(n_dps_rt_hz**2 / window_s + (FLICKER_FLOOR * s.bias_instability_deg_per_h / 3600.0) ** 2)
    return 1e6 * sigma_w_dps / cfg.plan.table_rate_dps


def _qmg(*args: str) -> str:
    proc = subprocess.run([sys.executable, "-m", "qmg_lab", *args], capture_output=True, text=True, cwd=ROOT)
    if proc.returncode != 0:
        raise SystemExit(f"qmg-lab {' '.join(args)} exited {proc.returncode}:\n{proc.stdout}\n{proc.stderr}")
    return proc.stdout


def one_run(folder: Path, rate_dps: float, seed: int, reuse: bool) -> dict[str, Any]:
    """Run (or reuse) the paper campaign at this table rate and seed; its analysis's figures."""
    text = with_values(PAPER.read_text(encoding="utf-8"), {"sim.seed": seed, "plan.table_rate_dps": rate_dps})
    stem = f"paper_{rate_dps:g}dps_seed{seed}"
    cfg_path, run = folder / f"{stem}.toml", folder / f"{stem}.h5"
    cfg_path.write_text(text, encoding="utf-8")
    if not (reuse and run.exists()):
        _qmg("run", str(cfg_path), "--sim", "-o", str(run), "-q", "--overwrite")
    res = json.loads(_qmg("analyze", str(run), "--json"))
    d = [p["true_change_ppm"] - p["truth_change_ppm"] for p in res["pairs"][1:]]
    mean = sum(d) / len(d)
    return {
        "table_rate_dps": rate_dps,
        "seed": seed,
        "n_pairs": len(res["pairs"]),
        "truth_check_rms_ppm": res["truth_check_rms_ppm"],
        "truth_check_rms_ppm_mean_removed": math.sqrt(sum((x - mean) ** 2 for x in d) / len(d)),
        "table_step_noise_ppm": res.get("table_step_noise_ppm"),
        "table_step_noise_ppm_low": res.get("table_step_noise_ppm_low"),
        "table_step_noise_ppm_high": res.get("table_step_noise_ppm_high"),
        "table_step_noise_pair0_ppm": res.get("table_step_noise_pair0_ppm"),
        "model_ppm": model_ppm(parse_config(text, str(cfg_path))),
    }


def _rms(values: list[float]) -> float:
    return math.sqrt(sum(v * v for v in values) / len(values))


def summary(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Per table rate: the seeds' mean and RMS of the measured truth check, the mean predicted figure, the model."""
    out = []
    for rate in sorted({r["table_rate_dps"] for r in rows}):
        mine = [r for r in rows if r["table_rate_dps"] == rate]
        measured = [r["truth_check_rms_ppm"] for r in mine]
        spread = [r["truth_check_rms_ppm_mean_removed"] for r in mine]
        predicted = [r["table_step_noise_ppm"] for r in mine if r["table_step_noise_ppm"] is not None]
        own = [
            math.sqrt(r["table_step_noise_ppm"] ** 2 - r["table_step_noise_pair0_ppm"] ** 2)
            for r in mine
            if r["table_step_noise_ppm"] is not None
        ]
        out.append(
            {
                "table_rate_dps": rate,
                "seeds": [r["seed"] for r in mine],
                "measured_mean_ppm": sum(measured) / len(measured),
                "measured_rms_ppm": _rms(measured),
                "predicted_rms_ppm": _rms(predicted) if predicted else None,
                "measured_mean_removed_rms_ppm": _rms(spread),
                "predicted_pairs_own_rms_ppm": _rms(own) if own else None,
                "model_ppm": mine[0]["model_ppm"],
            }
        )
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3, 4, 5])
    ap.add_argument("--fast-seeds", type=int, nargs="*", default=[1, 2, 3])
    ap.add_argument("--fast-rate", type=float, default=20.0, help="the faster table rate, deg/s")
    ap.add_argument("--dir", type=Path, default=Path("/tmp/truth_check_noise"))
    ap.add_argument("--reuse", action="store_true", help="analyse the run files already in --dir")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    args.dir.mkdir(parents=True, exist_ok=True)
    paper_rate = parse_config(PAPER.read_text(encoding="utf-8"), str(PAPER)).plan.table_rate_dps
    todo = [(paper_rate, s) for s in args.seeds] + [(args.fast_rate, s) for s in args.fast_seeds]
    rows = [one_run(args.dir, rate, seed, args.reuse) for rate, seed in todo]
    result = {"runs": rows, "summary": summary(rows)}
    if args.json:
        print(json.dumps(result, indent=2))
        return
    print(
        f"{'deg/s':>5} {'seed':>4} {'pairs':>5} {'truth check':>11} {'predicted (68 %)':>22} {'mean removed':>12} "
        f"{'pairs own':>9} {'model':>6}   (ppm RMS over pairs 1..n-1)"
    )
    for r in rows:
        pred = r["table_step_noise_ppm"]
        band = (
            "-"
            if pred is None
            else f"{pred:.2f} ({r['table_step_noise_ppm_low']:.2f}-{r['table_step_noise_ppm_high']:.2f})"
        )
        own = "-" if pred is None else f"{math.sqrt(pred**2 - r['table_step_noise_pair0_ppm'] ** 2):.2f}"
        print(
            f"{r['table_rate_dps']:>5g} {r['seed']:>4} {r['n_pairs']:>5} {r['truth_check_rms_ppm']:>11.2f} {band:>22} "
            f"{r['truth_check_rms_ppm_mean_removed']:>12.2f} {own:>9} {r['model_ppm']:>6.2f}"
        )
    for s in result["summary"]:
        pred, own = s["predicted_rms_ppm"], s["predicted_pairs_own_rms_ppm"]
        print(
            f"{s['table_rate_dps']:g} deg/s, seeds {s['seeds']}: truth check mean {s['measured_mean_ppm']:.2f}, "
            f"RMS {s['measured_rms_ppm']:.2f}, predicted RMS {'-' if pred is None else f'{pred:.2f}'}; mean removed "
            f"RMS {s['measured_mean_removed_rms_ppm']:.2f}, predicted {'-' if own is None else f'{own:.2f}'}; "
            f"model {s['model_ppm']:.2f} ppm"
        )


if __name__ == "__main__":
    main()
