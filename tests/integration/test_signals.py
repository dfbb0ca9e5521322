"""Every way a process is asked to stop ends in the safe state: SIGTERM, SIGHUP, SIGQUIT and a double SIGINT sent
to `qmg-lab run` (a real subprocess on the twins) end with exit 128 + the signal's number, the file's status
"aborted" with the signal named, a `safe_state` event "confirmed" and the terminal saying the same; then
`--resume` completes the run with exactly the plan's steps (each once, "completed"), which is what an
uninterrupted run records.

A full stdout and stderr (/dev/full: every write fails with ENOSPC) do not change how a run ends: exit 0,
"completed". After a table link drop longer than the recovery allows (120 s, the issue's case), the terminal's
last words about the safe state are the file's safe_state event, word for word ("not confirmed: table: ...").

No sleeping: the test waits on the run file's completed_steps (SWMR reads) between 20 ms waits on the process.
After the signal the short plan still has 8 table steps (more than 80 s simulated) to run, far more than the
test's polling latency.
"""

from __future__ import annotations

import shutil
import signal
import subprocess
import sys
from pathlib import Path

import h5py
import pytest

from qmg_lab.campaign.plan import build_plan
from qmg_lab.config.schema import parse_config
from qmg_lab.storage.records import read_events
from tests.integration.test_resume import wait_for_steps
from tests.support.campaigns import config_text, qmg

pytestmark = pytest.mark.skipif(sys.platform == "win32", reason="POSIX signals (SIGHUP, SIGQUIT) are sent here")

CASES = (
    [
        ("SIGTERM", (signal.SIGTERM,), 128 + signal.SIGTERM, "SIGTERM"),
        ("SIGHUP", (signal.SIGHUP,), 128 + signal.SIGHUP, "SIGHUP"),
        ("SIGQUIT", (signal.SIGQUIT,), 128 + signal.SIGQUIT, "SIGQUIT"),
        ("double SIGINT", (signal.SIGINT, signal.SIGINT), 130, "Ctrl-C"),
    ]
    if sys.platform != "win32"
    else []
)


@pytest.mark.parametrize(("label", "signals", "code", "named"), CASES, ids=[c[0] for c in CASES])
def test_stop_signal_ends_safe_and_the_run_resumes(tmp_path: Path, label, signals, code, named) -> None:
    text = config_text()
    cfg_path = tmp_path / "short.toml"
    cfg_path.write_text(text)
    plan = build_plan(parse_config(text))
    path = tmp_path / "run.h5"
    proc = subprocess.Popen(
        qmg("run", str(cfg_path), "-o", str(path), "-q"),
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,  # its own session: the SIGHUP sent here is the only one it gets
    )
    wait_for_steps(proc, path, 4)
    for sig in signals:
        proc.send_signal(sig)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == code, err
    assert "Traceback" not in err
    assert "(safe_state: confirmed)" in err  # the terminal's words are the file's event's
    with h5py.File(path, "r") as h5:
        assert h5.attrs["status"] == "aborted"
        assert named in h5.attrs["abort_reason"]
        events = read_events(h5)
        done_before = int(h5.attrs["completed_steps"])
    kinds = [e["kind"] for e in events]
    assert kinds[-2:] == ["safe_state", "interrupted"], kinds
    assert events[-2]["message"] == "confirmed"
    assert named in events[-1]["message"]
    assert 4 <= done_before < len(plan)

    resumed = subprocess.run(
        qmg("run", str(cfg_path), "--resume", str(path), "-q"), capture_output=True, text=True, timeout=600
    )
    assert resumed.returncode == 0, resumed.stderr
    with h5py.File(path, "r") as h5:
        assert h5.attrs["status"] == "completed"
        assert int(h5.attrs["resume_count"]) == 1
        rows = list(
            zip(
                h5["steps/index"][:].tolist(),
                [k.decode() for k in h5["steps/kind"][:]],
                h5["steps/table_rate"][:].tolist(),
                [s.decode() for s in h5["steps/status"][:]],
                strict=True,
            )
        )
    assert sorted(rows) == [(s.index, s.label, s.table_rate_dps, "completed") for s in plan]


@pytest.mark.skipif(not Path("/dev/full").exists(), reason="needs /dev/full")
def test_a_full_stdout_and_stderr_do_not_abort_a_run(tmp_path: Path) -> None:
    cfg_path = tmp_path / "short.toml"
    cfg_path.write_text(config_text())
    path = tmp_path / "run.h5"
    with open("/dev/full", "w") as full:
        # progress on (no -q): every progress line, log line and the summary table fail to be written
        done = subprocess.run(
            qmg("--log-level", "INFO", "run", str(cfg_path), "-o", str(path)),
            stdout=full,
            stderr=full,
            timeout=600,
        )
    assert done.returncode == 0
    with h5py.File(path, "r") as h5:
        assert h5.attrs["status"] == "completed"


def test_the_terminal_says_what_the_files_safe_state_event_says(tmp_path: Path) -> None:
    # the table's link drops at 40 s for 120 s: recovery gives up after recovery.timeout_s (30 s), and the safe
    # state cannot reach the table within recovery.safe_state_timeout_s (30 s) either: "not confirmed"
    faults = 'disconnect_at_s = [40.0]\ndisconnect_duration_s = 120.0\ndisconnect_instrument = "table"'
    cfg_path = tmp_path / "drop.toml"
    cfg_path.write_text(config_text(faults))
    path = tmp_path / "run.h5"
    done = subprocess.run(qmg("run", str(cfg_path), "-o", str(path), "-q"), capture_output=True, text=True)
    assert done.returncode == 3, done.stderr
    with h5py.File(path, "r") as h5:
        note = next(e["message"] for e in read_events(h5) if e["kind"] == "safe_state")
    assert note.startswith("not confirmed: table")
    said = " ".join(done.stderr.split())
    assert f"safe_state: {' '.join(note.split())}" in said
    assert "instruments in their safe state" not in said


@pytest.mark.parametrize("quiet", [True, False], ids=["-q", "progress"])
def test_a_run_whose_output_reader_died_completes_with_exit_0(tmp_path: Path, quiet: bool) -> None:
    """`qmg-lab run ... | consumer` where the consumer is gone before anything is written: every write to the
    pipe fails with EPIPE (rich's Console would raise SystemExit(1) there). With -q only the summary meets the
    dead pipe; with progress on, stderr's reader is gone too. The run completes and exits 0."""
    cfg_path = tmp_path / "short.toml"
    cfg_path.write_text(config_text())
    path = tmp_path / "run.h5"
    argv = qmg("run", str(cfg_path), "-o", str(path), *(["-q"] if quiet else []))
    proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    assert proc.stdout is not None and proc.stderr is not None
    proc.stdout.close()  # the reader of stdout dies at once
    if not quiet:
        proc.stderr.close()
    assert proc.wait(timeout=600) == 0
    with h5py.File(path, "r") as h5:
        assert h5.attrs["status"] == "completed" and h5.attrs["abort_reason"] == ""


def test_a_run_under_nohup_outlives_a_hang_up(tmp_path: Path) -> None:
    """`nohup qmg-lab run ...`: SIGHUP is ignored by whoever started the run, and the run keeps it so: a hang-up
    in the middle of the run changes nothing, the run completes and exits 0."""
    text = config_text()
    cfg_path = tmp_path / "short.toml"
    cfg_path.write_text(text)
    path = tmp_path / "run.h5"
    nohup = shutil.which("nohup")
    if nohup is None:
        pytest.skip("no nohup on this system")
    proc = subprocess.Popen(
        [nohup, *qmg("run", str(cfg_path), "-o", str(path), "-q")],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,  # its own session: the SIGHUP sent here is the only one it gets
    )
    wait_for_steps(proc, path, 4)
    proc.send_signal(signal.SIGHUP)
    _, err = proc.communicate(timeout=600)
    assert proc.returncode == 0, err
    with h5py.File(path, "r") as h5:
        assert h5.attrs["status"] == "completed"
        assert sorted(h5["steps/index"][:].tolist()) == [s.index for s in build_plan(parse_config(text))]
