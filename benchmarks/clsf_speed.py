"""Cost of the CLSF estimator alone, per lock-in block, on the blocks of a real twin campaign.

1. Records: the paper campaign (configs/paper_campaign.toml, 55 simulated minutes, the HF2 twin's 2 s blocks at
   1800 Sa/s) runs once on the twins in this process at the study storage level; every call the campaign makes
   on its ClsfEstimator (set_stream_timing, process with the block's arrays, hold, release_hold, reset_buffer) is
   recorded in order. `--minutes M` shortens the chamber's end hold for a quicker look.
2. Replays: a fresh estimator receives the same calls `--runs` times; only `process` is timed
   (time.perf_counter around each call). Printed: the median over runs of the mean ms per block, samples per
   second, and the implied real-time factor of the estimator alone (simulated s / s spent in process), plus the
   number of periods it returned, so that two versions can be checked to do the same work.

    python benchmarks/clsf_speed.py [--json] [--runs N] [--minutes M]

Target (this benchmark's task): >= 5x less per block than 38cd4c6 (about 2-3 ms per 2 s block of 3600 samples on
a quiet 2-core machine). These machines are shared and noisy: quote the median and the load average.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import tempfile
import time
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import tomlkit

from qmg_lab.campaign.runner import CampaignRunner
from qmg_lab.clsf.demod_filter import DemodFilter
from qmg_lab.clsf.estimator import ClsfEstimator, ClsfPeriods
from qmg_lab.config.schema import config_fingerprint, parse_config
from qmg_lab.station import build_station, make_world
from qmg_lab.storage.writer import RunWriter

ROOT = Path(__file__).resolve().parents[1]

Call = tuple[str, tuple[Any, ...]]


def paper_text(end_hold_s: float | None) -> str:
    """The paper campaign on the twins at the study storage level (optionally with a shorter end hold)."""
    doc = tomllib.loads((ROOT / "configs" / "paper_campaign.toml").read_text())
    for name in ("lockin", "generator", "table", "chamber"):
        doc[name]["sim"] = True
    doc.setdefault("storage", {})["level"] = "study"
    if end_hold_s is not None:
        doc["plan"]["chamber_end_c"] = 25.0 + 0.25 * end_hold_s / 60.0
        doc["plan"]["chamber_end_hold_s"] = 0.0
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
    station = build_station(cfg, make_world(cfg))
    with tempfile.TemporaryDirectory(prefix="qmg-clsf-bench-") as tmp:
        writer = RunWriter.create(
            Path(tmp) / "run.h5",
            config_text=text,
            config_sha256=config_fingerprint(text),
            mode="sim",
            software_version="bench",
            t0_unix=0.0,
            flush_interval_s=cfg.storage.flush_interval_s,
            compression="none",
            truth=True,
        )
        runner = CampaignRunner(cfg, station, writer)
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


def replay(calls: list[Call], kwargs: dict[str, Any]) -> tuple[list[float], list[ClsfPeriods]]:
    """Feed the recorded calls to a fresh estimator: (seconds spent in each process call, its results)."""
    est = ClsfEstimator(**kwargs)
    spent: list[float] = []
    results: list[ClsfPeriods] = []
    for name, args in calls:
        if name == "process":
            t0 = time.perf_counter()
            out = est.process(*args)
            spent.append(time.perf_counter() - t0)
            results.append(out)
        else:
            getattr(est, name)(*args)
    return spent, results


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--json", action="store_true", help="print one JSON object")
    ap.add_argument("--runs", type=int, default=5, help="replays of the recorded campaign (median quoted)")
    ap.add_argument("--minutes", type=float, default=None, help="shorten the campaign's end hold to this (min)")
    args = ap.parse_args()
    calls, kwargs, rate_hz = record(paper_text(None if args.minutes is None else 60.0 * args.minutes))
    blocks = [a for n, a in calls if n == "process"]
    samples = sum(int(a[0].size) for a in blocks)
    simulated = samples / rate_hz
    replay(calls, kwargs)  # warm-up: imports, caches, compiled code
    per_run = []
    periods = 0
    for _ in range(args.runs):
        spent, results = replay(calls, kwargs)
        per_run.append(sum(spent))
        periods = sum(len(r) for r in results)
    total = statistics.median(per_run)
    out = {
        "blocks": len(blocks),
        "samples": samples,
        "simulated_s": round(simulated, 3),
        "periods": periods,
        "runs": args.runs,
        "process_s_per_run": [round(s, 4) for s in per_run],
        "ms_per_block": 1e3 * total / len(blocks),
        "samples_per_s": samples / total,
        "realtime_factor_estimator": simulated / total,
        "load_average_1min": os.getloadavg()[0],
    }
    if args.json:
        print(json.dumps(out, indent=2))
        return
    print(f"{out['blocks']} blocks, {samples} samples, {simulated:.0f} simulated s, {periods} periods")
    print(f"process: {out['ms_per_block']:.3f} ms per block (median of {args.runs} runs)")
    print(f"         {out['samples_per_s']:.3g} samples/s, {out['realtime_factor_estimator']:.0f}x real time")
    print(f"load average (1 min): {out['load_average_1min']:.2f}")


if __name__ == "__main__":
    main()
