"""A full disk is an instrument-safe abort: the write that fails ends the campaign in its safe state with exit 3
and a message saying how much more space the run needs; no traceback, no crash; once space is free the file
resumes and completes the plan.

The full disk is real and portable on POSIX: the run's subprocess gets a file size limit (RLIMIT_FSIZE, what
`ulimit -f` sets), so the kernel refuses HDF5's write past it exactly as it refuses a write on a full disk (errno
EFBIG instead of ENOSPC; Python ignores the SIGXFSZ that comes with it). The resume runs without the limit: the
space was freed.
"""

from __future__ import annotations

import re
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest

from qmg_lab.campaign.pipeline import resume_space_need
from qmg_lab.campaign.plan import build_plan, checked_plan
from qmg_lab.config.schema import parse_config
from qmg_lab.storage.records import read_events
from tests.support.campaigns import config_text, qmg

pytestmark = pytest.mark.skipif(sys.platform == "win32", reason="RLIMIT_FSIZE is POSIX")

LIMIT_BYTES = 3_000_000  # the short campaign writes about 5 MB: the limit falls in its table steps


def _limited() -> None:
    import resource

    resource.setrlimit(resource.RLIMIT_FSIZE, (LIMIT_BYTES, LIMIT_BYTES))


def test_a_full_disk_aborts_safe_with_exit_3_and_the_run_resumes(tmp_path: Path) -> None:
    import subprocess

    text = config_text()
    cfg = tmp_path / "short.toml"
    cfg.write_text(text)
    path = tmp_path / "run.h5"
    full = subprocess.run(
        qmg("run", str(cfg), "-o", str(path), "-q"), capture_output=True, text=True, preexec_fn=_limited, timeout=600
    )
    said = " ".join(full.stderr.split())
    assert full.returncode == 3, full.stderr  # not 1 (a traceback) nor -11 (a segmentation fault)
    assert "Traceback" not in said
    assert "file size limit" in said and "The run needs about" in said and "MB more" in said
    assert "(safe_state: confirmed)" in said and f"--resume {path}" in said
    # the figure asked is what the resume's own check of this file asks: freeing it is enough
    asked = re.search(r"The run needs about ([0-9.]+) MB more", said)
    assert asked is not None
    plan_checked = checked_plan(parse_config(text))
    assert resume_space_need(parse_config(text), plan_checked, path).needed <= float(asked.group(1)) * 1e6

    done = subprocess.run(qmg("run", str(cfg), "--resume", str(path), "-q"), capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    plan = build_plan(parse_config(text))
    with h5py.File(path, "r") as h5:
        assert h5.attrs["status"] == "completed"
        assert sorted(h5["steps/index"][:].tolist()) == [s.index for s in plan]
        t = h5["lockin/time"][:]
        assert t[0] == 0.0 and np.all(np.diff(t) > 0)  # continued, not restarted at 0
        events = read_events(h5)
    first_abort = next(e for e in events if e["kind"] == "abort")
    assert "file size limit" in first_abort["message"] or "could not be written" in first_abort["message"]


def test_a_full_disk_at_the_last_write_is_no_success(tmp_path: Path) -> None:
    """The issue's false success: the disk fills during the run's last writes (the final flush and close). The
    limit is one byte under the size of the same run's uninterrupted file, so every write but the last ones
    succeeds: the run must exit 3 (never 0 while the file is not closed "completed" with every step), and a
    --resume without the limit completes it with every planned step and no NaN row in any column."""
    import resource
    import subprocess

    text = config_text()
    cfg = tmp_path / "short.toml"
    cfg.write_text(text)
    ref = tmp_path / "ref.h5"
    done = subprocess.run(qmg("run", str(cfg), "-o", str(ref), "-q"), capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    limit = ref.stat().st_size - 1

    def last_write_fails() -> None:
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))

    path = tmp_path / "run.h5"
    full = subprocess.run(
        qmg("run", str(cfg), "-o", str(path), "-q"), capture_output=True, text=True, preexec_fn=last_write_fails
    )
    said = " ".join(full.stderr.split())
    assert full.returncode == 3, said  # not 0: the file does not hold the whole run
    assert "Traceback" not in said and f"--resume {path}" in said
    done = subprocess.run(qmg("run", str(cfg), "--resume", str(path), "-q"), capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    plan = build_plan(parse_config(text))
    with h5py.File(path, "r") as h5:
        assert h5.attrs["status"] == "completed"
        assert sorted(h5["steps/index"][:].tolist()) == [s.index for s in plan]
        for group in ("lockin", "clsf", "table", "chamber", "truth"):
            for column in h5[group]:
                assert not np.isnan(h5[group][column][:]).any(), f"/{group}/{column} has a NaN row"
