"""Snapshots and the run log (issue 12): every run file holds the four instruments' snapshots, at the start and
at each resume, and /events logs faults, reconnects, recoveries, suspensions and the end of the run with its
run time (docs/hdf5.md, "Snapshots and events").

Runs are short campaigns on the twins, in-process (tests/test_faults_helpers.py); the expected identities are
the twins' documented answers (DS345 *IDN?, the 1291BR STA liveness, the EC1x STATUS?).
"""

from __future__ import annotations

from pathlib import Path

import h5py

from qmg_lab.storage.records import read_events, read_snapshots
from tests.support.campaigns import config_text, run_inprocess

NAMES = {"lockin", "generator", "table", "chamber"}


def test_every_run_file_holds_the_four_snapshots(tmp_path: Path) -> None:
    out = run_inprocess(tmp_path, config_text())
    assert out.error is None
    with h5py.File(out.path, "r", swmr=True) as f:
        snaps = read_snapshots(f)
        events = read_events(f)
        assert f["snapshots/json"].attrs["units"] == "byte"
    assert {s["instrument"] for s in snaps} == NAMES and len(snaps) == 4
    assert {s["occasion"] for s in snaps} == {"start"}
    docs = {s["instrument"]: s["document"] for s in snaps}
    assert docs["generator"]["identity"].startswith("StanfordResearchSystems,DS345,")
    assert docs["generator"]["firmware"] == docs["generator"]["identity"].split(",")[3]
    assert "1291BR" in docs["table"]["identity"]
    assert docs["table"]["settings"]["framing"] == {
        "command_terminator": "CRLF",
        "reply_terminator": "auto",
        "prompt": ">",
    }
    assert docs["chamber"]["settings"]["safe_setpoint_c"] == 20.0  # SHORT_TOML
    assert "HF2LI" in docs["lockin"]["identity"]
    assert docs["lockin"]["state"]["pll"]["enable"] == 1  # taken after the loops were configured
    for name, doc in docs.items():
        assert doc["simulated"] is True and doc["address"] == "twin", name
        assert "error" not in doc, name
    kinds = [e["kind"] for e in events]
    assert kinds[0] == "started" and kinds[-2:] == ["safe_state", "completed"]
    assert events[-1]["time"] >= 109.0  # the run's end, in run time


def test_faults_reconnects_and_suspensions_are_logged_with_run_time(tmp_path: Path) -> None:
    # the table's link drops at 40 s for 6 s: reconnects fail, the campaign suspends, recovers, completes
    out = run_inprocess(
        tmp_path, config_text('disconnect_at_s = [40.0]\ndisconnect_duration_s = 6.0\ndisconnect_instrument = "table"')
    )
    assert out.error is None, out.error
    with h5py.File(out.path, "r", swmr=True) as f:
        events = read_events(f)
    table = [e for e in events if e["instrument"] == "table"]
    first_fault = next(e for e in table if e["kind"] == "fault")
    assert 40.0 <= first_fault["time"] <= 43.0 and "timeout" in first_fault["message"]
    assert any(e["kind"] == "reconnect" for e in table)
    recovered = [e for e in table if e["kind"] == "recovered"]
    assert recovered and all(46.0 <= e["time"] <= 52.0 for e in recovered)
    suspended = [e for e in events if e["kind"] == "suspended"]
    assert suspended and "table being recovered" in suspended[0]["message"]
    assert any(e["kind"] == "resumed" for e in events)
    times = [e["time"] for e in events]
    assert times == sorted(times)


def test_a_resume_adds_four_resume_snapshots(tmp_path: Path) -> None:
    text = config_text()

    def stop_at_30_s(p) -> None:
        if p.run_time_s >= 30.0:
            raise KeyboardInterrupt  # what Ctrl-C raises inside a block

    first = run_inprocess(tmp_path, text, progress=stop_at_30_s)
    assert first.error is not None
    with h5py.File(first.path, "r", swmr=True) as f:
        ends = [e for e in read_events(f) if e["kind"] in ("abort", "interrupted")]
    assert [e["kind"] for e in ends] == ["interrupted"] and ends[0]["time"] >= 30.0
    second = run_inprocess(tmp_path, text, resume=True)
    assert second.error is None, second.error
    with h5py.File(second.path, "r", swmr=True) as f:
        snaps = read_snapshots(f)
        events = read_events(f)
    assert [s["occasion"] for s in snaps].count("start") == 4
    resumed = [s for s in snaps if s["occasion"] == "resume"]
    assert {s["instrument"] for s in resumed} == NAMES
    assert all(s["time"] >= 30.0 for s in resumed)
    assert [e["message"] for e in events if e["kind"] == "started"] == ["new run", "resumed run"]


def test_a_file_from_before_the_records_gets_them_when_resumed(tmp_path: Path) -> None:
    """A run file written before /snapshots and /events existed: --resume lays them out (before SWMR) and the
    resumed run records its four resume snapshots."""
    text = config_text()

    def stop_at_20_s(p) -> None:
        if p.run_time_s >= 20.0:
            raise KeyboardInterrupt

    first = run_inprocess(tmp_path, text, progress=stop_at_20_s)
    assert first.error is not None
    with h5py.File(first.path, "r+") as f:  # as an older qmg-lab wrote it
        del f["snapshots"], f["events"]
    second = run_inprocess(tmp_path, text, resume=True)
    assert second.error is None, second.error
    with h5py.File(second.path, "r", swmr=True) as f:
        snaps = read_snapshots(f)
        kinds = [e["kind"] for e in read_events(f)]
    assert sorted(s["instrument"] for s in snaps) == sorted(NAMES) and {s["occasion"] for s in snaps} == {"resume"}
    assert kinds[0] == "started" and kinds[-1] == "completed"
