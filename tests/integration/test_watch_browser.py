"""`qmg-lab watch` in a real browser: headless Chromium (the system's, driven by selenium through
/usr/bin/chromedriver) on the page of a twin campaign that a separate `qmg-lab run` process is writing.

Asserts: every plot's view is drawn (Bokeh reports it finished and displayed, its data non-empty), the header
names the run and its configuration, the page's last time point advances while the campaign runs and, once the
run has ended, equals the file's last time and stays there over two more page updates, and the browser console
shows no error. A screenshot goes to the test's temporary directory (docs/figures/watch_page.png is one).

Skipped, with the reason, when Chromium, its driver or selenium is missing; `.ci/run` installs Chromium and
chromium-driver from the system packages. No sleeping: the test waits on the page through WebDriverWait, and
on the processes.
"""

from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path

import h5py
import pytest

from qmg_lab.watch.page import PLOTS
from tests.support.browser import HEADER_JS, headless_chromium, missing
from tests.support.campaigns import qmg

REPO = Path(__file__).resolve().parents[2]
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
DRAWN_JS = """
const doc = Bokeh.documents[0]; const out = {};
for (const [plot, source] of Object.entries(arguments[0])) {
  const m = doc.get_model_by_name('plot_' + plot); const v = m ? Bokeh.index.find_one(m) : null;
  const s = doc.get_model_by_name(source); const col = s ? Object.keys(s.data)[0] : null;
  out[plot] = !!(v && v.has_finished() && v.is_displayed && col && s.data[col].length > 0);
}
return out;
"""


def _browser(tmp_path: Path):  # -> selenium WebDriver
    why = missing()
    if why:
        pytest.skip(why)
    return headless_chromium(tmp_path)


def _last_t(header: str) -> float:
    """The page's last time point, from the header's <span class='last-t'>...</span>."""
    try:
        return float(header.split("class='last-t'>", 1)[1].split("<", 1)[0])
    except (IndexError, ValueError):
        return float("nan")


POLLS_JS = "return Bokeh.documents[0].get_model_by_name('polls').data.n[0];"


def _file_end(path: Path) -> float:
    with h5py.File(path, "r", swmr=True) as f:
        return max(float(f[g]["time"][-1]) for g in ("clsf", "table", "chamber", "lockin") if f[g]["time"].shape[0])


def test_the_page_of_a_running_campaign_in_chromium(tmp_path: Path) -> None:
    from selenium.webdriver.support.ui import WebDriverWait

    driver = _browser(tmp_path)
    run_file = tmp_path / "paper.h5"
    run = watch = None
    try:
        # the page first (a browser takes seconds to load Bokeh), waiting for the file; then the campaign
        watch = subprocess.Popen(
            qmg("watch", str(run_file), "--wait", "--port", "5206"),
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        line = watch.stdout.readline() if watch.stdout else ""
        assert "http://127.0.0.1:" in line, (line, watch.stderr.read() if watch.poll() is not None else "")
        url = line.split(" at ", 1)[1].split()[0]
        driver.get(url)
        wait = WebDriverWait(driver, 300, poll_frequency=0.2)

        def header() -> str:
            return str(driver.execute_script(HEADER_JS) or "")

        wait.until(lambda _: "waiting for the run file" in header())
        run = subprocess.Popen(
            qmg("run", str(REPO / "configs" / "paper_campaign.toml"), "--sim", "-o", str(run_file), "-q"),
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
            text=True,
        )

        # the header names the run and its configuration once the run file exists
        wait.until(lambda _: "paper_campaign" in header())
        assert "paper.h5" in header() and "temperature_sweep" in header()

        # the last time point advances while the campaign runs
        wait.until(lambda _: _last_t(header()) > 0 or run.poll() is not None)
        t1, running = _last_t(header()), run.poll() is None
        if not running:
            pytest.fail(f"the campaign ended before the page showed it running (exit {run.returncode})")
        wait.until(lambda _: _last_t(header()) > t1)

        assert run.wait(timeout=600) == 0, run.stderr.read() if run.stderr else ""
        end = _file_end(run_file)
        wait.until(lambda _: "completed" in header() and _last_t(header()) == pytest.approx(end, abs=0.05))
        # ... and stays at the end over two more page updates
        for _ in range(2):
            before = driver.execute_script(POLLS_JS)
            wait.until(lambda _, before=before: driver.execute_script(POLLS_JS) > before)
            assert _last_t(header()) == pytest.approx(end, abs=0.05)

        drawn = driver.execute_script(DRAWN_JS, SOURCES)
        assert set(drawn) == set(PLOTS) and all(drawn.values()), drawn
        shot = tmp_path / "watch_page.png"
        assert driver.save_screenshot(str(shot)) and shot.stat().st_size > 10_000
        errors = [e for e in driver.get_log("browser") if e["level"] == "SEVERE"]
        assert not errors, errors
        if os.environ.get("QMG_WATCH_SCREENSHOT"):  # refresh the docs' reference screenshot on purpose
            shutil.copy(shot, os.environ["QMG_WATCH_SCREENSHOT"])
    finally:
        driver.quit()
        for proc in (watch, run):
            if proc is not None and proc.poll() is None:
                proc.terminate()
                proc.wait(timeout=30)


def test_run_watch_prints_the_page_address(tmp_path: Path) -> None:
    """`qmg-lab run --watch` starts the page beside the run, says where it is, and closes it at the end."""
    from tests.support.campaigns import config_text

    cfg = tmp_path / "short.toml"
    cfg.write_text(config_text())
    done = subprocess.run(
        qmg("run", str(cfg), "-o", str(tmp_path / "s.h5"), "-q", "--watch"),
        capture_output=True,
        text=True,
        env={**os.environ, "COLUMNS": "200"},
        timeout=600,
    )
    assert done.returncode == 0, done.stderr
    assert "live page of" in done.stderr and "http://127.0.0.1:" in done.stderr
    assert "live page closed" in done.stderr
