"""The watch page's data side without a browser: a Bokeh Document fed by WatchPage.update() from a running file
(a RunWriter open in this process), bounded traces, the replay of a resumed twin campaign, and the live pair SF
against `qmg-lab analyze`'s. The page in a real browser: test_watch_browser.py."""

from __future__ import annotations

import html
import math
import os
import re
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
from bokeh.document import Document
from bokeh.models import Div, GlyphRenderer, Legend, Plot, Range1d

from qmg_lab.analysis.compute import analyze
from qmg_lab.watch.page import CHUNK_BINS, MAX_POINTS, PLOTS, Band, StableRange, Trace, WatchPage
from tests.support.live_runs import append_block, interrupted_then_resumed, live_writer


def test_the_page_follows_a_running_file(tmp_path: Path) -> None:
    """Each block (live_runs.append_block: CLSF periods at 7 Hz to 10 k + 10 s, chamber and table every 0.5 s to
    10 k + 9.5 s) is shown up to the common horizon h = min of the groups' last times = 10 k + 9.5 s: the
    CLSF periods after h wait for the next poll; once the file is final every row is shown."""
    path = tmp_path / "live.h5"
    w = live_writer(path, "live one", ["soak", "soak", "soak"])
    try:
        page = WatchPage(path)
        doc = Document()
        page.attach(doc)
        assert {f"plot_{n}" for n in PLOTS} <= {m.name for m in doc.models if m.name}
        assert "live one" in page.header.text and "running" in page.header.text
        seen = []
        for k in range(2):
            append_block(w, k, "soak")
            page.update()
            seen.append(page.last_t)
            h = 10.0 * k + 9.5
            periods = int(np.floor(h * 7))  # the periods ending at j/7 <= h
            assert len(page.sf_band.source.data["t"]) == periods  # < 2 CHUNK_BINS: every row its own bin
            assert page.sf_band.t[-1] == periods / 7.0 <= h
            assert page.traces["chamber_air"].t[-1] == h and page.traces["table_measured"].t[-1] == h
            # the now panel: 60 s mean of the estimate 1e-6 t over the periods read, the last chamber row, the step
            mean = np.mean(np.arange(1, periods + 1) / 7.0)  # ppm: 1e-6 t x 1e6
            assert _now(page, "sf") == f"{mean:+.1f}" and _now(page, "air") == f"{25 + 0.1 * h:.2f}"
            assert _now(page, "setpoint") == "30.00" and _now(page, "gyro") is None  # bench file: no /truth
            assert _now(page, "pll") == "not recorded"  # no /lockin rows
            assert _now(page, "step") == str(k + 1) and _now(page, "kind") == "soak"
        assert seen == [9.5, 19.5]
        page.update()  # nothing new: nothing moves
        assert page.last_t == 19.5
        steps = page.steps.data
        assert steps["label"] == ["completed", "completed", "current"] and steps["color"][-1] == "#d62728"
    finally:
        w.set_status("completed")
        w.close()
    page.update()
    # final: every row; stopped short of its plan: the step not run stays on the timeline, grey, no longer current
    assert page.last_t == 20.0 and page.sf_band.t[-1] == 20.0
    assert "completed" in page.header.text and page.steps.data["label"] == ["completed", "completed", "planned"]
    assert _now(page, "status") == "completed" and _now(page, "not-run") == "1" and _now(page, "left") is None


def _now(page: WatchPage, name: str) -> str | None:
    """A value of the page's now panel (page._value), None if it does not show it."""
    m = re.search(rf"class='now-{name}'>([^<]*)<", page.now.text)
    return html.unescape(m.group(1)) if m else None


def test_the_envelope_keeps_every_minimum_and_maximum() -> None:
    band = Band("x")
    rng = np.random.default_rng(3)
    ys = []
    for k in range(30):  # 30 polls of 20000 periods
        t = k * 2000.0 + np.arange(20_000) / 10.0
        y = rng.standard_normal(t.shape[0])
        ys.append(y)
        band.add(t, y)
        assert len(band.source.data["t"]) <= 2 * MAX_POINTS + CHUNK_BINS
    y = np.concatenate(ys)
    assert band.lo.min() == y.min() and band.hi.max() == y.max() and np.all(band.lo <= band.hi)
    assert np.all(np.diff(band.t) > 0)


def test_a_trace_stays_bounded() -> None:
    tr = Trace("x")
    rng = np.random.default_rng(2)
    for k in range(50):  # 50 polls of 100000 rows each: 5 million rows in all
        t = k * 1000.0 + np.arange(100_000) / 100.0
        tr.add(t, rng.standard_normal(t.shape[0]))
        assert len(tr.source.data["t"]) <= 2 * MAX_POINTS + 2 * CHUNK_BINS + 2
    assert np.all(np.diff(tr.t) > 0) and tr.t[-1] == 49 * 1000.0 + 99_999 / 100.0


def test_replay_of_a_resumed_twin_campaign_and_its_pair_sf(tmp_path: Path) -> None:
    def replay_aborted(path: Path) -> None:
        page = WatchPage(path)
        page.attach(Document())
        assert "aborted" in page.header.text and "interrupted" in page.events.data["kind"]
        assert page.last_t >= 30.0 and page.steps.data["label"][-1] == "planned"  # no current step: it stopped

    done = interrupted_then_resumed(tmp_path, replay_aborted)
    page = WatchPage(done.path)
    page.attach(Document())
    for _ in range(3):
        page.update()
    assert "resumed 1x" in page.header.text and "completed" in page.header.text
    assert "interrupted" in page.events.data["kind"]
    with __import__("h5py").File(done.path, "r", swmr=True) as f:
        assert page.last_t == max(float(f[g]["time"][-1]) for g in ("clsf", "table", "chamber", "lockin"))

    # the live pair SF (dither-period means of periods ending in each window) against analyze's (whole periods of
    # the raw stream in the same window): they differ by at most the periods at the two edges of each window,
    # |delta m| <= 2 max|m_i - m| / N per step, and the SF change by the sum over both steps divided by SF
    steps = page.file_steps
    mids, live = page.follower.pair_changes(steps, page.settle_s)
    r = analyze(done.path)
    assert mids.shape[0] == len(r.pairs) == 4
    f = page.follower

    def edge(index: int) -> float:
        k = int(np.flatnonzero(steps["index"] == index)[0])
        a, b = float(steps["t_start"][k]) + page.settle_s, float(steps["t_end"][k])
        m = f.clsf_out[(f.clsf_t > a) & (f.clsf_t <= b)]
        return 2 * float(np.max(np.abs(m - m.mean()))) / m.shape[0]

    e = [edge(p.index_plus) + edge(p.index_minus) for p in r.pairs]
    scale = [abs(p.sf_v_per_dps * (p.rate_plus_dps - p.rate_minus_dps)) for p in r.pairs]
    bound = [(e[k] + e[0]) / scale[k] * 1e6 for k in range(len(r.pairs))]
    np.testing.assert_array_less(np.abs(live - [p.true_change_ppm for p in r.pairs]), np.array(bound) + 1e-9)


def test_watch_refuses_what_is_not_a_run_file(tmp_path: Path) -> None:
    bad = tmp_path / "x.h5"
    bad.write_bytes(b"nope")
    for target in (bad, tmp_path / "missing.h5"):
        done = subprocess.run([sys.executable, "-m", "qmg_lab", "watch", str(target)], capture_output=True, text=True)
        assert done.returncode == 2 and "Traceback" not in done.stderr


def test_host_opens_the_page_on_purpose_with_a_warning(tmp_path: Path) -> None:
    path = tmp_path / "live.h5"
    live_writer(path, "w", ["soak"]).close()
    proc = subprocess.Popen(
        [sys.executable, "-m", "qmg_lab", "watch", str(path), "--host", "0.0.0.0", "--port", "5256"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env={**os.environ, "COLUMNS": "300"},
    )
    try:
        line = proc.stdout.readline() if proc.stdout else ""
        assert line.startswith("watching") and ":525" in line
    finally:
        proc.terminate()
        _, err = proc.communicate(timeout=30)
    assert "open to every machine" in err and "without a password" in err


def test_missing_lockin_samples_are_counted_within_each_stretch_read() -> None:
    from qmg_lab.watch.follow import missing_samples

    dt = 1 / 1800
    a = np.arange(100) * dt
    b = 10.0 + np.delete(np.arange(100), [40, 41, 42, 70]) * dt  # 4 samples lost inside the second stretch
    t = np.concatenate((a, b))
    # the jump from the first stretch to the second (chunks not read in between) is no loss
    assert missing_samples(t, [(0, 100), (5000, 5096)]) == 4
    assert missing_samples(a, [(0, 100)]) == 0


def test_the_closed_tab_warning_alone_is_filtered(caplog) -> None:  # type: ignore[no-untyped-def]
    import logging

    from qmg_lab.watch.server import CLOSED_TAB, quiet_closed_tabs

    quiet_closed_tabs()
    quiet_closed_tabs()  # once is enough: a second call adds nothing
    log = logging.getLogger("bokeh.server.views.ws")
    assert len(log.filters) == 1
    with caplog.at_level(logging.WARNING, logger="bokeh.server.views.ws"):
        log.warning(CLOSED_TAB)
        log.warning("another websocket problem")
    assert [r.getMessage() for r in caplog.records] == ["another websocket problem"]


def test_a_stable_range_moves_only_when_its_data_leave_it() -> None:
    """StableRange's rule (its docstring): first [lo - 0.1 w, hi + 0.1 w] rounded out to the 1-2-5 step >= span/5;
    data inside change nothing; data beyond a side move that side out by the span beyond them."""
    r = StableRange()
    r.cover(0.0, 10.0)  # [-1, 11]: span 12, step 5 (>= 2.4)
    assert r.bounds == (-5.0, 15.0)
    assert (r.range.start, r.range.end, r.range.reset_start, r.range.reset_end) == (-5.0, 15.0, -5.0, 15.0)
    r.cover(-4.0, 14.0)
    assert r.bounds == (-5.0, 15.0)
    r.cover(-4.0, 16.0)  # above by 1: the top moves to 16 + 20 = 36; [-5, 36]: span 41, step 10
    assert r.bounds == (-10.0, 40.0)
    r.cover(-12.0, 16.0)  # below: -12 - 50 = -62; [-62, 40]: span 102, step 50
    assert r.bounds == (-100.0, 50.0)
    r.clear()
    r.cover(2200.0, 2200.0)  # flat: w = 2200e-6 -> [2199.99978, 2200.00022], step 1e-4
    a, b = r.bounds or (0.0, 0.0)
    assert math.isclose(a, 2199.9997, rel_tol=1e-12) and math.isclose(b, 2200.0003, rel_tol=1e-12)
    r.clear()
    r.cover(0.0, 0.0)  # flat at zero: w = 1 -> [-0.1, 0.1], step 0.05
    assert r.bounds is not None and np.allclose(r.bounds, (-0.1, 0.1))
    r.cover(math.nan, 1.0)  # nothing finite: nothing moves
    assert r.bounds is not None and np.allclose(r.bounds, (-0.1, 0.1))


def test_every_plot_holds_its_data_and_every_legend_draws_from_a_source_that_never_changes(tmp_path: Path) -> None:
    """After a live file's blocks: each numeric plot's y range holds all of its traces' points; every legend
    entry's renderers draw from the page's key source, which stays as it was made, one row of NaN coordinates (so
    streaming a trace never makes the browser rebuild a legend, and the stand-ins draw nothing); the now panel and
    header are a root of their own, apart from the plots."""
    path = tmp_path / "live.h5"
    w = live_writer(path, "ranges", ["soak", "soak", "soak"])
    try:
        page = WatchPage(path)
        doc = Document()
        page.attach(doc)
        for k in range(3):
            append_block(w, k, "soak")
            page.update()
            assert page.traces["chamber_air"].t.shape[0] > 0
            drawn: dict[str, list[Any]] = {}
            for r in page.plots.select({"type": GlyphRenderer}):
                if r.data_source is page.key_source:
                    continue
                data = r.data_source.data
                ys = [data[c] for c in ("y", "lo", "hi") if c in data and len(data[c])]
                fig = next(f for f in page.plots.select({"type": Plot}) if r in f.renderers)
                drawn.setdefault(fig.name, []).extend(ys)
            for name, arrays in drawn.items():
                if not arrays or not isinstance(doc.get_model_by_name(name).y_range, Range1d):
                    continue
                y = np.concatenate([np.asarray(a, dtype=float) for a in arrays])
                rng = doc.get_model_by_name(name).y_range
                assert rng.start <= np.nanmin(y) and np.nanmax(y) <= rng.end, name
    finally:
        w.set_status("completed")
        w.close()
    legends = list(page.plots.select({"type": Legend}))
    assert len(legends) == len(PLOTS)
    for legend in legends:
        assert legend.items
        for item in legend.items:
            assert all(r.data_source is page.key_source for r in item.renderers)
    key = page.key_source.data
    assert all(len(v) == 1 for v in key.values())
    assert all(np.isnan(key[c][0]) for c in ("t", "y", "lo", "hi", "left", "right"))
    texts = set(page.text.select({"type": Div}))
    assert texts == {page.now, page.header} and not set(page.plots.select({"type": Div}))
    assert [r for r in doc.roots if r is page.text or r is page.plots] == [page.text, page.plots]
