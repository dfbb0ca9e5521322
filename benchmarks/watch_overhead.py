"""How much watching a twin campaign from another process slows it (issue 26: at most 10 %).

Runs `python -m qmg_lab run configs/paper_campaign.toml --sim -o <tmp> -q` in a fresh process, alternately
unwatched and watched, and reads each run's own wall time from its summary ("wall time": the campaign from the
first step to the file's close, without the process's start-up). Watched: `qmg-lab watch <tmp> --wait` started
first in its own process, with its page open in headless Chromium (the system's, through selenium and
/usr/bin/chromedriver) before the campaign starts, as a user at the bench would have it; with `--no-browser`
(or without Chromium) a process that runs the page's own timer (qmg_lab.watch.page.WatchPage.check every
CHECK_MS: the status check, and every POLL_MS the file reads, decimation and models) instead, without a websocket
and a browser.
A first unwatched run warms numba's cache and is not counted.

    python benchmarks/watch_overhead.py [--json] [--pairs N] [--ramp-divisor K] [--no-browser]

`--ramp-divisor K` divides the chamber ramp rate by K: the paper campaign (55 simulated minutes) becomes about
K times longer (K = 3.3: about 3 hours). Reported: the medians, `slowdown` = median(watched) / median(unwatched)
- 1, each pair's ratio, and the CPU seconds the page server and the browser (all its processes, from Linux's
/proc) used during each watched run, with the page's updates in that time (`page_updates`, its "polls" model)
and the browser's CPU per update. These machines are shared and noisy (2 cores for everything, the browser
included): quote the median and the pairs. Headless Chromium started with --disable-gpu draws every canvas in
software, so its share here is an upper bound for a desktop browser; `--no-browser` isolates the page's own cost
(reading the file, decimating, building the models).
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import statistics
import subprocess
import sys
import tempfile
import tomllib
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
PAPER = REPO / "configs" / "paper_campaign.toml"
# how many times the page has read the file and sent an update (qmg_lab/watch/page.py's "polls" model)
POLLS_JS = "return Bokeh.documents[0].get_model_by_name('polls').data.n[0];"
WALL = re.compile(r"wall time\s*│\s*([0-9.]+) s")
PAGE_LOOP = """
import sys, time
from pathlib import Path
from qmg_lab.watch.page import CHECK_MS, WatchPage
page = WatchPage(Path(sys.argv[1]))
while True:
    page.check()
    time.sleep(CHECK_MS / 1000.0)
"""


def _config(tmp: Path, divisor: float) -> Path:
    text = PAPER.read_text()
    if divisor != 1.0:
        ramp = float(tomllib.loads(text)["plan"]["chamber_ramp_c_per_min"])
        text = re.sub(r"(?m)^chamber_ramp_c_per_min\s*=.*$", f"chamber_ramp_c_per_min = {ramp / divisor!r}", text)
    path = tmp / "campaign.toml"
    path.write_text(text)
    return path


def _run(cfg: Path, out: Path) -> float:
    if out.exists():
        out.unlink()
    done = subprocess.run(
        [sys.executable, "-m", "qmg_lab", "run", str(cfg), "--sim", "-o", str(out), "-q"],
        capture_output=True,
        text=True,
        env={**os.environ, "COLUMNS": "200"},
    )
    if done.returncode != 0:
        raise SystemExit(f"the campaign failed (exit {done.returncode}): {done.stderr[-2000:]}")
    m = WALL.search(done.stdout)
    if m is None:
        raise SystemExit(f"no wall time in the run's summary: {done.stdout[-2000:]}")
    return float(m.group(1))


def _browser(tmp: Path):  # -> selenium WebDriver | None
    sys.path.insert(0, str(REPO))  # the tests' helper that starts the system's headless Chromium
    from tests.support.browser import headless_chromium, missing

    return None if missing() else headless_chromium(tmp)


def _cpu_s(root: int) -> float:
    """User + system CPU seconds of process `root` and all its descendants so far (Linux /proc; 0 elsewhere)."""
    tick = os.sysconf("SC_CLK_TCK") if hasattr(os, "sysconf") else 100
    children: dict[int, list[int]] = {}
    stats: dict[int, float] = {}
    for entry in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = entry.read_text().rsplit(")", 1)[1].split()
        except (OSError, IndexError):
            continue
        pid = int(entry.parent.name)
        children.setdefault(int(fields[1]), []).append(pid)
        stats[pid] = (int(fields[11]) + int(fields[12])) / tick
    total, todo = 0.0, [root]
    while todo:
        pid = todo.pop()
        total += stats.get(pid, 0.0)
        todo.extend(children.get(pid, []))
    return total


def _watched(cfg: Path, out: Path, tmp: Path, use_browser: bool) -> tuple[float, str, dict[str, float]]:
    """The watched run's wall time, the watcher's kind, and the CPU seconds the watcher's processes used during
    the run (page server; browser)."""
    if out.exists():
        out.unlink()
    driver = _browser(tmp) if use_browser else None
    if driver is None:
        watcher = subprocess.Popen([sys.executable, "-c", PAGE_LOOP, str(out)], cwd=REPO)
        try:
            c0 = _cpu_s(watcher.pid)
            wall = _run(cfg, out)
            return wall, "page-update loop (no browser)", {"page_cpu_s": _cpu_s(watcher.pid) - c0}
        finally:
            watcher.terminate()
            watcher.wait()
    from selenium.webdriver.support.ui import WebDriverWait

    server = subprocess.Popen(
        [sys.executable, "-m", "qmg_lab", "watch", str(out), "--wait", "--port", "5306"],
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        text=True,
    )
    try:
        line = server.stdout.readline() if server.stdout else ""
        driver.get(line.split(" at ", 1)[1].split()[0])
        from tests.support.browser import HEADER_JS

        WebDriverWait(driver, 120, poll_frequency=0.2).until(lambda d: "waiting" in str(d.execute_script(HEADER_JS)))
        browser_pid = driver.service.process.pid
        c0, b0 = _cpu_s(server.pid), _cpu_s(browser_pid)
        n0 = driver.execute_script(POLLS_JS)
        wall = _run(cfg, out)
        cpu = {"page_cpu_s": _cpu_s(server.pid) - c0, "browser_cpu_s": _cpu_s(browser_pid) - b0}
        cpu["page_updates"] = driver.execute_script(POLLS_JS) - n0
        cpu["browser_cpu_s_per_update"] = round(cpu["browser_cpu_s"] / max(cpu["page_updates"], 1), 3)
        return wall, "qmg-lab watch + headless Chromium", cpu
    finally:
        driver.quit()
        server.terminate()
        server.wait()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--pairs", type=int, default=3)
    ap.add_argument("--ramp-divisor", type=float, default=1.0)
    ap.add_argument("--no-browser", action="store_true")
    args = ap.parse_args()
    tmp = Path(tempfile.mkdtemp(prefix="watch_overhead_"))
    try:
        cfg = _config(tmp, args.ramp_divisor)
        out = tmp / "run.h5"
        _run(cfg, out)  # warm-up: numba's cache
        plain, watched, how, cpu = [], [], "", []
        for _ in range(args.pairs):
            plain.append(_run(cfg, out))
            w, how, c = _watched(cfg, out, tmp, not args.no_browser)
            watched.append(w)
            cpu.append(c)
        from qmg_lab.storage.reader import read_run

        simulated = float(read_run(out, select=("lockin/time",)).groups["lockin"]["time"][-1])
        result = {
            "config": str(PAPER.relative_to(REPO)),
            "ramp_divisor": args.ramp_divisor,
            "simulated_s": round(simulated, 1),
            "watcher": how,
            "pairs": args.pairs,
            "unwatched_wall_s": plain,
            "watched_wall_s": watched,
            "unwatched_wall_s_median": statistics.median(plain),
            "watched_wall_s_median": statistics.median(watched),
            "slowdown": statistics.median(watched) / statistics.median(plain) - 1.0,
            "pair_ratios": [round(w / p, 4) for p, w in zip(plain, watched, strict=True)],
            "watcher_cpu_s": cpu,  # during each watched run: the page server's, and the browser's (all processes)
            "target_slowdown_max": 0.10,
            "cpus": os.cpu_count(),
        }
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    if args.json:
        print(json.dumps(result, indent=2))
    else:
        for k, v in result.items():
            print(f"{k:28s} {v}")


if __name__ == "__main__":
    main()
