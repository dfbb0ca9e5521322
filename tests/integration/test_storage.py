"""The qmg-lab/1 run file: layout and units (docs/hdf5.md), appends, SWMR reads, kill and resume."""

from __future__ import annotations

import hashlib
import json
import os
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import h5py
import numpy as np
import pytest

from qmg_lab.storage.writer import RunWriter, StorageError, read_run, writer_flags_set

REPO = Path(__file__).resolve().parents[2]
CONFIG = "[campaign]\nname = 'storage test'\n"
SHA = hashlib.sha256(CONFIG.encode()).hexdigest()
FS = 1400.0  # Sa/s

# The contract, written out from the file contract in docs/hdf5.md (not imported from the code under test).
CONTRACT = {
    "lockin": {
        "time": "s",
        "x_sense": "V",
        "y_sense": "V",
        "rate_output": "V",
        "drive_amplitude": "V",
        "drive_frequency": "Hz",
        "dither": "V",
        "table_encoder": "1",
        "pll_locked": "1",
    },
    "clsf": {"time": "s", "eta": "1", "sf_change_estimate": "1", "gain_correction": "1", "rate_output_mean": "V"},
    "table": {"time": "s", "rate_command": "deg/s", "rate_measured": "deg/s", "position": "deg"},
    "chamber": {"time": "s", "setpoint": "degC", "temperature": "degC"},
    "steps": {
        "index": "1",
        "kind": "text",
        "t_start": "s",
        "t_end": "s",
        "table_rate": "deg/s",
        "chamber_setpoint": "degC",
        "status": "text",
    },
    "truth": {"time": "s", "scale_factor": "V/(deg/s)", "temperature": "degC", "rate": "deg/s"},
}
ROOT_ATTRS = [
    "format",
    "created",
    "t0_unix",
    "software_version",
    "mode",
    "config_toml",
    "config_sha256",
    "status",
    "abort_reason",
    "completed_steps",
    "resume_count",
    "planned_steps",
    "planned_step_kinds",
]


def lockin_block(k: int, n: int = 700) -> dict[str, np.ndarray]:
    """Block k of n samples at 1400 Sa/s; every column a known function of time."""
    t = (k * n + np.arange(n)) / FS
    return {
        "time": t,
        "x_sense": 1e-3 * np.sin(t),
        "y_sense": 2e-3 * np.cos(t),
        "rate_output": 0.06 * 5 + 0 * t,
        "drive_amplitude": 0.5 + 0 * t,
        "drive_frequency": 2200.0 + 1e-3 * t,
        "dither": np.sign(np.sin(2 * np.pi * 7 * t)),
        "table_encoder": np.floor(200 * t) % 4,
        "pll_locked": np.ones(n, dtype=np.uint8),
    }


def new_writer(path: Path, **kw) -> RunWriter:
    args = dict(config_text=CONFIG, config_sha256=SHA, mode="sim", software_version="0.1.0", t0_unix=1.7e9, truth=True)
    args.update(kw)
    return RunWriter.create(path, **args)


def test_every_contract_item_present_with_units(tmp_path: Path) -> None:
    p = tmp_path / "run.h5"
    w = new_writer(p, planned_steps=3, planned_step_kinds=["lock", "rate", "rate"])
    w.close()
    with h5py.File(p, "r") as f:
        for a in ROOT_ATTRS:
            assert a in f.attrs, a
        assert f.attrs["format"] == "qmg-lab/2"  # new files: layout.FORMAT
        assert f.attrs["status"] == "running"
        assert f.attrs["config_toml"] == CONFIG and f.attrs["config_sha256"] == SHA
        assert f.attrs["created"].endswith("Z") and f.attrs["created"][4] == "-"
        assert json.loads(f.attrs["planned_step_kinds"]) == ["lock", "rate", "rate"]
        for g, cols in CONTRACT.items():
            assert set(f[g]) == set(cols), g
            for c, unit in cols.items():
                ds = f[g][c]
                assert ds.ndim == 1 and ds.maxshape == (None,) and ds.chunks is not None, f"{g}/{c}"
                assert ds.attrs["units"] == unit, f"{g}/{c}"
                assert ds.attrs["description"]
        assert f["steps/kind"].dtype.kind == "S" and f["steps/status"].dtype.kind == "S"
        assert f["lockin/pll_locked"].dtype == np.uint8
    # hardware files have no /truth
    q = tmp_path / "hw.h5"
    new_writer(q, truth=False, mode="hardware").close()
    assert "truth" not in read_run(q).groups


def test_roundtrip_buffers_until_flush(tmp_path: Path) -> None:
    """The hardware layout (realtime): every flush writes every buffered row."""
    p = tmp_path / "run.h5"
    now = [0.0]
    w = new_writer(p, clock=lambda: now[0], flush_interval_s=1.0, realtime=True)
    w.append("lockin", **lockin_block(0))
    w.append(
        "clsf",
        time=[1 / 7, 2 / 7],
        eta=[1e-4, 2e-4],
        sf_change_estimate=[-1e-4, -2e-4],
        gain_correction=[1.0, 1.0],
        rate_output_mean=[0.3, 0.3],
    )
    w.append("table", time=0.25, rate_command=5.0, rate_measured=5.0001, position=1.25)
    assert w.last_time() == pytest.approx(699 / FS)
    assert w._h5["lockin/time"].shape == (0,)  # buffered: nothing written before the interval
    now[0] = 0.999
    w.maybe_flush()
    w.drain()  # whatever maybe_flush handed to the writer thread is written now: nothing, before the interval
    assert w._h5["lockin/time"].shape == (0,)
    now[0] = 1.0
    w.maybe_flush()  # asynchronous: the writer thread writes and flushes the rows
    w.drain()
    assert w._h5["lockin/time"].shape == (700,)
    w.append("lockin", **lockin_block(1))
    w.append_step(
        index=0, kind="rate", t_start=0.0, t_end=1.0, table_rate=5.0, chamber_setpoint=25.0, status="completed"
    )
    w.drain()
    assert w._h5["lockin/time"].shape == (1400,)  # a step row is a checkpoint: everything before it is written
    assert w._h5["steps/index"].shape == (1,)
    w.set_status("completed")
    w.close()
    run = read_run(p)
    assert not run.writer_open and run.status == "completed"
    expect = {k: np.concatenate([lockin_block(0)[k], lockin_block(1)[k]]) for k in CONTRACT["lockin"]}
    for k, v in expect.items():
        np.testing.assert_array_equal(run.groups["lockin"][k], v)
    np.testing.assert_array_equal(run.groups["clsf"]["eta"], [1e-4, 2e-4])
    np.testing.assert_array_equal(run.groups["table"]["position"], [1.25])
    assert list(run.steps["kind"]) == ["rate"] and list(run.steps["status"]) == ["completed"]
    assert run.attrs["completed_steps"] == 1
    sub = read_run(p, select=["lockin/rate_output"])
    assert set(sub.groups) == {"lockin"} and set(sub.groups["lockin"]) == {"time", "rate_output"}


def test_twins_layout_writes_whole_chunks_and_steps_after_their_data(tmp_path: Path) -> None:
    """The twins' layout: maybe_flush and append_step hand /lockin and /truth over in whole chunks only (no dead
    partial compressed chunk is left behind), a /steps row only once every sample appended before it is in; flush
    and close write the rest."""
    p = tmp_path / "run.h5"
    now = [0.0]
    w = new_writer(p, truth=False, clock=lambda: now[0])
    chunk = w._h5["lockin/time"].chunks[0]
    per_chunk = chunk // 700  # whole 700-row blocks per chunk
    for k in range(per_chunk):
        w.append("lockin", **lockin_block(k))
    w.append_step(
        index=0, kind="rate", t_start=0.0, t_end=1.0, table_rate=5.0, chamber_setpoint=25.0, status="completed"
    )
    w.drain()
    assert w._h5["lockin/time"].shape == (0,)  # 700 * per_chunk < chunk rows: nothing whole to write yet
    assert w._h5["steps/index"].shape == (0,)  # the step's data are not in: neither is its row
    assert w.completed_steps() == {0}  # the campaign knows it is done
    w.append("lockin", **lockin_block(per_chunk))  # crosses the first chunk boundary
    now[0] = 2.0
    w.maybe_flush()
    w.drain()
    assert w._h5["lockin/time"].shape == (chunk,)
    assert w._h5["steps/index"].shape == (1,) and w._h5.attrs["completed_steps"] == 1
    n = 700 * (per_chunk + 1)
    w.flush()  # everything, the partial chunk included
    assert w._h5["lockin/time"].shape == (n,)
    w.close()
    run = read_run(p)
    np.testing.assert_array_equal(run.groups["lockin"]["time"], np.arange(n) / FS)
    np.testing.assert_array_equal(run.groups["lockin"]["x_sense"], 1e-3 * np.sin(np.arange(n) / FS))
    assert list(run.steps["index"]) == [0]


@pytest.mark.parametrize("compression", ["none", "gzip", "lzf"])
def test_compression_choices(tmp_path: Path, compression: str) -> None:
    p = tmp_path / f"{compression}.h5"
    w = new_writer(p, compression=compression)
    w.append("lockin", **lockin_block(0))
    w.close()
    rt = tmp_path / f"{compression}-realtime.h5"
    w = new_writer(rt, compression=compression, realtime=True)
    w.append("lockin", **lockin_block(0))
    w.close()
    expected = None if compression == "none" else compression
    with h5py.File(p, "r") as f, h5py.File(rt, "r") as g:
        # twins: chunks are written whole, so every fast column is compressed
        assert all(f[f"lockin/{c}"].compression == expected for c in f["lockin"])
        assert all(f[f"lockin/{c}"].shuffle == (compression != "none") for c in f["lockin"])
        assert all(f[f"truth/{c}"].compression == expected for c in f["truth"])
        # real time: the noise-dominated columns are stored plain (their partial chunks would leave dead copies)
        for col in ("time", "drive_frequency", "dither"):
            assert g[f"lockin/{col}"].compression == expected
        for col in ("x_sense", "y_sense", "rate_output", "drive_amplitude"):
            assert g[f"lockin/{col}"].compression is None
    for path in (p, rt):
        for col, values in lockin_block(0).items():
            np.testing.assert_array_equal(read_run(path).groups["lockin"][col], values)


def test_bad_appends_and_arguments_are_named(tmp_path: Path) -> None:
    p = tmp_path / "run.h5"
    w = new_writer(p, truth=False)
    with pytest.raises(StorageError, match=r"missing \['dither'\]"):
        cols = lockin_block(0)
        del cols["dither"]
        w.append("lockin", **cols)
    with pytest.raises(StorageError, match="1-D with 700 rows"):
        w.append("lockin", **{**lockin_block(0), "dither": np.zeros(3)})
    with pytest.raises(StorageError, match="unknown group 'foo'"):
        w.append("foo", time=[0.0])
    with pytest.raises(StorageError, match="no /truth group"):
        w.append("truth", time=[0.0], scale_factor=[0.06], temperature=[25.0], rate=[0.0])
    w.append("lockin", **lockin_block(1))
    with pytest.raises(StorageError, match="must not decrease"):
        w.append("lockin", **lockin_block(0))
    with pytest.raises(StorageError, match="step kind"):
        w.append_step(index=1, kind="x" * 49, t_start=0, t_end=1, table_rate=0, chamber_setpoint=25, status="completed")
    with pytest.raises(StorageError, match="status must be one of"):
        w.set_status("done")
    w.close()
    with pytest.raises(StorageError, match="already exists"):
        new_writer(p)
    with pytest.raises(StorageError, match="compression must be one of"):
        new_writer(tmp_path / "c.h5", compression="zstd")
    with pytest.raises(StorageError, match="mode must be one of"):
        new_writer(tmp_path / "m.h5", mode="real")
    with pytest.raises(StorageError, match="closed"):
        w.flush()


def test_reader_refuses_what_is_not_a_run_file(tmp_path: Path) -> None:
    text = tmp_path / "notes.h5"
    text.write_text("hello")
    with pytest.raises(StorageError, match=r"notes\.h5: not an HDF5 file"):
        read_run(text)
    with pytest.raises(StorageError, match="no such run file"):
        read_run(tmp_path / "absent.h5")
    other = tmp_path / "other.h5"
    with h5py.File(other, "w", libver="latest") as f:
        f.attrs["format"] = "something/2"
    with pytest.raises(
        StorageError, match=r"other\.h5: not a qmg-lab run file: its root attribute format is 'something/2'"
    ):
        read_run(other)
    newer = tmp_path / "newer.h5"
    with h5py.File(newer, "w", libver="latest") as f:
        f.attrs["format"] = "qmg-lab/3"
    with pytest.raises(StorageError, match=r"format qmg-lab/3, which this version of qmg-lab does not read"):
        read_run(newer)


def test_context_manager_marks_aborted(tmp_path: Path) -> None:
    p = tmp_path / "run.h5"
    with pytest.raises(RuntimeError), new_writer(p) as w:
        w.append("lockin", **lockin_block(0))
        raise RuntimeError("table interlock")
    run = read_run(p)
    assert run.status == "aborted" and run.attrs["abort_reason"] == "RuntimeError: table interlock"
    assert run.groups["lockin"]["time"].shape == (700,)


def test_reopen_refuses_another_configuration(tmp_path: Path) -> None:
    p = tmp_path / "run.h5"
    new_writer(p).close()
    other = hashlib.sha256(b"other").hexdigest()
    with pytest.raises(StorageError) as err:
        RunWriter.reopen(p, config_sha256=other)
    assert SHA in str(err.value) and other in str(err.value) and str(p) in str(err.value)


def test_reopen_drops_incomplete_steps_and_equalizes_columns(tmp_path: Path) -> None:
    p = tmp_path / "run.h5"
    w = new_writer(p)
    for k in range(4):
        w.append("lockin", **lockin_block(k))
    w.append_step(index=0, kind="lock", t_start=0, t_end=0.5, table_rate=0, chamber_setpoint=25, status="completed")
    w.append_step(index=1, kind="rate", t_start=0.5, t_end=1.0, table_rate=5, chamber_setpoint=25, status="started")
    w.append_step(index=1, kind="rate", t_start=0.5, t_end=1.5, table_rate=5, chamber_setpoint=25, status="aborted")
    w.set_status("aborted", "power cut")
    w.close()
    with h5py.File(p, "r+") as f:  # what a kill between two resizes leaves: one column a block longer
        f["lockin/dither"].resize((3500,))
    w = RunWriter.reopen(p, config_sha256=SHA)
    assert w.completed_steps() == {0}
    assert w.last_time() == pytest.approx(2799 / FS)
    w.append("lockin", **lockin_block(4))
    w.append_step(index=1, kind="rate", t_start=1.6, t_end=3.0, table_rate=5, chamber_setpoint=25, status="completed")
    w.set_status("completed")
    w.close()
    run = read_run(p)
    assert list(run.steps["index"]) == [0, 1] and list(run.steps["status"]) == ["completed", "completed"]
    assert run.attrs["resume_count"] == 1 and run.attrs["abort_reason"] == "" and run.status == "completed"
    assert {len(v) for v in run.groups["lockin"].values()} == {3500}
    np.testing.assert_array_equal(run.groups["lockin"]["time"], np.arange(3500) / FS)


# ---- a writer in another process: live SWMR reads, SIGKILL, resume -------------------------------------------

CHILD = textwrap.dedent("""
    import sys, numpy as np
    sys.path.insert(0, {repo!r})
    from qmg_lab.storage.writer import RunWriter
    path, mode = sys.argv[1], sys.argv[2]
    now = [0.0]
    w = RunWriter.create(path, config_text={config!r}, config_sha256={sha!r}, mode="sim", software_version="t",
                         t0_unix=1.7e9, truth=False, compression="lzf", realtime=True,
                         flush_interval_s=1.0 if mode == "driven" else 0.02,
                         clock=(lambda: now[0]) if mode == "driven" else __import__("time").monotonic)
    def block(k, n=700):
        t = (k * n + np.arange(n)) / 1400.0
        return dict(time=t, x_sense=np.sin(t), y_sense=np.cos(t), rate_output=0.3 + 1e-3 * t,
                    drive_amplitude=0.5 + 0 * t, drive_frequency=2200 + 0 * t, dither=np.sign(np.sin(44 * t)),
                    table_encoder=0 * t, pll_locked=np.ones(n, dtype=np.uint8))
    k = 0
    if mode == "driven":
        print("ready", flush=True)
        for line in sys.stdin:
            cmd = line.split()
            if cmd[0] == "append":
                w.append("lockin", **block(k)); k += 1
            elif cmd[0] == "tick":
                now[0] += 1.0; w.maybe_flush(); w.drain()  # "ok" once the writer thread's flush is done
            elif cmd[0] == "step":
                w.append_step(index=int(cmd[1]), kind="rate", t_start=0, t_end=k * 0.5, table_rate=5,
                              chamber_setpoint=25, status=cmd[2])
                w.drain()
            elif cmd[0] == "close":
                w.set_status("completed"); w.close()
            print("ok", flush=True)
    else:
        while True:  # free running: a flush per 1 s of data, a completed step every 4 s
            w.append("lockin", **block(k)); k += 1
            w.append("chamber", time=[k * 0.5], setpoint=[25.0], temperature=[25.0 + 0.001 * k])
            if k % 2 == 0:
                w.flush()
                print("flushed", k * 0.5 - 1 / 1400.0, flush=True)
            if k % 8 == 0:
                w.append_step(index=k // 8 - 1, kind="rate", t_start=(k - 8) * 0.5, t_end=k * 0.5,
                              table_rate=5, chamber_setpoint=25, status="completed")
            w.maybe_flush()
""")


def _child(tmp_path: Path, mode: str) -> tuple[subprocess.Popen, Path]:
    script = tmp_path / "child.py"
    script.write_text(CHILD.format(repo=str(REPO), config=CONFIG, sha=SHA))
    path = tmp_path / "live.h5"
    proc = subprocess.Popen(
        [sys.executable, str(script), str(path), mode],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
        bufsize=1,
    )
    return proc, path


def _cmd(proc: subprocess.Popen, line: str) -> None:
    proc.stdin.write(line + "\n")
    proc.stdin.flush()
    assert proc.stdout.readline().strip() == "ok"


def test_file_is_readable_while_being_written(tmp_path: Path) -> None:
    proc, path = _child(tmp_path, "driven")
    try:
        assert proc.stdout.readline().strip() == "ready"
        _cmd(proc, "append")
        _cmd(proc, "append")
        run = read_run(path)
        assert run.writer_open and run.status == "running"
        assert run.groups["lockin"]["time"].shape == (0,)  # buffered for less than flush_interval_s
        _cmd(proc, "tick")  # 1 s of (fake) wall time: maybe_flush writes
        run = read_run(path)
        np.testing.assert_array_equal(run.groups["lockin"]["time"], np.arange(1400) / FS)
        np.testing.assert_array_equal(run.groups["lockin"]["x_sense"], np.sin(np.arange(1400) / FS))
        _cmd(proc, "append")
        _cmd(proc, "step 0 completed")
        run = read_run(path)
        assert run.groups["lockin"]["time"].shape == (2100,)
        assert list(run.steps["index"]) == [0]
        _cmd(proc, "close")
        proc.stdin.close()
        assert proc.wait(timeout=30) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    run = read_run(path)
    assert not run.writer_open and run.status == "completed"


@pytest.mark.parametrize("flushes_before_kill", [3, 12])
def test_sigkill_mid_write_leaves_a_readable_file_then_resumes(tmp_path: Path, flushes_before_kill: int) -> None:
    proc, path = _child(tmp_path, "free")
    last_flushed = -1.0
    try:
        for _ in range(flushes_before_kill):
            word, value = proc.stdout.readline().split()
            assert word == "flushed"
            last_flushed = float(value)
        os.kill(proc.pid, signal.SIGKILL)  # the child keeps writing until here: the kill lands anywhere
    finally:
        proc.wait(timeout=30)
    assert proc.returncode == -signal.SIGKILL
    assert writer_flags_set(path)
    run = read_run(path)
    assert run.writer_open and run.status == "running"
    t = run.groups["lockin"]["time"]
    # everything reported flushed is there (loss bounded by the 1 s of data between flushes), rows whole
    assert t[-1] >= last_flushed - 1e-9
    np.testing.assert_allclose(np.diff(t), 1 / FS, rtol=1e-9)
    assert t[0] == 0.0
    np.testing.assert_allclose(run.groups["lockin"]["rate_output"], 0.3 + 1e-3 * t, rtol=1e-12)
    assert {len(v) for v in run.groups["lockin"].values()} == {t.shape[0]}
    n_steps = run.steps["index"].shape[0]
    assert list(run.steps["index"]) == list(range(n_steps))
    assert all(t[-1] >= te - 1e-9 for te in run.steps["t_end"])  # a completed step implies its data is stored
    # resume: continue after the last stored sample
    w = RunWriter.reopen(path, config_sha256=SHA)
    assert w.completed_steps() == set(range(n_steps))
    k0 = int(round((w.last_time() + 1 / FS) * FS))
    t_new = (k0 + np.arange(700)) / FS
    w.append(
        "lockin",
        time=t_new,
        x_sense=0 * t_new,
        y_sense=0 * t_new,
        rate_output=0.3 + 1e-3 * t_new,
        drive_amplitude=0 * t_new,
        drive_frequency=0 * t_new,
        dither=0 * t_new,
        table_encoder=0 * t_new,
        pll_locked=1 + 0 * t_new,
    )
    w.set_status("completed")
    w.close()
    run = read_run(path)
    assert not run.writer_open and run.attrs["resume_count"] == 1 and run.status == "completed"
    np.testing.assert_allclose(np.diff(run.groups["lockin"]["time"]), 1 / FS, rtol=1e-9)


def test_reopen_cuts_groups_that_end_after_the_lockin(tmp_path: Path) -> None:
    """A kill between two groups' writes can leave /truth ending after /lockin; the resumed run continues after
    the last lock-in sample, so reopen cuts the other groups back to that time."""
    p = tmp_path / "run.h5"
    w = new_writer(p)
    w.append("lockin", **lockin_block(0))  # ends at 699/1400 s
    t = np.arange(0, 1400) / FS  # truth one block further
    w.append("truth", time=t, scale_factor=0.06 + 0 * t, temperature=25 + 0 * t, rate=0 * t)
    w.close()
    w = RunWriter.reopen(p, config_sha256=SHA)
    assert w.resume_state().last_time == pytest.approx(699 / FS)
    w.close()
    with h5py.File(p, "r") as f:
        assert f["truth/time"][-1] == pytest.approx(699 / FS)
        assert all(f["truth"][c].shape == (700,) for c in f["truth"])


def test_reopen_drops_a_checkpoint_whose_data_is_not_on_disk(tmp_path: Path) -> None:
    """A completed step row ending after the last stored lock-in sample (the data of the step did not all reach
    the disk) is not a checkpoint: reopen drops it and the step is run again after the resume point."""
    p = tmp_path / "run.h5"
    w = new_writer(p, truth=False)
    for k in range(2):
        w.append("lockin", **lockin_block(k))  # up to 1399/1400 s
    w.append_step(index=0, kind="lock", t_start=0, t_end=0.5, table_rate=0, chamber_setpoint=25, status="completed")
    w.append_step(index=1, kind="rate", t_start=0.5, t_end=1.2, table_rate=5, chamber_setpoint=25, status="completed")
    w.close()
    with h5py.File(p, "r+") as f:  # the lock-in data of step 1 lost: the file ends at 0.75 s
        for c in f["lockin"]:
            f["lockin"][c].resize((1050,))
    w = RunWriter.reopen(p, config_sha256=SHA)
    assert w.completed_steps() == {0}
    assert w.last_time() == pytest.approx(1049 / FS)
    w.close()
    assert read_run(p).attrs["completed_steps"] == 1


def test_reopen_keeps_truth_aligned_with_the_lockin(tmp_path: Path) -> None:
    """A kill between the /lockin and the /truth writes of one flush: the file is cut back to the last instant both
    have, so /truth/time stays equal to /lockin/time row for row."""
    p = tmp_path / "run.h5"
    w = new_writer(p)
    for k in range(3):
        b = lockin_block(k)
        w.append("lockin", **b)
        if k < 2:
            t = b["time"]
            w.append("truth", time=t, scale_factor=0.06 + 0 * t, temperature=25 + 0 * t, rate=0 * t)
    w.close()
    w = RunWriter.reopen(p, config_sha256=SHA)
    assert w.last_time() == pytest.approx(1399 / FS)
    w.close()
    run = read_run(p)
    np.testing.assert_array_equal(run.groups["truth"]["time"], run.groups["lockin"]["time"])


def test_resume_checks_change_nothing_and_name_the_instruments(tmp_path: Path) -> None:
    p = tmp_path / "run.h5"
    w = new_writer(
        p,
        instrument_modes={"lockin": "twin", "generator": "twin", "table": "hardware", "chamber": "twin"},
        mode="hardware",
    )
    w.append("lockin", **lockin_block(0))
    w.close()
    before = p.read_bytes()
    with pytest.raises(StorageError) as err:
        RunWriter.reopen(
            p, config_sha256=SHA, instrument_modes={n: "twin" for n in ("lockin", "generator", "table", "chamber")}
        )
    assert "table was hardware, now twin" in str(err.value) and "(lockin, generator, chamber)" in str(err.value)
    assert p.read_bytes() == before
    w = RunWriter.reopen(p, config_sha256=SHA)
    w.set_status("completed")
    w.close()
    before = p.read_bytes()
    with pytest.raises(StorageError, match="already completed"):
        RunWriter.reopen(p, config_sha256=SHA)
    assert p.read_bytes() == before


def test_chunks_follow_the_write_pattern(tmp_path: Path) -> None:
    """Twins (faster than real time) get big chunks for the fast groups, a real-time writer small ones; the slow
    groups are never compressed."""
    fast, slow = tmp_path / "twins.h5", tmp_path / "bench.h5"
    new_writer(fast).close()
    new_writer(slow, realtime=True, truth=False, mode="hardware").close()
    with h5py.File(fast, "r") as f, h5py.File(slow, "r") as g:
        assert f["lockin/time"].chunks[0] > g["lockin/time"].chunks[0]
        assert f["truth/time"].chunks == f["lockin/time"].chunks
        for grp in ("clsf", "table", "chamber", "steps"):
            assert all(f[grp][c].compression is None for c in f[grp])


def test_a_file_written_before_pll_locked_existed_is_read_and_resumed_without_it(tmp_path: Path) -> None:
    """/lockin/pll_locked is optional (storage.layout.OPTIONAL_COLUMNS): a file without it, as files written before
    the column existed are, reads as before, and a writer that reopens it appends the columns the file has."""
    p = tmp_path / "old.h5"
    w = new_writer(p, truth=False)
    w.append("lockin", **lockin_block(0))
    w.close()
    with h5py.File(p, "r+") as f:  # the older layout: the same file without the column
        del f["lockin/pll_locked"]
    run = read_run(p)
    assert "pll_locked" not in run.groups["lockin"]
    np.testing.assert_array_equal(run.groups["lockin"]["dither"], lockin_block(0)["dither"])
    w = RunWriter.reopen(p, config_sha256=SHA, flush_interval_s=1.0)
    w.append("lockin", **lockin_block(1))
    w.close()
    run = read_run(p)
    assert run.groups["lockin"]["time"].shape == (1400,) and "pll_locked" not in run.groups["lockin"]
