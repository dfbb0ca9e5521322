"""Crash safety: `qmg-lab run` killed with SIGKILL in the middle of a simulated campaign leaves a file that h5py
opens, with monotonic time; `--resume` finishes it, and the result matches an uninterrupted run of the same
configuration (same seed) step by step: same indices, kinds, table rates and chamber setpoints, each once.

No sleeping: the test waits on the run file's `completed_steps` attribute (read through HDF5 SWMR) between
waits on the process itself.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest

from qmg_lab.config import parse_config
from qmg_lab.plan import build_plan
from tests.test_faults_helpers import config_text, run_inprocess

def long_config() -> str:
    """The short plan with 17 pairs of 10 s table steps (ceil((30 s ramp + 300 s hold) / 20 s)) and lock, dither, soak, return: 38 steps."""
    text = config_text()
    return text.replace("chamber_end_hold_s = 50.0", "chamber_end_hold_s = 300.0")


def qmg(*args: str) -> list[str]:
    return [sys.executable, "-m", "qmg_lab", *args]


def completed_steps(path: Path) -> int:
    """The run file's completed_steps attribute, read as a SWMR reader; -1 while it cannot be opened yet."""
    try:
        with h5py.File(path, "r", swmr=True, libver="latest") as h5:
            return int(h5.attrs["completed_steps"])
    except (OSError, KeyError):
        return -1


def wait_for_steps(proc: subprocess.Popen, path: Path, n: int) -> int:
    """Wait (on the process, 20 ms at a time) until the file records n completed steps; the count seen."""
    seen = -1
    while seen < n:
        try:
            proc.wait(timeout=0.02)
        except subprocess.TimeoutExpired:
            pass
        else:
            pytest.fail(f"the run ended (exit {proc.returncode}) before {n} steps were recorded; "
                        f"stderr: {proc.stderr.read() if proc.stderr else ''}")
        seen = completed_steps(path)
    return seen


def test_kill_9_then_resume_matches_an_uninterrupted_run(tmp_path):
    text = long_config()
    cfg_path = tmp_path / "long.toml"
    cfg_path.write_text(text)
    planned = build_plan(parse_config(text))
    assert len(planned) == 3 + 34 + 1

    path = tmp_path / "killed.h5"
    proc = subprocess.Popen(qmg("run", str(cfg_path), "-o", str(path), "-q"), stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, text=True, cwd=tmp_path)
    seen = wait_for_steps(proc, path, 12)
    os.kill(proc.pid, signal.SIGKILL)
    assert proc.wait() == -signal.SIGKILL

    # the killed file: h5py opens it, time is monotonic, every checkpoint seen before the kill is there
    with h5py.File(path, "r", swmr=True, libver="latest") as h5:
        assert h5.attrs["status"] == "running"
        assert int(h5.attrs["completed_steps"]) >= seen
        t = h5["lockin/time"][:]
        assert len(t) and np.all(np.diff(t) > 0)
        steps_before = h5["steps/index"][:]
        assert len(steps_before) < len(planned)  # killed in the middle

    # the analysis reads the killed file and names exactly the steps the plan has and the file lacks
    an = subprocess.run(qmg("analyze", str(path), "--json"), capture_output=True, text=True, cwd=tmp_path,
                        timeout=120)
    assert an.returncode == 0, an.stderr
    res = json.loads(an.stdout)
    assert res["status"] == "running"
    missing = sorted(set(range(len(planned))) - set(steps_before.tolist()))
    assert [m["index"] for m in res["missing_steps"]] == missing
    assert [m["kind"] for m in res["missing_steps"]] == [planned[i].kind for i in missing]

    done = subprocess.run(qmg("run", str(cfg_path), "--resume", str(path), "-q"), capture_output=True, text=True,
                          cwd=tmp_path, timeout=120)
    assert done.returncode == 0, done.stderr

    ref = run_inprocess(tmp_path, text, name="reference.h5")
    assert ref.error is None
    resumed, reference = h5py.File(path, "r"), h5py.File(ref.path, "r")
    try:
        assert resumed.attrs["status"] == "completed" and int(resumed.attrs["resume_count"]) == 1
        s, r = resumed["steps"], reference["steps"]
        order = np.argsort(s["index"][:])
        assert s["index"][:][order].tolist() == r["index"][:].tolist() == list(range(len(planned)))
        assert s["kind"][:][order].tolist() == r["kind"][:].tolist() == [p.kind.encode() for p in planned]
        assert s["table_rate"][:][order].tolist() == r["table_rate"][:].tolist()
        assert s["chamber_setpoint"][:][order].tolist() == r["chamber_setpoint"][:].tolist()
        assert set(s["status"][:].tolist()) == {b"completed"}
        # steps follow each other in time, and every group's time is monotonic across the resume
        t_start, t_end = s["t_start"][:][order], s["t_end"][:][order]
        assert np.all(t_end >= t_start) and np.all(t_start[1:] >= t_end[:-1] - 1e-9)
        for group in ("lockin", "clsf", "table", "chamber", "truth"):
            tg = resumed[f"{group}/time"][:]
            assert np.all(np.diff(tg) >= 0), group
        assert np.all(np.diff(resumed["lockin/time"][:]) > 0)
    finally:
        resumed.close()
        reference.close()


def test_resume_refuses_another_configuration(tmp_path):
    out = run_inprocess(tmp_path, config_text(faults="interlock_trip_at_s = 30.0"))
    assert out.run().status == "aborted"
    other = tmp_path / "other.toml"
    other.write_text(config_text(seed=4))
    done = subprocess.run(qmg("run", str(other), "--resume", str(out.path), "-q"), capture_output=True, text=True,
                          timeout=60)
    assert done.returncode == 2
    assert "resume with the configuration the run was started with" in done.stderr
    assert "Traceback" not in done.stderr
