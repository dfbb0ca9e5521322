"""CLSF accuracy on a bench whose clocks share nothing: the paper campaign over rates, dithers and DS345 offsets.

Every case is the paper campaign (configs/paper_campaign.toml) on the twins, as a user runs it
(`python -m qmg_lab run ... --sim` then `analyze --json`), with every deterministic accuracy source switched
off (qmg_lab.budget.sweep.DETERMINISTIC_OFF: pickoff-ratio drift, mode split, Q and damping drift, forcer
cubic, feedthrough, table ripple; docs/accuracy-budget.md), so that the CLSF estimate must follow the scale
factor the table steps measure. Each case changes:

* the lock-in rate: the HF2's own rates (900, 1800, 3600 Sa/s) and, with the twin told to offer any
  clockbase/integer rate ([sim] hf2_rate_set = "ticks"), rates no HF2 offers (1234.5, 2500 Sa/s);
* the dither frequency between 5 and 10 Hz, none of them commensurate with the rate (a period is a non-integer,
  drifting number of samples, its edges fall between samples);
* the DS345's timebase offset against the HF2's clock: -50, +3 (the twin's default) and +50 ppm, plus the
  default 0.5 ppm wander.

Printed per case: samples per dither period, CLSF accuracy RMS (CLSF vs table steps, ppm), the same with the mean
removed, the table-step analysis against the twin's truth (truth_check) and the CLSF against the twin's truth
(clsf_vs_truth: the estimator's own error, without the table steps' noise). The worst case is the figure of
merit (target <= 20 ppm). With --noise off the twin's ARW, bias instability and pickoff noise are switched off:
what remains is the estimator's systematic error on an asynchronous bench. The default grid pairs every rate
with every dither and cycles the offsets through them (20 campaigns, a few minutes on 2 cores); --full runs
the whole product (60).

    python benchmarks/clsf_robustness.py [--json] [--full] [--noise on|off] [--workers N]
"""

from __future__ import annotations

import argparse
import itertools
import json
import math
import statistics
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from qmg_lab.budget.sweep import DETERMINISTIC_OFF, sim_lines  # noqa: E402 - after the path set-up

RATES = [(900.0, "hf2"), (1800.0, "hf2"), (3600.0, "hf2"), (1234.5, "ticks"), (2500.0, "ticks")]
DITHERS = [5.3, 7.0, 8.6, 9.7]
OFFSETS = [-50.0, 3.0, 50.0]


NOISE_OFF = (
    "arw_deg_per_rt_h = 0.0\nbias_instability_deg_per_h = 0.0\npickoff_noise_vrms_per_rt_hz = 0.0\n"
    "forcer_noise_v_per_rt_hz = 0.0\nauxin_noise_v_rms = 0.0\nauxin_bits = 0\nauxout_bits = 0\n"
)


def case_config(rate_hz: float, rate_set: str, dither_hz: float, offset_ppm: float, noise: bool = True) -> str:
    text = (ROOT / "configs" / "paper_campaign.toml").read_text()
    for old, new in (
        ("demod_rate_hz = 1800.0", f"demod_rate_hz = {rate_hz}"),
        ("frequency_hz = 7.0", f"frequency_hz = {dither_hz}"),
    ):
        if old not in text:
            raise SystemExit(f"configs/paper_campaign.toml no longer holds {old!r}: update this benchmark")
        text = text.replace(old, new)
    return (
        text
        + (sim_lines(DETERMINISTIC_OFF) + f'ds345_timebase_offset_ppm = {offset_ppm}\nhf2_rate_set = "{rate_set}"\n')
        + ("" if noise else NOISE_OFF)
    )


def clsf_vs_truth_rms_ppm(h5: Path) -> float:
    """RMS over step pairs 1..n-1 of (CLSF change - true change), both referred to pair 0 (qmg_lab.analysis.compute)."""
    from qmg_lab.analysis.compute import analyze

    pairs = analyze(h5).pairs
    d = [p.clsf_change_ppm - p.truth_change_ppm for p in pairs[1:]]
    return float(math.sqrt(sum(x * x for x in d) / len(d))) if d else math.nan


def run_case(case: tuple[float, str, float, float], workdir: Path, noise: bool = True) -> dict[str, object]:
    rate_hz, rate_set, dither_hz, offset_ppm = case
    name = f"r{rate_hz:g}_f{dither_hz:g}_o{offset_ppm:g}"
    cfg, h5 = workdir / f"{name}.toml", workdir / f"{name}.h5"
    cfg.write_text(case_config(rate_hz, rate_set, dither_hz, offset_ppm, noise))
    t0 = time.perf_counter()
    run = subprocess.run(
        [sys.executable, "-m", "qmg_lab", "run", str(cfg), "--sim", "-o", str(h5), "--overwrite", "-q"],
        cwd=ROOT,
        capture_output=True,
        text=True,
    )
    if run.returncode != 0:
        return {"case": name, "error": run.stderr.strip()[-400:] or f"exit {run.returncode}"}
    ana = subprocess.run(
        [sys.executable, "-m", "qmg_lab", "analyze", str(h5), "--json"], cwd=ROOT, capture_output=True, text=True
    )
    vs_truth = clsf_vs_truth_rms_ppm(h5) if ana.returncode == 0 else math.nan
    h5.unlink(missing_ok=True)
    if ana.returncode != 0:
        return {"case": name, "error": ana.stderr.strip()[-400:]}
    res = json.loads(ana.stdout)
    return {
        "case": name,
        "rate_hz": rate_hz,
        "rate_set": rate_set,
        "dither_hz": dither_hz,
        "ds345_offset_ppm": offset_ppm,
        "samples_per_period": rate_hz / dither_hz,
        "clsf_accuracy_rms_ppm": res.get("clsf_accuracy_rms_ppm"),
        "clsf_accuracy_rms_ppm_mean_removed": res.get("clsf_accuracy_rms_ppm_mean_removed"),
        "truth_check_rms_ppm": res.get("truth_check_rms_ppm"),
        "clsf_vs_truth_rms_ppm": vs_truth,
        "n_step_pairs": res.get("n_step_pairs"),
        "wall_s": round(time.perf_counter() - t0, 1),
    }


def grid(full: bool) -> list[tuple[float, str, float, float]]:
    if full:
        return [(r, s, f, o) for (r, s), f, o in itertools.product(RATES, DITHERS, OFFSETS)]
    offsets = itertools.cycle(OFFSETS)
    return [(r, s, f, next(offsets)) for (r, s), f in itertools.product(RATES, DITHERS)]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--full", action="store_true", help="every rate x dither x offset (60 campaigns)")
    ap.add_argument("--noise", choices=("on", "off"), default="on", help="the twin's noise sources")
    ap.add_argument("--workers", type=int, default=2)
    args = ap.parse_args()
    cases = grid(args.full)
    with tempfile.TemporaryDirectory(prefix="qmg-robust-") as d, ThreadPoolExecutor(args.workers) as pool:
        results = list(pool.map(lambda c: run_case(c, Path(d), args.noise == "on"), cases))
    ok = [r for r in results if "error" not in r and r["clsf_accuracy_rms_ppm"] is not None]
    worst = max(ok, key=lambda r: float(r["clsf_accuracy_rms_ppm"])) if ok else None
    summary = {
        "cases": len(results),
        "failed": len(results) - len(ok),
        "worst_clsf_accuracy_rms_ppm": worst["clsf_accuracy_rms_ppm"] if worst else None,
        "worst_case": worst["case"] if worst else None,
        "median_clsf_accuracy_rms_ppm": statistics.median(float(r["clsf_accuracy_rms_ppm"]) for r in ok)
        if ok
        else None,
        "worst_clsf_vs_truth_rms_ppm": max(float(r["clsf_vs_truth_rms_ppm"]) for r in ok) if ok else None,
        "noise": args.noise,
        "target_ppm": 20.0,
    }
    if args.json:
        print(json.dumps({"results": results, **summary}, indent=1))
        return
    print(f"{'case':>22} {'Sa/period':>10} {'acc RMS':>8} {'mean rem.':>9} {'truth chk':>9} {'vs truth':>9}")
    for r in results:
        if "error" in r:
            print(f"{r['case']:>22}  FAILED: {r['error']}")
            continue
        print(
            f"{r['case']:>22} {r['samples_per_period']:10.3f} {r['clsf_accuracy_rms_ppm']:8.1f} "
            f"{r['clsf_accuracy_rms_ppm_mean_removed']:9.1f} {r['truth_check_rms_ppm']:9.1f} "
            f"{r['clsf_vs_truth_rms_ppm']:9.1f}"
        )
    print(json.dumps(summary))


if __name__ == "__main__":
    main()
