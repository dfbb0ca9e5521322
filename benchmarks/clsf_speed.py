"""Cost of the CLSF estimator alone, per lock-in block, on the blocks of a real twin campaign.

1. Records: the paper campaign (configs/paper_campaign.toml, 55 simulated minutes, the HF2 twin's 2 s blocks at
   1800 Sa/s) runs once on the twins in this process at the study storage level; every call the campaign makes
   on its ClsfEstimator (set_stream_timing, process with the block's arrays, hold, release_hold, reset_buffer) is
   recorded in order. `--minutes M` shortens the chamber's end hold for a quicker look.
2. Replays: a fresh estimator receives the same calls `--runs` times; only `process` is timed
   (time.perf_counter around each call). Printed: the median over runs of the mean ms per block, samples per
   second, and the implied real-time factor of the estimator alone (simulated s / s spent in process), plus the
   number of periods it returned.
3. With `--reference REV`: the estimator of git revision REV (its qmg_lab/clsf, loaded from `git show` into a
   temporary package) replays the same calls, alternating with this one: its ms per block, the speed-up
   (median of the per-run ratios), and the largest difference of every ClsfPeriods field between the two
   (0 when bit-identical; relative to the field's magnitude, eta and sf_change_estimate relative to 1).

    python benchmarks/clsf_speed.py [--json] [--runs N] [--minutes M] [--reference REV] [--block-s S]

`--block-s 10` records the campaign with the HF2 twin's blocks 10 s long (as the shipped studies run it) instead
of the config's 2 s: the estimator's fixed cost per call then weighs five times less per sample.

Target (this benchmark's task): >= 5x less per block than 38cd4c6 (about 2-3 ms per 2 s block of 3600 samples on
a quiet 2-core machine). These machines are shared and noisy: quote the median and the load average.
"""

from __future__ import annotations

import argparse
import importlib
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import tomlkit

from qmg_lab.campaign.pipeline import new_run_file
from qmg_lab.campaign.plan import checked_plan
from qmg_lab.campaign.runner import CampaignRunner
from qmg_lab.clsf.demod_filter import DemodFilter
from qmg_lab.clsf.estimator import ClsfEstimator, ClsfPeriods
from qmg_lab.config.schema import parse_config
from qmg_lab.instruments import INSTRUMENT_NAMES
from qmg_lab.station import build_station, make_world

ROOT = Path(__file__).resolve().parents[1]

Call = tuple[str, tuple[Any, ...]]


def paper_text(end_hold_s: float | None, block_s: float | None = None) -> str:
    """The paper campaign on the twins at the study storage level (optionally with a shorter end hold, and with
    the HF2 twin's blocks `block_s` long instead of the configured 2 s: [lockin] sim_poll_interval_s)."""
    doc = tomllib.loads((ROOT / "configs" / "paper_campaign.toml").read_text())
    for name in INSTRUMENT_NAMES:
        doc[name]["sim"] = True
    doc.setdefault("storage", {})["level"] = "study"
    if end_hold_s is not None:
        doc["plan"]["chamber_end_c"] = 25.0 + 0.25 * end_hold_s / 60.0
        doc["plan"]["chamber_end_hold_s"] = 0.0
    if block_s is not None:
        doc["lockin"]["sim_poll_interval_s"] = block_s
    return tomlkit.dumps(doc)


@dataclass
class RecordingEstimator:
    """Stands in for the campaign's ClsfEstimator: forwards every call and keeps a copy of its arguments."""

    inner: ClsfEstimator
    calls: list[Call] = field(default_factory=list)

    def __getattr__(self, name: str) -> Any:  # attributes the runner reads (mode, rho_ref, gain_correction ...)
        return getattr(self.inner, name)

    def set_stream_timing(self, demod_filter: DemodFilter, auxin_window_s: float) -> None:
        self.calls.append(("set_stream_timing", (demod_filter, auxin_window_s)))
        self.inner.set_stream_timing(demod_filter, auxin_window_s)

    def process(self, t: np.ndarray, x: np.ndarray, r: np.ndarray, d: np.ndarray) -> ClsfPeriods:
        self.calls.append(("process", tuple(np.array(a, dtype=float) for a in (t, x, r, d))))
        return self.inner.process(t, x, r, d)

    def hold(self, t_start: float, t_end: float) -> None:
        self.calls.append(("hold", (t_start, t_end)))
        self.inner.hold(t_start, t_end)

    def release_hold(self, t_end: float) -> None:
        self.calls.append(("release_hold", (t_end,)))
        self.inner.release_hold(t_end)

    def reset_buffer(self) -> None:
        self.calls.append(("reset_buffer", ()))
        self.inner.reset_buffer()


def record(text: str) -> tuple[list[Call], dict[str, Any], float]:
    """Run the campaign of `text` on the twins: the estimator's calls, its constructor arguments, the rate."""
    cfg = parse_config(text)
    plan = checked_plan(cfg)
    station = build_station(cfg, make_world(cfg))
    with tempfile.TemporaryDirectory(prefix="qmg-clsf-bench-") as tmp:
        writer = new_run_file(Path(tmp) / "run.h5", cfg, text, plan, t0_unix=0.0, software_version="bench")
        runner = CampaignRunner(cfg, station, writer, plan=plan)
        est = runner.clsf
        kwargs = {
            "tau_s": est.tau_s,
            "mode": est.mode,
            "time_constant_s": est.time_constant_s,
            "reference_periods": est.reference_periods,
            "dither_min_step_v": est.dither_min_step_v,
        }
        rate_hz = cfg.lockin.demod_rate_hz
        recorder = RecordingEstimator(est)
        runner.__dict__["clsf"] = recorder  # the runner only calls the methods recorded above
        try:
            runner.run()
        finally:
            station.close()
            writer.close()
    return recorder.calls, kwargs, rate_hz


def replay(
    calls: list[Call], kwargs: dict[str, Any], estimator: Any = ClsfEstimator, demod_filter: Any = DemodFilter
) -> tuple[list[float], list[ClsfPeriods]]:
    """Feed the recorded calls to a fresh estimator: (seconds spent in each process call, its results)."""
    est = estimator(**kwargs)
    spent: list[float] = []
    results: list[ClsfPeriods] = []
    for name, args in calls:
        if name == "process":
            t0 = time.perf_counter()
            out = est.process(*args)
            spent.append(time.perf_counter() - t0)
            results.append(out)
        elif name == "set_stream_timing":
            est.set_stream_timing(demod_filter(args[0].order, args[0].tc_s), args[1])
        else:
            getattr(est, name)(*args)
    return spent, results


def reference_package(rev: str, into: Path) -> tuple[Any, Any]:
    """(ClsfEstimator, DemodFilter) of git revision rev: its qmg_lab/clsf copied into `into` as clsf_reference."""
    pkg = into / "clsf_reference"
    pkg.mkdir()
    names = subprocess.run(
        ["git", "ls-tree", "--name-only", f"{rev}:qmg_lab/clsf"], cwd=ROOT, check=True, capture_output=True, text=True
    ).stdout.split()
    for name in names:
        if name.endswith(".py"):
            text = subprocess.run(
                ["git", "show", f"{rev}:qmg_lab/clsf/{name}"], cwd=ROOT, check=True, capture_output=True, text=True
            ).stdout
            text = text.replace("from qmg_lab.clsf import", "from clsf_reference import")
            (pkg / name).write_text(text.replace("qmg_lab.clsf.", "clsf_reference."), encoding="utf-8")
    sys.path.insert(0, str(into))
    return (
        importlib.import_module("clsf_reference.estimator").ClsfEstimator,
        importlib.import_module("clsf_reference.demod_filter").DemodFilter,
    )


FIELDS = ("time", "eta", "sf_change_estimate", "gain_correction", "rate_output_mean")


def largest_differences(ours: list[ClsfPeriods], theirs: list[ClsfPeriods]) -> dict[str, float]:
    """Per field, the largest |a - b| / scale over all periods (scale: |a| for time, gain and rate; 1 for eta and
    the SF change, which are relative already); inf if the two return different numbers of periods."""
    worst = dict.fromkeys(FIELDS, 0.0)
    for a, b in zip(ours, theirs, strict=True):
        for name in FIELDS:
            u, v = getattr(a, name), getattr(b, name)
            if u.shape != v.shape:
                worst[name] = float("inf")
                continue
            if u.size == 0 or np.array_equal(u, v, equal_nan=True):
                continue
            scale = 1.0 if name in ("eta", "sf_change_estimate") else np.maximum(np.abs(v), 1e-300)
            worst[name] = max(worst[name], float(np.nanmax(np.abs(u - v) / scale)))
    return worst


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--json", action="store_true", help="print one JSON object")
    ap.add_argument("--runs", type=int, default=5, help="replays of the recorded campaign (median quoted)")
    ap.add_argument("--minutes", type=float, default=None, help="shorten the campaign's end hold to this (min)")
    ap.add_argument("--reference", metavar="REV", help="also replay the estimator of this git revision")
    ap.add_argument(
        "--block-s", type=float, default=None, help="the HF2 twin's block length, s (default: the config's, 2 s)"
    )
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="qmg-clsf-ref-") as ref_dir:
        reference = reference_package(args.reference, Path(ref_dir)) if args.reference else None
        out = measure(args, reference)
    if args.json:
        print(json.dumps(out, indent=2))
        return
    print(f"{out['blocks']} blocks of {out['block_s']:.2f} s, {out['samples']} samples", end=", ")
    print(f"{out['simulated_s']:.0f} simulated s")
    print(f"{out['periods']} periods estimated")
    print(f"process: {out['ms_per_block']:.3f} ms per block (median of {args.runs} runs)")
    print(f"         {out['samples_per_s']:.3g} samples/s, {out['realtime_factor_estimator']:.0f}x real time")
    if reference is not None:
        print(f"{args.reference}: {out['reference_ms_per_block']:.3f} ms per block, speed-up {out['speedup']:.2f}x")
        print(f"largest differences: {out['largest_differences']}")
    print(f"load average (1 min): {out['load_average_1min']:.2f}")


def measure(args: argparse.Namespace, reference: tuple[Any, Any] | None) -> dict[str, Any]:
    """Record the campaign, replay it (alternating with the reference, if any) and return the figures."""
    calls, kwargs, rate_hz = record(paper_text(None if args.minutes is None else 60.0 * args.minutes, args.block_s))
    blocks = [a for n, a in calls if n == "process"]
    samples = sum(int(a[0].size) for a in blocks)
    simulated = samples / rate_hz
    results = replay(calls, kwargs)[1]  # warm-up: imports, caches, compiled code
    ref_results = replay(calls, kwargs, *reference)[1] if reference is not None else []
    per_run: list[float] = []
    ref_run: list[float] = []
    for _ in range(args.runs):
        per_run.append(sum(replay(calls, kwargs)[0]))
        if reference is not None:
            ref_run.append(sum(replay(calls, kwargs, *reference)[0]))
    total = statistics.median(per_run)
    out: dict[str, Any] = {
        "block_s": samples / rate_hz / len(blocks),
        "blocks": len(blocks),
        "samples": samples,
        "simulated_s": round(simulated, 3),
        "periods": sum(len(r) for r in results),
        "runs": args.runs,
        "process_s_per_run": [round(s, 4) for s in per_run],
        "ms_per_block": 1e3 * total / len(blocks),
        "samples_per_s": samples / total,
        "realtime_factor_estimator": simulated / total,
        "load_average_1min": os.getloadavg()[0],
    }
    if reference is not None:
        out["reference"] = args.reference
        out["reference_s_per_run"] = [round(s, 4) for s in ref_run]
        out["reference_ms_per_block"] = 1e3 * statistics.median(ref_run) / len(blocks)
        out["speedup"] = statistics.median(r / o for r, o in zip(ref_run, per_run, strict=True))
        out["largest_differences"] = largest_differences(results, ref_results)
    return out


if __name__ == "__main__":
    main()
