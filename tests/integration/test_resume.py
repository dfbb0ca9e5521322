"""Crash safety: `qmg-lab run` killed with SIGKILL in the middle of a simulated campaign leaves a file that h5py
opens, with monotonic time; `--resume` finishes it, and the result matches an uninterrupted run of the same
configuration (same seed) step by step: same indices, kinds, table rates and chamber setpoints, each once; every
time axis runs on continuously across the resume (no gap longer than the group's own spacing) and /truth is the
twin's truth at exactly the /lockin sample times.

The resume edge cases change nothing in the file (its bytes are compared): a completed run is refused (exit 2,
"already completed"), a station that does not answer ends with exit 3 before the file is touched, and a run made
on the twins is not resumed on the hardware (exit 2, saying to add --sim).

No sleeping: the test waits on the run file's `completed_steps` attribute (read through HDF5 SWMR) between
waits on the process itself.
"""

from __future__ import annotations

import hashlib
import json
import os
import signal
import subprocess
from pathlib import Path

import h5py
import numpy as np
import pytest
import typer

from qmg_lab.campaign.plan import build_plan
from qmg_lab.config.schema import config_fingerprint, parse_config
from qmg_lab.storage.writer import RunWriter, read_run
from tests.support.campaigns import completed_steps, config_text, long_config, qmg, run_inprocess


def wait_for_steps(proc: subprocess.Popen, path: Path, n: int) -> int:
    """Wait (on the process, 20 ms at a time) until the file records n completed steps; the count seen."""
    seen = -1
    while seen < n:
        try:
            proc.wait(timeout=0.02)
        except subprocess.TimeoutExpired:
            pass
        else:
            pytest.fail(
                f"the run ended (exit {proc.returncode}) before {n} steps were recorded; "
                f"stderr: {proc.stderr.read() if proc.stderr else ''}"
            )
        seen = completed_steps(path)
    return seen


def test_kill_9_then_resume_matches_an_uninterrupted_run(tmp_path):
    text = long_config()
    cfg_path = tmp_path / "long.toml"
    cfg_path.write_text(text)
    planned = build_plan(parse_config(text))
    assert len(planned) == 3 + 34 + 1

    path = tmp_path / "killed.h5"
    proc = subprocess.Popen(
        qmg("run", str(cfg_path), "-o", str(path), "-q"),
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
        cwd=tmp_path,
    )
    # killed after the 4th step: 34 steps (more than 300 s simulated) remain, so even a parent process starved
    # by a loaded machine kills it before it could finish
    seen = wait_for_steps(proc, path, 4)
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
    an = subprocess.run(qmg("analyze", str(path), "--json"), capture_output=True, text=True, cwd=tmp_path, timeout=120)
    assert an.returncode == 0, an.stderr
    res = json.loads(an.stdout)
    assert res["status"] == "running" and res["status_detail"] == "interrupted (process died)"
    missing = sorted(set(range(len(planned))) - set(steps_before.tolist()))
    assert [m["index"] for m in res["missing_steps"]] == missing
    assert [m["kind"] for m in res["missing_steps"]] == [planned[i].kind for i in missing]

    done = subprocess.run(
        qmg("run", str(cfg_path), "--resume", str(path), "-q"),
        capture_output=True,
        text=True,
        cwd=tmp_path,
        timeout=120,
    )
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
        # continuous: the lock-in samples 1/demod_rate_hz apart everywhere, the resume point included, and the
        # file ends where its last step does (nothing after the end of the run's own data)
        rate = parse_config(text).lockin.demod_rate_hz
        dt = round(210e6 / rate) / 210e6  # the HF2 twin streams in whole ticks of its 210 MHz clock
        tl = resumed["lockin/time"][:]
        assert tl[0] == 0.0
        np.testing.assert_allclose(np.diff(tl), dt, rtol=1e-6)
        assert t_end.max() <= tl[-1]
        # table and chamber: one reading per block (blocks of lockin.sim_poll_interval_s at most)
        for group in ("table", "chamber"):
            assert np.diff(resumed[f"{group}/time"][:]).max() <= parse_config(text).lockin.sim_poll_interval_s + dt
        # /truth: the twin's truth at exactly the lock-in sample times, from the first sample on
        np.testing.assert_array_equal(resumed["truth/time"][:], tl)
    finally:
        resumed.close()
        reference.close()


def test_resume_refuses_another_configuration(tmp_path):
    out = run_inprocess(tmp_path, config_text(faults="interlock_trip_at_s = 30.0"))
    assert out.run().status == "aborted"
    other = tmp_path / "other.toml"
    other.write_text(config_text(seed=4))
    done = subprocess.run(
        qmg("run", str(other), "--resume", str(out.path), "-q"), capture_output=True, text=True, timeout=60
    )
    assert done.returncode == 2
    assert "resume with the configuration the run was started with" in done.stderr
    assert "Traceback" not in done.stderr


def file_digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def test_resuming_a_completed_run_is_refused_and_changes_nothing(tmp_path):
    text = config_text()
    out = run_inprocess(tmp_path, text)
    assert out.error is None and out.run().status == "completed"
    cfg_path = tmp_path / "short.toml"
    cfg_path.write_text(text)
    before = file_digest(out.path)
    done = subprocess.run(
        qmg("run", str(cfg_path), "--resume", str(out.path), "-q"), capture_output=True, text=True, timeout=120
    )
    assert done.returncode == 2, done.stderr
    assert "already completed" in " ".join(done.stderr.split()) and "Traceback" not in done.stderr
    assert file_digest(out.path) == before


def test_resume_that_cannot_connect_changes_nothing(tmp_path):
    """A bench run (every instrument on hardware) left "running" by a killed process; the bench does not answer
    on this machine: exit 3, and the file is exactly as the killed process left it."""
    text = config_text().replace("sim = true", "sim = false")
    assert "sim = true" not in text
    cfg_path = tmp_path / "bench.toml"
    cfg_path.write_text(text)
    path = tmp_path / "bench.h5"
    w = RunWriter.create(
        path,
        config_text=text,
        config_sha256=config_fingerprint(text),
        mode="hardware",
        software_version="test",
        t0_unix=0.0,
        truth=False,
    )
    w.append_step(
        index=0, kind="lock", t_start=0.0, t_end=2.0, table_rate=0.0, chamber_setpoint=25.0, status="completed"
    )
    w.set_status("aborted", "power cut")
    w.close()
    before = file_digest(path)
    done = subprocess.run(
        qmg("run", str(cfg_path), "--resume", str(path), "-q"), capture_output=True, text=True, timeout=120
    )
    assert done.returncode == 3, done.stderr
    assert "could not connect" in " ".join(done.stderr.split()) and "Traceback" not in done.stderr
    assert file_digest(path) == before


def test_a_twin_run_is_not_resumed_on_the_hardware(tmp_path):
    """A bench configuration run with --sim (every instrument its twin) and aborted; `--resume` without --sim
    would continue it on the bench: exit 2, naming the instruments and saying to add --sim; file unchanged."""
    text = config_text(faults="interlock_trip_at_s = 30.0").replace("sim = true", "sim = false")
    cfg_path = tmp_path / "bench.toml"
    cfg_path.write_text(text)
    path = tmp_path / "twins.h5"
    first = subprocess.run(
        qmg("run", str(cfg_path), "--sim", "-o", str(path), "-q"), capture_output=True, text=True, timeout=120
    )
    assert first.returncode == 3, first.stderr  # the interlock
    before = file_digest(path)
    done = subprocess.run(
        qmg("run", str(cfg_path), "--resume", str(path), "-q"), capture_output=True, text=True, timeout=120
    )
    assert done.returncode == 2, done.stderr
    message = " ".join(done.stderr.split())  # the console wraps long lines
    assert "lockin was twin, now hardware" in message and "resume it with --sim" in message
    assert "Traceback" not in done.stderr
    assert file_digest(path) == before


def test_truth_is_aligned_with_the_lockin_when_samples_are_lost(tmp_path):
    """The HF2 twin drops 50 samples in the middle of a block: /lockin has a 51-period gap there and /truth the same
    rows (the twin's truth of exactly the delivered samples), from the very first sample on."""
    out = run_inprocess(tmp_path, config_text(faults="sample_loss_at_s = [30.0]\nsample_loss_count = 50"))
    assert out.error is None
    run = out.run()
    tl, tt = run.groups["lockin"]["time"], run.groups["truth"]["time"]
    np.testing.assert_array_equal(tt, tl)
    dt = 1.0 / out.cfg.lockin.demod_rate_hz
    gaps = np.rint(np.diff(tl) / dt).astype(int)
    assert sorted(set(gaps.tolist())) == [1, 51] and np.sum(gaps == 51) == 1


def test_the_cli_final_close_is_protected_from_a_second_ctrl_c(tmp_path, monkeypatch):
    """Two Ctrl-C arrive while the CLI closes the run file: the close completes (the file is clean, its superblock
    flags cleared) and the interrupt is raised after it (the command exits 130). Unprotected, the second Ctrl-C
    would cut the close."""
    import signal as sig

    from qmg_lab.cli import main as cli
    from qmg_lab.storage.writer import RunWriter

    closes_completed: list[bool] = []
    plain_close = RunWriter.close

    def close_with_two_ctrl_c(self: RunWriter) -> None:
        if not self.closed:
            os.kill(os.getpid(), sig.SIGINT)
            os.kill(os.getpid(), sig.SIGINT)
            self._flush_buffers()  # some of the close's own work after the signals arrived
        plain_close(self)
        closes_completed.append(True)

    # on the class, so that the writer the CLI makes (whichever module creates it) closes this way
    monkeypatch.setattr(RunWriter, "close", close_with_two_ctrl_c)
    text = config_text()
    path = tmp_path / "run.h5"
    with pytest.raises(typer.Exit) as stopped:  # the second signal, raised after the close: exit 128 + SIGINT
        cli._execute(parse_config(text), text, output=path, resume=None, quiet=True)
    assert stopped.value.exit_code == 130
    assert closes_completed == [True]  # the interrupt came after the close, not in the middle of it
    run = read_run(path)
    assert run.status == "completed" and not run.writer_open


def test_a_resume_continues_the_twin_table_where_it_stood(tmp_path):
    """The table does not turn back to 0 deg because its host process died: a run stopped in the middle of a
    +5 deg/s step is resumed with the twin's table at the angle of its last /table reading (the once-per-revolution
    rate ripple, table_rate_ripple_ppm, depends on it: a table put back at 0 deg gives the resumed steps another
    delivered rate than the uninterrupted run's). Between the stop and the first reading of the resumed run the
    table does not move: the safe state stopped it, and the resume waits for lock with the table at rest."""
    stopped_at: list[float] = []

    def progress(p) -> None:
        if p.step.index == 5 and p.step_elapsed_s >= 6.0 and not stopped_at:
            stopped_at.append(p.run_time_s)
            os.kill(os.getpid(), signal.SIGINT)

    text = config_text()
    first = run_inprocess(tmp_path, text, progress=progress)
    assert stopped_at and first.error is not None
    before = first.run().groups["table"]
    angle = float(before["position"][-1])
    assert angle > 20.0  # 6 s into a +5 deg/s step that started at 0 deg
    second = run_inprocess(tmp_path, text, resume=True)
    assert second.error is None
    after = second.run().groups["table"]
    later = after["time"] > before["time"][-1]
    assert after["rate_measured"][later][0] == 0.0  # at rest: the first reading of the resumed run is in its lock wait
    assert abs(float(after["position"][later][0]) - angle) < 0.01  # the 1291BR's position reads to 0.01 deg
