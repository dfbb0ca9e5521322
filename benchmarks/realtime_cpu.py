"""Host CPU of a campaign at real time (`qmg-lab run CONFIG --sim --realtime`), per second of campaign, without the
twins' own cost: what the lab PC will spend on the driver path at the bench (issue goal: at most 2 % of one core).

The campaign: configs/paper_campaign.toml (HF2 demodulators at 1800 Sa/s, 0.5 s polls as on hardware, the table
stepping +-5 deg/s every 60 s, CLSF observing, gzip run file) with the chamber held at 25 deg C for `--seconds`
after the lock and the reference (no 40-minute ramp; the plan rounds the hold up to pairs of 60 s table steps:
0 and 60 s give 141 s of campaign, 300 s give 381 s), run in this process on the twins, paced to the wall clock by
`build_station(cfg, pacing=RealTimePacing())`, the progress view drawing as on a terminal (to /dev/null).

Method (one process, the twins subtracted by measurement):
* host CPU = process CPU time (time.process_time: user + system of every thread of this process: the campaign
  loop, zhinst-toolkit's poll, the CLSF estimator, the writer's compression thread, the progress refresh) over
  the campaign, minus the HF2 twin's own CPU time: RealTimePacedConnection measures the thread CPU time
  (time.thread_time) of each of the twin's polls, which run on the calling thread and do all the twin's work
  (the world, the gyro kernel, the demodulators).
* What stays in: the table, chamber and DS345 twins' replies (a few transactions per second, run on the caller's
  thread inside the drivers' I/O calls) and the sleeps' wake-ups. The figure is therefore an upper bound of the
  host's cost; on hardware those replies are the serial/VISA libraries' reads instead.
* per second of campaign: divided by the campaign's own time (its summary's simulated_s); at real time that is
  also its wall time. The median and the largest of `--window`-second windows are printed beside the whole
  run's figure, and the goal.
* `--no-progress`: without the live progress view (the difference is its share; the CLI's view redraws 4 times
  a second on a terminal). The CPU seconds of each thread (psutil) are printed too.
* `--watch`: also a process that runs the watch page's update (qmg_lab.watch.page.WatchPage.update: the file
  reads, decimation and models) at the page's own period on the run file, as a browser session would make the
  page server do; its CPU time (psutil) is reported on its own line and added to a second total.

    python benchmarks/realtime_cpu.py [--seconds S] [--window S] [--watch] [--no-progress] [--json]

The first seconds of a run include numba's cache load; the window median shows the steady state.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import psutil
from rich.console import Console

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from qmg_lab.campaign.pipeline import new_run_file  # noqa: E402
from qmg_lab.campaign.plan import checked_plan  # noqa: E402
from qmg_lab.campaign.runner import CampaignRunner  # noqa: E402
from qmg_lab.cli.progress import ProgressView  # noqa: E402
from qmg_lab.config.schema import parse_config  # noqa: E402
from qmg_lab.station import RealTimePacing, build_station  # noqa: E402

PAPER = REPO / "configs" / "paper_campaign.toml"
GOAL_PERCENT_OF_ONE_CORE = 2.0
PAGE_LOOP = """
import sys, time
from pathlib import Path
from qmg_lab.watch.page import POLL_MS, WatchPage
while not Path(sys.argv[1]).exists():
    time.sleep(0.1)
page = WatchPage(Path(sys.argv[1]))
while True:
    page.update()
    time.sleep(POLL_MS / 1000.0)
"""


def campaign_text(hold_s: float) -> str:
    """The paper campaign with the chamber held at its start temperature for hold_s (no ramp, no soak)."""
    text = PAPER.read_text(encoding="utf-8")
    for key, value in (("chamber_end_c", "25.0"), ("chamber_soak_s", "0.0"), ("chamber_end_hold_s", repr(hold_s))):
        text, n = re.subn(rf"(?m)^{key}\s*=\s*[^#\n]*", f"{key} = {value}  ", text)
        assert n == 1, key
    return text


class Sampler:
    """Every `period_s`: (wall, process CPU, twin CPU) — the windows' host CPU comes from their differences."""

    def __init__(self, pacing: RealTimePacing, period_s: float) -> None:
        self.pacing, self.period_s = pacing, period_s
        self.samples: list[tuple[float, float, float]] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _take(self) -> None:
        self.samples.append((time.monotonic(), time.process_time(), self.pacing.twin_cpu_s))

    def _run(self) -> None:
        while not self._stop.wait(self.period_s):
            self._take()

    def __enter__(self) -> Sampler:
        self._take()
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join()
        self._take()

    def window_percents(self) -> list[float]:
        """Host CPU of each full window, % of one core (process CPU minus twin CPU over wall time)."""
        out = []
        for (w0, p0, t0), (w1, p1, t1) in zip(self.samples, self.samples[1:], strict=False):
            if w1 - w0 >= 0.5 * self.period_s:
                out.append(100.0 * ((p1 - p0) - (t1 - t0)) / (w1 - w0))
        return out


def thread_cpu() -> dict[str, float]:
    """CPU seconds (user + system) of each live thread of this process, by thread name (psutil's per-thread
    times, matched to Python's threads by native id; threads Python does not know are "other")."""
    names = {t.native_id: t.name for t in threading.enumerate()}
    out: dict[str, float] = {}
    for t in psutil.Process().threads():
        name = names.get(t.id, "other")
        out[name] = out.get(name, 0.0) + t.user_time + t.system_time
    return out


def run(seconds: float, window_s: float, watch: bool, progress: bool) -> dict[str, Any]:
    text = campaign_text(seconds)
    cfg = parse_config(text).with_all_sim()
    plan = checked_plan(cfg)
    with tempfile.TemporaryDirectory(prefix="realtime-cpu-") as tmp:
        path = Path(tmp) / "run.h5"
        page: subprocess.Popen[bytes] | None = None
        if watch:
            env = {**os.environ, "PYTHONPATH": str(REPO)}
            page = subprocess.Popen([sys.executable, "-c", PAGE_LOOP, str(path)], env=env)
        pacing = RealTimePacing()
        station = build_station(cfg, pacing=pacing)
        writer = new_run_file(path, cfg, text, plan)
        devnull = open(os.devnull, "w")  # noqa: SIM115 - closed below, after the view
        view = ProgressView(Console(file=devnull, force_terminal=True, width=120), enabled=progress)
        try:
            with view, Sampler(pacing, window_s) as sampler:
                runner = CampaignRunner(cfg, station, writer, progress=view.update, plan=plan)
                threads0 = thread_cpu()
                cpu0, twin0 = time.process_time(), pacing.twin_cpu_s
                summary = runner.run()
                cpu1, twin1 = time.process_time(), pacing.twin_cpu_s
                threads1 = thread_cpu()
        finally:
            writer.close()
            station.close()
            devnull.close()
            page_cpu_s = None
            if page is not None:
                times = psutil.Process(page.pid).cpu_times()
                page_cpu_s = times.user + times.system
                page.kill()
                page.wait()
    process_cpu_s, twin_cpu_s = cpu1 - cpu0, twin1 - twin0
    host_cpu_s = process_cpu_s - twin_cpu_s
    campaign_s = summary.simulated_s
    windows = sampler.window_percents()
    result: dict[str, Any] = {
        "campaign_s": campaign_s,
        "wall_s": summary.wall_s,
        "demod_rate_hz": cfg.lockin.demod_rate_hz,
        "poll_interval_s": cfg.lockin.poll_interval_s,
        "status": summary.status,
        "process_cpu_s": process_cpu_s,
        "hf2_twin_cpu_s": twin_cpu_s,
        "host_cpu_s": host_cpu_s,
        "host_cpu_percent_of_one_core": 100.0 * host_cpu_s / campaign_s,
        "window_s": window_s,
        "window_median_percent": statistics.median(windows) if windows else None,
        "window_max_percent": max(windows) if windows else None,
        "twin_max_late_s": pacing.max_late_s,
        "progress_view": progress,
        # per thread, campaign CPU s (the main thread's includes the HF2 twin's polls)
        "threads_cpu_s": {k: round(v - threads0.get(k, 0.0), 3) for k, v in threads1.items()},
        "goal_percent": GOAL_PERCENT_OF_ONE_CORE,
    }
    if page_cpu_s is not None:
        result["watch_page_cpu_s"] = page_cpu_s
        result["host_with_page_percent_of_one_core"] = 100.0 * (host_cpu_s + page_cpu_s) / campaign_s
    return result


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=60.0, help="chamber hold after the reference, s (default 60)")
    ap.add_argument("--window", type=float, default=20.0, help="window of the time-resolved figure, s (default 20)")
    ap.add_argument("--watch", action="store_true", help="also run the watch page's update beside it")
    ap.add_argument("--no-progress", action="store_true", help="without the live progress view (its share)")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    r = run(args.seconds, args.window, args.watch, not args.no_progress)
    if args.json:
        print(json.dumps(r, indent=2))
        return
    print(f"campaign {r['campaign_s']:.1f} s at {r['demod_rate_hz']:g} Sa/s, wall {r['wall_s']:.1f} s ({r['status']})")
    print(
        f"process CPU {r['process_cpu_s']:.2f} s - HF2 twin {r['hf2_twin_cpu_s']:.2f} s = host {r['host_cpu_s']:.2f} s"
    )
    print("by thread, CPU s (MainThread includes the HF2 twin's polls):", r["threads_cpu_s"])
    print(
        f"host CPU per second of campaign: {r['host_cpu_percent_of_one_core']:.2f} % of one core "
        f"(windows of {r['window_s']:g} s: median {r['window_median_percent']:.2f} %, "
        f"max {r['window_max_percent']:.2f} %); goal <= {r['goal_percent']:g} %"
    )
    if "watch_page_cpu_s" in r:
        print(
            f"watch page update loop {r['watch_page_cpu_s']:.2f} CPU s: with it "
            f"{r['host_with_page_percent_of_one_core']:.2f} % of one core"
        )


if __name__ == "__main__":
    main()
