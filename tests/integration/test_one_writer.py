"""A run file has one writer: while run A writes F, `qmg-lab run ... -o F --overwrite` and `--resume F` are refused
(exit 2, the writer named) and A's file completes intact; two runs started together on one -o: one is refused,
the other completes, and the file holds exactly one run's plan. The lock is released when its holder dies
(SIGKILL): a resume can take the file over at once. Creating a file leaves no hidden temporary file behind and
never replaces a file that appeared meanwhile.

No sleeping: the tests wait on the run file (completed_steps) and on the processes.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

import h5py
import pytest

from qmg_lab.campaign.plan import build_plan
from qmg_lab.config.schema import parse_config
from qmg_lab.storage.layout import StorageError
from qmg_lab.storage.lock import RunFileLock, lock_path, writer_state
from qmg_lab.storage.writer import RunWriter
from tests.integration.test_resume import wait_for_steps
from tests.support.campaigns import config_text, long_config, qmg


def _plan_rows(cfg: Path) -> list[tuple[int, str]]:
    return [(s.index, s.label) for s in build_plan(parse_config(cfg.read_text()))]


def _file_rows(path: Path) -> list[tuple[int, str]]:
    with h5py.File(path, "r") as h5:
        assert h5.attrs["status"] == "completed"
        return sorted(zip(h5["steps/index"][:].tolist(), [k.decode() for k in h5["steps/kind"][:]], strict=True))


@pytest.fixture
def short_cfg(tmp_path: Path) -> Path:
    cfg = tmp_path / "short.toml"
    cfg.write_text(config_text())
    return cfg


@pytest.fixture
def endless_cfg(tmp_path: Path) -> Path:
    """A plan of a simulated day: it cannot end while the test works on its file (no race on wall time)."""
    cfg = tmp_path / "endless.toml"
    cfg.write_text(long_config().replace("chamber_end_hold_s = 300.0", "chamber_end_hold_s = 86400.0"))
    return cfg


def _started(cfg: Path, path: Path, steps: int) -> subprocess.Popen:
    """`qmg-lab run CFG -o PATH` started, once its file records `steps` completed steps."""
    proc = subprocess.Popen(
        qmg("run", str(cfg), "-o", str(path), "-q"), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE
    )
    wait_for_steps(proc, path, steps)
    return proc


def _stop(proc: subprocess.Popen) -> None:
    proc.send_signal(signal.SIGTERM)  # the safe way to stop a run (test_signals.py)
    proc.communicate(timeout=300)
    assert proc.returncode == 128 + signal.SIGTERM


@pytest.mark.skipif(sys.platform == "win32", reason="stopped with SIGTERM (Windows terminates the process)")
def test_a_live_runs_file_is_neither_overwritten_nor_resumed(tmp_path: Path, endless_cfg: Path) -> None:
    path = tmp_path / "F.h5"
    a = _started(endless_cfg, path, 2)
    for args in (("-o", str(path), "--overwrite"), ("--resume", str(path))):
        b = subprocess.run(qmg("run", str(endless_cfg), *args, "-q"), capture_output=True, text=True, timeout=300)
        assert b.returncode == 2, b.stderr
        said = " ".join(b.stderr.split())
        assert "being written by another qmg-lab process" in said and f"process {a.pid}" in said
        assert "Traceback" not in said
    seen = wait_for_steps(a, path, 6)  # A went on writing its file meanwhile
    _stop(a)
    with h5py.File(path, "r") as h5:  # A's data intact: its plan's first steps, each once, in order
        assert h5.attrs["status"] == "aborted"
        rows = list(zip(h5["steps/index"][:].tolist(), [k.decode() for k in h5["steps/kind"][:]], strict=True))
    assert len(rows) >= seen and rows == _plan_rows(endless_cfg)[: len(rows)]


def test_two_runs_started_together_on_one_path(tmp_path: Path, short_cfg: Path) -> None:
    path = tmp_path / "F.h5"
    runs = [
        subprocess.Popen(
            qmg("run", str(short_cfg), "-o", str(path), "-q"),
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
            text=True,
        )
        for _ in range(2)
    ]
    outcomes = [(p.wait(timeout=600), p.stderr.read() if p.stderr else "") for p in runs]
    codes = sorted(code for code, _ in outcomes)
    assert codes == [0, 2], outcomes
    refused = next(err for code, err in outcomes if code == 2)
    said = " ".join(refused.split())
    assert "being written by another qmg-lab process" in said or "exists" in said
    assert "Traceback" not in said
    assert _file_rows(path) == _plan_rows(short_cfg)
    # no temporary file left behind; the lock file stays (filelock keeps it so waiters share one inode), free
    assert [p.name for p in tmp_path.glob(".F.h5.*")] == [".F.h5.lock"]
    assert writer_state(path) == "gone"


@pytest.mark.skipif(sys.platform == "win32", reason="SIGKILL")
def test_the_lock_dies_with_its_holder(tmp_path: Path, endless_cfg: Path) -> None:
    path = tmp_path / "F.h5"
    a = _started(endless_cfg, path, 3)
    with pytest.raises(StorageError, match="being written by another"):
        RunFileLock(path).acquire()
    os.kill(a.pid, signal.SIGKILL)
    a.wait()
    assert lock_path(path).exists()  # a stale lock file: harmless
    with RunFileLock(path):  # the kernel released the dead holder's lock
        pass
    b = subprocess.Popen(
        qmg("run", str(endless_cfg), "--resume", str(path), "-q"), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE
    )
    with h5py.File(path, "r", swmr=True, libver="latest") as h5:
        before = int(h5["steps/index"].shape[0])
    wait_for_steps(b, path, before + 1)  # the resume took the file over and completes steps
    _stop(b)


def test_the_lock_is_reentrant_in_one_process_and_exclusive_across_writers(tmp_path: Path) -> None:
    path = tmp_path / "F.h5"
    with RunFileLock(path):
        w = RunWriter.create(
            path, config_text="", config_sha256="x", mode="sim", software_version="t", t0_unix=0.0, truth=False
        )
        w.close()  # the writer's share of the lock ends; the outer one still holds it
        assert writer_state(path) == "writing"  # held by this process
    assert lock_path(path).exists() and writer_state(path) == "gone"
    with pytest.raises(StorageError, match="already exists"):
        RunWriter.create(
            path, config_text="", config_sha256="x", mode="sim", software_version="t", t0_unix=0.0, truth=False
        )
    assert sorted(p.name for p in tmp_path.iterdir()) == [".F.h5.lock", "F.h5"]


def test_a_reused_pid_is_not_a_writer_and_a_held_lock_is(tmp_path: Path) -> None:
    """Liveness is the lock's state, never the recorded pid: a "running" file whose recorded writer pid names a
    live process (here this test's own parent, as after PID reuse) but whose lock is free is an interrupted run
    that --resume may continue; while another process holds the lock it is running, and --resume's check
    refuses."""
    from qmg_lab.storage.writer import read_run, status_detail

    path = tmp_path / "F.h5"
    w = RunWriter.create(
        path, config_text="", config_sha256="x", mode="sim", software_version="t", t0_unix=0.0, truth=False
    )
    w._h5.attrs["writer_pid"] = os.getppid()  # a live process that is not the writer
    w.close()  # status stays "running", as a killed writer leaves it
    assert status_detail(read_run(path, select=())) == "interrupted (process died)"
    RunWriter.check_resumable(path, config_sha256="x")  # not refused: the lock is free

    hold = "from qmg_lab.storage.lock import RunFileLock; import sys; RunFileLock(sys.argv[1]).acquire(); "
    hold += "print('held', flush=True); sys.stdin.read()"
    holder = subprocess.Popen(
        [sys.executable, "-c", hold, str(path)],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert holder.stdout is not None and holder.stdout.readline().strip() == "held"
        assert writer_state(path) == "writing"
        assert status_detail(read_run(path, select=())).startswith("running (process")
        with pytest.raises(StorageError, match="still being written by another process"):
            RunWriter.check_resumable(path, config_sha256="x")
    finally:
        holder.communicate("")
    assert writer_state(path) == "gone"


def test_a_reader_holding_the_file_is_named_when_a_resume_cannot_open_it(tmp_path: Path) -> None:
    """HDF5 locks a file for each open: a plain (non-SWMR) reader in another process makes the writer's open fail
    with "unable to lock file". The resume waits a moment (a polling reader lets go within milliseconds), then says
    that a reader holds the file, naming the reader's process, and changes nothing."""
    path = tmp_path / "F.h5"
    w = RunWriter.create(
        path, config_text="", config_sha256="x", mode="sim", software_version="t", t0_unix=0.0, truth=False
    )
    w.set_status("aborted", "test")
    w.close()
    before = path.read_bytes()
    hold = "import h5py, sys; f = h5py.File(sys.argv[1], 'r'); print('open', flush=True); sys.stdin.read()"
    reader = subprocess.Popen(
        [sys.executable, "-c", hold, str(path)], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True
    )
    try:
        assert reader.stdout is not None and reader.stdout.readline().strip() == "open"
        with pytest.raises(StorageError, match="another process holds the run file open for reading") as err:
            RunWriter.reopen(path, config_sha256="x")
        assert f"(process {reader.pid} (" in str(err.value)  # named: its id and command line (storage/holders.py)
    finally:
        reader.communicate("")
    assert path.read_bytes() == before
    RunWriter.reopen(path, config_sha256="x").close()  # the reader gone, the resume opens it
