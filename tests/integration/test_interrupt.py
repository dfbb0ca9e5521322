"""Ctrl-C: the campaign stops between blocks, brings the station to its safe state, marks the file "aborted" and
the CLI exits 130; a second Ctrl-C during a write is deferred until the write is complete.

SIGINT is sent to this process (os.kill) from inside the campaign (progress callback, a writer's append), so
the tests are deterministic without sleeping; one subprocess test checks the real exit code.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from typing import ClassVar

import h5py
import numpy as np
import pytest

from qmg_lab.campaign.runner import CampaignInterrupted
from qmg_lab.storage.writer import RunWriter
from tests.support.campaigns import completed_steps, config_text, long_config, qmg, run_inprocess


def _ctrl_c() -> None:
    os.kill(os.getpid(), signal.SIGINT)


def test_ctrl_c_stops_at_the_next_block_in_the_safe_state(tmp_path):
    sent = []

    def progress(p) -> None:
        if p.step.index == 4 and not sent:
            sent.append(p.run_time_s)
            _ctrl_c()

    out = run_inprocess(tmp_path, config_text(), progress=progress)
    assert isinstance(out.error, CampaignInterrupted)
    run = out.run()
    assert run.status == "aborted" and "Ctrl-C" in run.attrs["abort_reason"]
    assert sorted(run.steps["index"].tolist()) == [0, 1, 2, 3]  # step 4 was running, not completed
    assert run.groups["lockin"]["time"][-1] == pytest.approx(sent[0])  # no block after the one that saw it
    assert out.world_is_safe()


class _SecondCtrlCInsideAWrite(RunWriter):
    """A real RunWriter that receives both Ctrl-Cs in the middle of appending a block's table row, after the
    lock-in rows of that block were appended and before its chamber and truth rows are."""

    armed_at_s = 40.0
    fired = False
    finished_writes_after: ClassVar[list[str]] = []

    def _maybe_fire(self, group, time_s):
        if group == "table" and not self.fired and time_s >= self.armed_at_s:
            type(self).fired = True
            _ctrl_c()
            _ctrl_c()  # the second one raises KeyboardInterrupt unless deferred

    def append(self, group, **columns):
        self._maybe_fire(group, float(np.atleast_1d(columns["time"])[0]))
        super().append(group, **columns)
        if self.fired:
            self.finished_writes_after.append(group)

    def append_row(self, group, **values):  # the recorder appends the table and chamber readings as rows
        self._maybe_fire(group, float(values["time"]))
        super().append_row(group, **values)
        if self.fired:
            self.finished_writes_after.append(group)


def test_second_ctrl_c_cannot_cut_a_write_half_way(tmp_path):
    out = run_inprocess(tmp_path, config_text(), writer_cls=_SecondCtrlCInsideAWrite)
    assert _SecondCtrlCInsideAWrite.fired
    assert isinstance(out.error, CampaignInterrupted)
    # the block being written was finished: its table, chamber and truth rows follow the interrupted append
    assert _SecondCtrlCInsideAWrite.finished_writes_after[:3] == ["table", "chamber", "truth"]
    run = out.run()
    t_end = run.groups["lockin"]["time"][-1]
    assert run.groups["table"]["time"][-1] == t_end == run.groups["chamber"]["time"][-1]
    with h5py.File(out.path, "r") as h5:
        for group in ("lockin", "table", "chamber", "truth"):
            lengths = {h5[group][c].shape[0] for c in h5[group]}
            assert len(lengths) == 1, group  # every column of every group complete
    assert run.status == "aborted"
    assert out.world_is_safe()


def test_cli_exits_130_on_sigint(tmp_path):
    # a plan of a simulated day (4300 pairs of 10 s steps): however slowly this process is scheduled beside a
    # loaded machine, the run cannot end before the SIGINT below reaches it (no race on wall-clock time)
    cfg = tmp_path / "endless.toml"
    cfg.write_text(long_config().replace("chamber_end_hold_s = 300.0", "chamber_end_hold_s = 86400.0"))
    path = tmp_path / "run.h5"
    proc = subprocess.Popen(
        qmg("run", str(cfg), "-o", str(path), "-q"), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True
    )
    while completed_steps(path) < 5:
        try:
            proc.wait(timeout=0.02)
        except subprocess.TimeoutExpired:
            continue
        pytest.fail(f"run ended early: {proc.returncode}")
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130, err
    assert "safe state" in err and "Traceback" not in err
    with h5py.File(path, "r") as h5:
        assert h5.attrs["status"] == "aborted"
        assert "Ctrl-C" in h5.attrs["abort_reason"]


def test_main_maps_a_stray_keyboard_interrupt_to_130():
    # SIGINT back to Python's default handler first: a suite started in the background (nohup, '&' without job
    # control) hands its children SIGINT ignored, and the kill below would then do nothing
    done = subprocess.run(
        [
            sys.executable,
            "-c",
            "import signal, os\n"
            "signal.signal(signal.SIGINT, signal.default_int_handler)\n"
            "from qmg_lab.cli import main as cli\n"
            "cli.app = lambda: os.kill(os.getpid(), signal.SIGINT)\n"
            "cli.main()",
        ],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert done.returncode == 130
