"""The watch page's data side without a browser: a Bokeh Document fed by WatchPage.update() from a running file
(a RunWriter open in this process), bounded traces, the replay of a resumed twin campaign, and the live pair SF
against `qmg-lab analyze`'s. The page in a real browser: test_watch_browser.py."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
from bokeh.document import Document

from qmg_lab.analysis.compute import analyze
from qmg_lab.watch.page import CHUNK_BINS, MAX_POINTS, PLOTS, Trace, WatchPage
from tests.support.live_runs import append_block, interrupted_then_resumed, live_writer


def test_the_page_follows_a_running_file(tmp_path: Path) -> None:
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
            assert len(page.traces["sf_period"].source.data["t"]) == 70 * (k + 1)  # < 2 CHUNK_BINS: all rows
            assert page.traces["chamber_air"].t[-1] == 10.0 * k + 9.5
        assert seen == [10.0, 20.0]  # the last CLSF period ends each block
        page.update()  # nothing new: nothing moves
        assert page.last_t == 20.0
        steps = page.steps.data
        assert steps["label"] == ["completed", "completed", "current"] and steps["color"][-1] == "#d62728"
    finally:
        w.set_status("completed")
        w.close()
    page.update()
    # stopped short of its plan: the step not run stays on the timeline, grey, no longer current
    assert "completed" in page.header.text and page.steps.data["label"] == ["completed", "completed", "planned"]


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
