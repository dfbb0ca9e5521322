"""A resume never discards recorded data, however often it is killed inside the file's repair on reopen.

A campaign killed with SIGKILL leaves a file whose end `RunWriter.reopen` repairs (cuts every group to one
consistent instant). Shrinking an HDF5 dataset writes fill values into its last partial chunk before the new
extent is flushed, so a kill inside the repair used to leave 0.0 rows that the next repair took as data (and a
resume then restarted at t = 0). Here the repair is killed (SIGKILL, in a subprocess) right after its k-th
dataset resize, for every k, and once more inside the next repair; after each kill, the read-only repair plan
of the file (`plan_repair`: what the next resume keeps) must be exactly the plan of the untouched killed file
(same end instant, same rows, same checkpoints), and every kept row must hold the killed file's values (the
same stored numbers, compared exactly: they are copies of bytes, not computed). Finally `--resume` on a file
killed twice inside its repair completes the plan's steps, each once.

A resume whose repair would drop completed steps refuses (exit 2) and changes nothing.
"""

from __future__ import annotations

import hashlib
import os
import shutil
import signal
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import h5py
import numpy as np
import pytest

from qmg_lab.campaign.plan import build_plan
from qmg_lab.config.schema import config_fingerprint, parse_config
from qmg_lab.storage.h5clear import clear_superblock_flags
from qmg_lab.storage.layout import GROUP_UNITS
from qmg_lab.storage.resume import plan_repair, refuse_discarding_repair
from tests.integration.test_resume import wait_for_steps
from tests.support.campaigns import config_text, qmg

pytestmark = pytest.mark.skipif(sys.platform == "win32", reason="SIGKILL of a subprocess")

# One process imports h5py and the writer once, then forks a child per kill (a Python start with h5py per kill
# made this file take minutes): each child reopens the file for a resume with the k-th resize of its repair
# followed by SIGKILL, and tells its parent through a pipe, before its SIGKILL, whether the repair ended before
# the k-th resize. Requests "<k> <path>" on stdin, answers "killed" or "finished" on stdout.
KILL_INSIDE_REPAIR = """
import os, signal, sys
import h5py
from qmg_lab.storage.writer import RunWriter

sha = sys.argv[1]
resize = h5py.Dataset.resize

def repair_killed_at(path, k, report):
    count = 0

    def killing_resize(self, size, axis=None):
        nonlocal count
        resize(self, size) if axis is None else resize(self, size, axis)
        count += 1
        if count == k:  # the fill values are written, the new extent not yet flushed
            os.kill(os.getpid(), signal.SIGKILL)

    h5py.Dataset.resize = killing_resize
    RunWriter.reopen(path, config_sha256=sha)
    os.write(report, b"finished")  # the repair finished before the k-th resize
    os.kill(os.getpid(), signal.SIGKILL)

for line in sys.stdin:
    k, path = line.rstrip("\\n").split(" ", 1)
    r, w = os.pipe()
    pid = os.fork()
    if pid == 0:
        os.close(r)
        try:
            repair_killed_at(path, int(k), w)
        finally:  # an error in the repair: the child must not go on reading requests
            os._exit(1)
    os.close(w)
    _, status = os.waitpid(pid, 0)
    said = os.read(r, 64)
    os.close(r)
    assert os.WIFSIGNALED(status) and os.WTERMSIG(status) == signal.SIGKILL, status
    print("finished" if said else "killed", flush=True)
"""


class RepairKiller:
    """The forking process above, for one killed file's fingerprint."""

    def __init__(self, sha: str) -> None:
        self.proc = subprocess.Popen(
            [sys.executable, "-c", KILL_INSIDE_REPAIR, sha], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True
        )

    def kill_inside_repair(self, path: Path, k: int) -> bool:
        """Reopen `path` for a resume, SIGKILLed after the k-th resize of its repair; False if the repair had
        fewer."""
        assert self.proc.stdin is not None and self.proc.stdout is not None
        self.proc.stdin.write(f"{k} {path}\n")
        self.proc.stdin.flush()
        said = self.proc.stdout.readline().strip()
        assert said in ("killed", "finished"), f"the killing process ended: {self.proc.wait(timeout=60)}"
        return said == "killed"

    def close(self) -> None:
        assert self.proc.stdin is not None
        self.proc.stdin.close()
        assert self.proc.wait(timeout=60) == 0


@pytest.fixture
def repair_killer(killed_run: tuple[Path, Path, str]) -> Iterator[RepairKiller]:
    killer = RepairKiller(killed_run[2])
    yield killer
    killer.close()


@pytest.fixture(scope="module")
def killed_run(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, str]:
    """A short campaign killed with SIGKILL after 5 completed steps: (file, configuration, fingerprint)."""
    tmp = tmp_path_factory.mktemp("killed")
    text = config_text()
    cfg = tmp / "short.toml"
    cfg.write_text(text)
    path = tmp / "killed.h5"
    proc = subprocess.Popen(
        qmg("run", str(cfg), "-o", str(path), "-q"), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True
    )
    wait_for_steps(proc, path, 5)
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    return path, cfg, config_fingerprint(text)


def _plan_and_rows(path: Path) -> tuple[object, dict[str, dict[str, np.ndarray]]]:
    with h5py.File(path, "r", swmr=True, libver="latest") as h5:
        plan = plan_repair(h5)
        rows = {g: {c: h5[g][c][: plan.rows[g]] for c in h5[g]} for g in GROUP_UNITS if g in h5}
        rows["steps"] = {c: h5["steps"][c][: plan.steps_rows] for c in h5["steps"]}
    return plan, rows


def _assert_same(plan, rows, ref_plan, ref_rows, where: str) -> None:
    # what the next resume keeps: the same end instant, rows and checkpoints, and no refusal
    assert (plan.t_end, plan.rows, plan.steps_rows) == (ref_plan.t_end, ref_plan.rows, ref_plan.steps_rows), where
    refuse_discarding_repair(Path(where), plan)
    for g, cols in ref_rows.items():
        for c, ref in cols.items():
            assert np.array_equal(rows[g][c], ref), f"{where}: /{g}/{c}"


def test_a_repair_killed_at_every_resize_keeps_every_recorded_row(
    killed_run, repair_killer: RepairKiller, tmp_path: Path
) -> None:
    path, _, _ = killed_run
    ref_plan, ref_rows = _plan_and_rows(path)
    assert ref_plan.steps_rows >= 5 and not ref_plan.dropped_steps
    assert ref_plan.t_end > 0.0
    k = 1
    while True:
        copy = tmp_path / f"k{k}.h5"
        shutil.copyfile(path, copy)
        killed_inside = repair_killer.kill_inside_repair(copy, k)
        _assert_same(*_plan_and_rows(copy), ref_plan, ref_rows, f"killed after resize {k}")
        # and killed once more inside the next repair, at its first and at a later resize
        for k2 in (1, k):
            again = tmp_path / f"k{k}-{k2}.h5"
            shutil.copyfile(copy, again)
            repair_killer.kill_inside_repair(again, k2)
            _assert_same(*_plan_and_rows(again), ref_plan, ref_rows, f"killed after resize {k}, then {k2}")
        if not killed_inside:
            break
        k += 1
    assert k > 3  # the repair had resizes to be killed at


def test_resume_after_two_kills_inside_the_repair_completes_the_plan(
    killed_run, repair_killer: RepairKiller, tmp_path: Path
) -> None:
    path, cfg, _ = killed_run
    copy = tmp_path / "twice.h5"
    shutil.copyfile(path, copy)
    repair_killer.kill_inside_repair(copy, 2)
    repair_killer.kill_inside_repair(copy, 1)
    ref_plan, _ = _plan_and_rows(path)
    done = subprocess.run(qmg("run", str(cfg), "--resume", str(copy), "-q"), capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    plan = build_plan(parse_config(cfg.read_text()))
    with h5py.File(copy, "r") as h5:
        assert h5.attrs["status"] == "completed"
        assert sorted(h5["steps/index"][:].tolist()) == [s.index for s in plan]
        t = h5["lockin/time"][:]
        assert np.all(np.diff(t) > 0)
        assert t[-1] > ref_plan.t_end  # continued after the kept data, not restarted at 0
        steps_t = h5["steps/t_start"][:]
        # the checkpoints kept from before the kill start where they started (nothing was rerun from 0)
        kept = h5["steps/index"][:] < ref_plan.steps_rows
        assert np.all(steps_t[~kept] >= ref_plan.t_end - 1e-9)


def test_a_resume_that_would_drop_completed_steps_refuses(killed_run, tmp_path: Path) -> None:
    path, cfg, _ = killed_run
    copy = tmp_path / "damaged.h5"
    shutil.copyfile(path, copy)
    # a damaged end: /lockin's time holds 0.0 after its first row (as a repair killed before this fix left
    # it), while the completed steps say their data were recorded (47 s of them, more than a kill loses)
    clear_superblock_flags(copy)
    with h5py.File(copy, "r+") as h5:
        t = h5["lockin/time"]
        t[1:] = 0.0
    before = hashlib.sha256(copy.read_bytes()).hexdigest()
    done = subprocess.run(qmg("run", str(cfg), "--resume", str(copy), "-q"), capture_output=True, text=True)
    assert done.returncode == 2, done.stderr
    assert "would discard" in done.stderr and "Nothing was changed" in done.stderr
    assert "Traceback" not in done.stderr
    assert hashlib.sha256(copy.read_bytes()).hexdigest() == before


@pytest.mark.parametrize("fill", [0.0, np.nan], ids=["fill 0.0 (files before issue 27)", "fill NaN"])
def test_fill_values_a_killed_shrink_leaves_are_never_data(killed_run, tmp_path: Path, fill: float) -> None:
    """The state the issue saw, made exactly: every row a repair cuts holds the fill value while the row counts
    are unchanged (the shrink's fill writes reached the file, its new extents did not). The next plan keeps
    exactly the rows the first one kept, with their values."""
    path, _, _ = killed_run
    ref_plan, ref_rows = _plan_and_rows(path)
    copy = tmp_path / "filled.h5"
    shutil.copyfile(path, copy)
    clear_superblock_flags(copy)
    with h5py.File(copy, "r+") as h5:
        filled = 0
        for g in [g for g in GROUP_UNITS if g in h5]:
            for c in h5[g]:
                ds = h5[g][c]
                if ds.shape[0] > ref_plan.rows[g]:
                    ds[ref_plan.rows[g] :] = fill if ds.dtype.kind == "f" else ds.fillvalue  # pll_locked: 0
                    filled += 1
    assert filled >= 8  # /lockin and /truth at least: the repair cuts there
    _assert_same(*_plan_and_rows(copy), ref_plan, ref_rows, f"fill {fill}")


KILL_BEFORE_SWMR = """
import os, signal, sys
from qmg_lab.storage import writer

path, sha = sys.argv[1], sys.argv[2]
opened = writer._open_for_writing

def open_then_die(p, what):
    h5 = opened(p, what)
    os.kill(os.getpid(), signal.SIGKILL)  # opened for writing, SWMR not yet started

writer._open_for_writing = open_then_die
writer.RunWriter.reopen(path, config_sha256=sha)
"""


def test_a_resume_killed_before_its_swmr_start_is_continued_by_a_plain_resume(killed_run, tmp_path: Path) -> None:
    """The first moments of a resume's write: the file is open for writing, not yet SWMR. A kill there leaves a
    superblock that no reader opens ("not already open for SWMR writing"); the next plain --resume heals it (the
    lock is free: the writer is gone) and completes the plan, each step once."""
    from qmg_lab.storage.h5clear import left_open_without_swmr

    path, cfg, sha = killed_run
    copy = tmp_path / "window.h5"
    shutil.copyfile(path, copy)
    killed = subprocess.run([sys.executable, "-c", KILL_BEFORE_SWMR, str(copy), sha], capture_output=True, text=True)
    assert killed.returncode == -signal.SIGKILL, killed.stderr
    assert left_open_without_swmr(copy)
    done = subprocess.run(qmg("run", str(cfg), "--resume", str(copy), "-q"), capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    with h5py.File(copy, "r") as h5:
        assert h5.attrs["status"] == "completed"
        index = h5["steps/index"][:].tolist()
    assert sorted(index) == [s.index for s in build_plan(parse_config(cfg.read_text()))]
