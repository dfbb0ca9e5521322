"""`qmg-lab watch` in a real browser: headless Chromium (the system's, driven by selenium through
/usr/bin/chromedriver) on the page of a twin campaign that a separate `qmg-lab run` process is writing.

Asserts, for the paper campaign run to its end:
  * every plot's view is drawn (Bokeh reports it finished and displayed, its data non-empty), the header names
    the run and its configuration, and the page's horizon advances while the campaign runs;
  * one data horizon: at every look while the run goes on, each trace's newest point t_k lies in [h - g, h], h the
    page's horizon and g the largest gap between two rows of any followed group in the file (a trace ends on its
    group's last row at or before h; the groups are read to the same h); once the run has ended each trace ends
    exactly on its group's last row in the file, and h on the file's last time;
  * the final status is on the page within 2 s of the run's process ending: completed here, "aborted: <the file's
    abort_reason>" after Ctrl-C, "process died: check the instruments" after kill -9 (then with the warning that
    the instruments may not be in their safe state);
  * the now panel against the file: the SF change (the mean of /clsf/sf_change_estimate over the periods ending in
    the last 60 s, shown to 0.1 ppm: within 0.05 ppm), the chamber setpoint and air temperature (last /chamber row)
    and the gyro temperature (last /truth row), shown to 0.01 degC: within 0.005 degC; the PLL lock as the last
    /lockin/pll_locked row says; the steps not run after Ctrl-C (planned minus completed in /steps, exactly); the
    safe-state outcome (the file's last safe_state event message, exactly); the end (the file's modification
    time, to the second, within 1 s);
  * no error in the browser console.
And `run --watch` keeps serving the final page after the run has ended, until Ctrl-C.

A screenshot goes to the test's temporary directory (QMG_WATCH_SCREENSHOT=path copies it there: how
docs/figures/watch_page.png is made). Skipped, with the reason, when Chromium, its driver or selenium is
missing; `.ci/run` installs Chromium and chromium-driver from the system packages. No sleeping: the test waits
on the page through WebDriverWait, and on the processes.
"""

from __future__ import annotations

import html
import os
import re
import shutil
import signal
import subprocess
import time
import urllib.request
from pathlib import Path
from typing import Any

import h5py
import numpy as np
import pytest

from qmg_lab.watch.page import PLOTS
from tests.support.browser import headless_chromium, missing
from tests.support.campaigns import qmg

REPO = Path(__file__).resolve().parents[2]
PAPER = REPO / "configs" / "paper_campaign.toml"
FINAL_WITHIN_S = 2.0
# each plot and a data source that must have points once the run has data
SOURCES = {
    "sf": "sf_mean",
    "gain": "gain",
    "temp": "chamber_air",
    "table": "table_measured",
    "drive": "drive_amplitude",
    "pll": "pll_frequency",
    "steps": "steps_timeline",
    "events": "events",
}
# each trace's source and the file group it is drawn from
TRACES = {
    "sf_period": "clsf",
    "sf_mean": "clsf",
    "gain": "clsf",
    "chamber_air": "chamber",
    "chamber_setpoint": "chamber",
    "gyro_temperature": "truth",
    "table_command": "table",
    "table_measured": "table",
    "drive_amplitude": "lockin",
    "pll_frequency": "lockin",
}
DRAWN_JS = """
const doc = Bokeh.documents[0]; const out = {};
for (const [plot, source] of Object.entries(arguments[0])) {
  const m = doc.get_model_by_name('plot_' + plot); const v = m ? Bokeh.index.find_one(m) : null;
  const s = doc.get_model_by_name(source); const col = s ? Object.keys(s.data)[0] : null;
  out[plot] = !!(v && v.has_finished() && v.is_displayed && col && s.data[col].length > 0);
}
return out;
"""
# the page's state at one instant (the browser applies each poll's models as one message)
STATE_JS = """
if (!window.Bokeh || !Bokeh.documents || !Bokeh.documents.length) return null;
const doc = Bokeh.documents[0]; const get = (n) => doc.get_model_by_name(n);
if (!get('header') || !get('now')) return null;
const ends = {};
for (const n of arguments[0]) {
  const s = get(n); if (s && s.data.t.length) ends[n] = s.data.t[s.data.t.length - 1];
}
return {header: get('header').text, now: get('now').text, polls: get('polls').data.n[0], ends: ends};
"""


# the browser stamps (its clock: Date.now(), the same machine's clock as time.time()) the first moment the now panel
# shows the status given, looking every 50 ms: the page's latency without WebDriver's round trips
STAMP_JS = """
window.qmgFinal = null; const want = "class='now-status'>" + arguments[0];
const timer = setInterval(() => {
  const d = window.Bokeh && Bokeh.documents[0]; const n = d && d.get_model_by_name('now');
  if (n && n.text.includes(want)) { window.qmgFinal = Date.now() / 1000; clearInterval(timer); }
}, 50);
"""


class Page:
    """The page in the browser, read through STATE_JS."""

    def __init__(self, driver: Any) -> None:
        self.driver = driver

    def state(self) -> dict[str, Any]:
        return self.driver.execute_script(STATE_JS, list(TRACES)) or {"header": "", "now": "", "polls": 0, "ends": {}}

    def now(self, name: str, st: dict[str, Any] | None = None) -> str | None:
        m = re.search(rf"class='now-{name}'>([^<]*)<", (st or self.state())["now"])
        return html.unescape(m.group(1)) if m else None

    def horizon(self, st: dict[str, Any] | None = None) -> float:
        """The page's horizon, from the header's <span class='last-t'>...</span>."""
        m = re.search(r"class='last-t'[^>]*>([^<]*)<", (st or self.state())["header"])
        try:
            return float(m.group(1)) if m else float("nan")
        except ValueError:
            return float("nan")

    def stamp(self, status: str) -> None:
        """From now on, note when the now panel first shows `status` (STAMP_JS)."""
        self.driver.execute_script(STAMP_JS, html.escape(status, quote=False))

    def stamped(self) -> float | None:
        return self.driver.execute_script("return window.qmgFinal;")

    def errors(self) -> list[Any]:
        return [e for e in self.driver.get_log("browser") if e["level"] == "SEVERE"]


def _browser(tmp_path: Path) -> Any:
    why = missing()
    if why:
        pytest.skip(why)
    driver = headless_chromium(tmp_path)
    driver.set_script_timeout(120)  # a loaded machine can starve the browser for many seconds
    return driver


def _serve(run_file: Path, port: int) -> tuple[subprocess.Popen[str], str]:
    watch = subprocess.Popen(
        qmg("watch", str(run_file), "--wait", "--port", str(port)),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    line = watch.stdout.readline() if watch.stdout else ""
    assert "http://127.0.0.1:" in line, (line, watch.stderr.read() if watch.poll() is not None else "")
    return watch, line.split(" at ", 1)[1].split()[0]


def _campaign(run_file: Path, config: Path = PAPER) -> subprocess.Popen[str]:
    return subprocess.Popen(
        qmg("run", str(config), "--sim", "-o", str(run_file), "-q"),
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
    )


def _stop(*procs: subprocess.Popen[str] | None) -> None:
    for proc in procs:
        if proc is not None and proc.poll() is None:
            proc.terminate()
            proc.wait(timeout=30)


def _file(path: Path) -> dict[str, Any]:
    """What the page must show, read from the file as an outside reader would."""
    with h5py.File(path, "r", swmr=True) as f:
        t = {g: f[g]["time"][:] for g in ("clsf", "table", "chamber", "lockin")}
        clsf_s = f["clsf/sf_change_estimate"][:]
        ev_kind = [k.decode() for k in f["events/kind"][:]]
        ev_msg = [m.decode() for m in f["events/message"][:]]
        steps_done = int(np.sum(f["steps/status"][:] == b"completed"))
        out = {
            "ends": {g: float(v[-1]) for g, v in t.items()} | {"truth": float(f["lockin/time"][-1])},
            "gap": max(float(np.max(np.diff(v))) for g, v in t.items() if g != "lockin"),
            "sf_ppm": float(np.mean(clsf_s[t["clsf"] > t["clsf"][-1] - 60.0])) * 1e6,
            "setpoint": float(f["chamber/setpoint"][-1]),
            "air": float(f["chamber/temperature"][-1]),
            "gyro": float(f["truth/temperature"][-1]),
            "locked": bool(f["lockin/pll_locked"][-1]),
            "status": f.attrs["status"],
            "abort_reason": f.attrs["abort_reason"],
            "planned": int(f.attrs["planned_steps"]),
            "not_run": int(f.attrs["planned_steps"]) - steps_done,
            "safe_state": [m for k, m in zip(ev_kind, ev_msg, strict=True) if k == "safe_state"],
        }
    out["mtime"] = path.stat().st_mtime
    return out


def _final_within(page: Page, wait: Any, ended: float) -> float:
    """Seconds from the run's process end (`ended`, time.time()) to the page showing the status stamped for
    (Page.stamp; negative: the page showed it before the process had exited)."""
    wait.until(lambda _: page.stamped() is not None)
    return float(page.stamped()) - ended


def _slow_paper(tmp_path: Path) -> Path:
    """The paper campaign with the chamber ramp 3 times slower (as benchmarks/watch_overhead.py --ramp-divisor 3):
    it runs long enough to be stopped midway on a loaded machine."""
    text = PAPER.read_text()
    ramp = float(re.search(r"(?m)^chamber_ramp_c_per_min\s*=\s*([0-9.eE+-]+)", text).group(1))  # type: ignore[union-attr]
    path = tmp_path / "slow_paper.toml"
    path.write_text(re.sub(r"(?m)^chamber_ramp_c_per_min\s*=.*$", f"chamber_ramp_c_per_min = {ramp / 3!r}", text))
    return path


def test_the_page_of_a_running_campaign_in_chromium(tmp_path: Path) -> None:
    from selenium.webdriver.support.ui import WebDriverWait

    driver = _browser(tmp_path)
    page = Page(driver)
    run_file = tmp_path / "paper.h5"
    run = watch = None
    try:
        # the page first (a browser takes seconds to load Bokeh), waiting for the file; then the campaign
        watch, url = _serve(run_file, 5206)
        driver.get(url)
        wait = WebDriverWait(driver, 300, poll_frequency=0.1)
        wait.until(lambda _: "waiting for the run file" in page.state()["header"])
        run = _campaign(run_file)

        # the header names the run and its configuration once the run file exists
        wait.until(lambda _: "paper_campaign" in page.state()["header"])
        assert "paper.h5" in page.state()["header"] and "temperature_sweep" in page.state()["header"]

        # the horizon advances while the campaign runs; at each of three polls every trace is on it
        wait.until(lambda _: page.horizon() > 0 or run.poll() is not None)
        if run.poll() is not None:
            pytest.fail(f"the campaign ended before the page showed it running (exit {run.returncode})")
        looks = []
        for _ in range(3):
            before = page.state()["polls"]
            wait.until(lambda _, before=before: page.state()["polls"] > before and page.state()["ends"])
            looks.append(page.state())
        assert page.horizon(looks[-1]) > page.horizon(looks[0]) or run.poll() is not None

        page.stamp("completed")
        assert run.wait(timeout=900) == 0, run.stderr.read() if run.stderr else ""
        took = _final_within(page, wait, time.time())
        f = _file(run_file)
        for st in looks:  # the looks while running, judged with the file's row gaps
            if (page.now("status", st) or "").startswith("running"):
                h = page.horizon(st)
                late = {n: t for n, t in st["ends"].items() if not h - f["gap"] - 1e-9 <= t <= h + 1e-9}
                assert not late, (h, f["gap"], late)
        print(f"completed shown {took:+.2f} s after the run's process ended")  # the figure, with pytest -s
        assert took <= FINAL_WITHIN_S, f"completed shown {took:.2f} s after the run's end"
        end = max(f["ends"].values())
        wait.until(lambda _: page.horizon() == pytest.approx(end, abs=0.05))
        # ... and stays at the end over two more page updates, every trace on its group's last row
        for _ in range(2):
            before = page.state()["polls"]
            wait.until(lambda _, before=before: page.state()["polls"] > before)
            st = page.state()
            assert page.horizon(st) == pytest.approx(end, abs=0.05)
            for name, group in TRACES.items():
                assert st["ends"][name] == pytest.approx(f["ends"][group], abs=1e-6), name

        # the now panel against the file
        st = page.state()
        assert float(page.now("sf", st) or "nan") == pytest.approx(f["sf_ppm"], abs=0.05 + 1e-9)
        for name in ("setpoint", "air", "gyro"):
            assert float(page.now(name, st) or "nan") == pytest.approx(f[name], abs=0.005 + 1e-9), name
        assert page.now("pll", st) == ("locked" if f["locked"] else "NOT LOCKED")
        assert page.now("safe", st) == f["safe_state"][-1]
        assert page.now("left", st) is None and page.now("not-run", st) is None  # every step done
        shown = time.mktime(
            time.strptime(time.strftime("%Y-%m-%d ") + (page.now("end", st) or ""), "%Y-%m-%d %H:%M:%S")
        )
        assert abs(shown - f["mtime"]) <= 1.0

        drawn = driver.execute_script(DRAWN_JS, SOURCES)
        assert set(drawn) == set(PLOTS) and all(drawn.values()), drawn
        driver.execute_script("window.scrollTo(0, 0)")
        shot = tmp_path / "watch_page.png"
        assert driver.save_screenshot(str(shot)) and shot.stat().st_size > 10_000
        assert not page.errors()
        if os.environ.get("QMG_WATCH_SCREENSHOT"):  # refresh the docs' reference screenshot on purpose
            shutil.copy(shot, os.environ["QMG_WATCH_SCREENSHOT"])
    finally:
        driver.quit()
        _stop(watch, run)


@pytest.mark.parametrize("how", ["ctrl-c", "kill -9"])
def test_the_page_says_how_a_stopped_run_ended(tmp_path: Path, how: str) -> None:
    from selenium.webdriver.support.ui import WebDriverWait

    driver = _browser(tmp_path)
    page = Page(driver)
    run_file = tmp_path / "paper.h5"
    run = watch = None
    try:
        watch, url = _serve(run_file, 5207 if how == "ctrl-c" else 5208)
        driver.get(url)
        wait = WebDriverWait(driver, 300, poll_frequency=0.1)
        wait.until(lambda _: "waiting for the run file" in page.state()["header"])
        run = _campaign(run_file, _slow_paper(tmp_path))
        wait.until(lambda _: page.horizon() > 120.0 or run.poll() is not None)
        assert run.poll() is None, "the campaign ended before it could be stopped"
        assert (page.now("status") or "").startswith("running") and page.now("left") is not None
        page.stamp("aborted" if how == "ctrl-c" else "process died: check the instruments")
        run.send_signal(signal.SIGINT if how == "ctrl-c" else signal.SIGKILL)
        code = run.wait(timeout=120)
        ended = time.time()
        took = _final_within(page, wait, ended)
        if how == "ctrl-c":
            assert code == 130, run.stderr.read() if run.stderr else ""
            f = _file(run_file)
            assert f["status"] == "aborted"
            # the status comes first, alone; the page's read of the file's end follows on the next tick
            wait.until(lambda _: page.now("not-run") == str(f["not_run"]))
            assert page.now("status") == (f"aborted: {f['abort_reason']}" if f["abort_reason"] else "aborted")
            # no "remaining 0:00:00" with steps not run: the steps not run, counted as the file counts them
            assert page.now("left") is None and page.now("remaining") is None
            assert page.now("not-run") == str(f["not_run"]) and f["not_run"] > 0
            assert page.now("safe") == f["safe_state"][-1]
        else:
            assert code == -signal.SIGKILL
            assert "may NOT be in their safe state" in page.state()["now"]
            assert page.now("left") is None and page.now("remaining") is None
        print(f"{how}: the final status shown {took:+.2f} s after the run's process ended")
        assert took <= FINAL_WITHIN_S, f"{how}: the final status shown {took:.2f} s after the run's end"
        assert not page.errors()
    finally:
        driver.quit()
        _stop(watch, run)


def test_run_watch_serves_the_final_page_until_ctrl_c(tmp_path: Path) -> None:
    """`qmg-lab run --watch` starts the page beside the run, says where it is, keeps it up with the final status
    after the run has ended, and closes it at a second Ctrl-C (the first stops the run, not the page)."""
    from tests.support.campaigns import config_text

    cfg = tmp_path / "short.toml"
    cfg.write_text(config_text())
    run = subprocess.Popen(
        qmg("run", str(cfg), "-o", str(tmp_path / "s.h5"), "-q", "--watch", "--port", "5209", "--watch-linger", "600"),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env={**os.environ, "COLUMNS": "300"},
    )
    try:
        said = []
        for line in run.stderr or []:
            said.append(line)
            if "stays at" in line:
                break
        text = "".join(said)
        assert "live page of" in text and "http://127.0.0.1:5209/" in text and "for 600 s" in text, text
        assert run.poll() is None  # the run is over; the command waits with its page up
        with urllib.request.urlopen("http://127.0.0.1:5209/", timeout=30) as r:
            assert r.status == 200 and b"bokeh" in r.read().lower()
        run.send_signal(signal.SIGINT)
        _, err = run.communicate(timeout=60)
    finally:
        _stop(run)
    assert run.returncode == 0, err  # the run completed: the Ctrl-C closed the page only
    assert "live page closed" in err
    with pytest.raises(OSError):
        urllib.request.urlopen("http://127.0.0.1:5209/", timeout=5)


def test_run_watch_linger_ends_by_itself(tmp_path: Path) -> None:
    from tests.support.campaigns import config_text

    cfg = tmp_path / "short.toml"
    cfg.write_text(config_text())
    done = subprocess.run(
        qmg("run", str(cfg), "-o", str(tmp_path / "s.h5"), "-q", "--watch", "--watch-linger", "1"),
        capture_output=True,
        text=True,
        env={**os.environ, "COLUMNS": "300"},
        timeout=600,
    )
    assert done.returncode == 0, done.stderr
    assert "live page of" in done.stderr and "http://127.0.0.1:" in done.stderr
    assert "for 1 s" in done.stderr and "live page closed" in done.stderr
