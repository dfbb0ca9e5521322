"""The read handles of the data API (qmg_lab/data/run.py `_RunFile`) and of the watch page's follower
(qmg_lab/watch/follow.py) never outlive a read unless the user holds them (`with open_run(...)`).

HDF5 refuses to open for writing a file this process still has open for reading ("file is already open for
read-only"), so a resume (`RunWriter.reopen`, what `qmg-lab run --resume` calls) in the same process is the
witness: it succeeds only if no read handle is left. The garbage collector is off while the readers' objects
are alive, as it is between two of its passes: an xarray DataTree is a reference cycle (its nodes point at their
parent), freed only by a pass, so a handle reachable from a tree stays open until then.

The file: an aborted bench run of two 10 s blocks (tests/support/live_runs.py) with lock-in samples at 100 Sa/s
up to 20 s, so that a resume keeps every row (its end instant is the last lock-in time).
"""

from __future__ import annotations

import gc
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

import qmg_lab
from qmg_lab.storage.writer import RunWriter
from qmg_lab.watch.follow import RunFollower
from tests.support.live_runs import append_block, live_writer


@pytest.fixture
def aborted(tmp_path: Path) -> Path:
    path = tmp_path / "aborted.h5"
    w = live_writer(path, "handles", ["lock", "soak", "return"])
    for k in range(2):
        t = 10.0 * k + np.arange(1, 1001) / 100.0
        z = 0 * t
        w.append(
            "lockin",
            time=t,
            x_sense=z,
            y_sense=z,
            rate_output=z,
            drive_amplitude=z,
            drive_frequency=z,
            dither=z,
            table_encoder=z,
            pll_locked=z + 1,
        )
        append_block(w, k, ("lock", "soak")[k])
    w.set_status("aborted", "interrupted")
    w.close()
    return path


@pytest.fixture
def no_gc() -> Iterator[None]:
    gc.disable()
    try:
        yield
    finally:
        gc.enable()


def resume_and_abort(path: Path) -> None:
    """Reopen the file for writing as a resume does (its repair included), then mark it aborted and close it."""
    sha = str(qmg_lab.open_run(path).attrs["config_sha256"])
    w = RunWriter.reopen(path, config_sha256=sha)
    w.set_status("aborted", "interrupted")
    w.close()


def test_a_tree_and_a_run_left_alive_hold_no_file(aborted: Path, no_gc: None) -> None:
    tree = qmg_lab.open_run(aborted).to_xarray()  # the Run itself is dropped at once
    before = float(tree["clsf"]["sf_change_estimate"].mean())
    run = qmg_lab.open_run(aborted)
    chamber = run.to_pandas("chamber")
    resume_and_abort(aborted)  # refused ("already open for read-only") if a read left a handle open
    # after the writer's close the tree and the Run read the file again: the rows of append_block, 70 per block
    t = tree["clsf"]["time"].to_numpy()
    assert t.shape[0] == 140
    assert float(tree["clsf"]["sf_change_estimate"].mean()) == pytest.approx(before, rel=1e-12)
    np.testing.assert_allclose(before, np.mean(1e-6 * (np.arange(140) / 7.0 + 1 / 7.0)), rtol=1e-12)
    np.testing.assert_array_equal(run.to_pandas("chamber").to_numpy(), chamber.to_numpy())


def test_with_holds_one_handle_until_it_is_left(aborted: Path, no_gc: None) -> None:
    with qmg_lab.open_run(aborted) as run:
        tree = run.to_xarray(["clsf"], chunks=35)
        assert run._file.is_open()  # to_xarray opened the handle every read inside `with` shares
        first = float(tree["clsf"]["eta"].mean().compute())
    assert not run._file.is_open()
    resume_and_abort(aborted)
    assert float(tree["clsf"]["eta"].mean().compute()) == first == 0.0  # dask reads after `with`, each for itself


def test_tree_close_releases_the_handle_of_its_with_block(aborted: Path) -> None:
    run = qmg_lab.open_run(aborted).__enter__()
    tree = run.to_xarray(["clsf"])
    assert run._file.is_open()
    tree.close()
    assert not run._file.is_open()


def test_the_follower_holds_no_file_between_polls(aborted: Path, no_gc: None) -> None:
    follower = RunFollower(aborted)
    up = follower.poll()
    assert up.ready and up.final and up.groups["clsf"]["time"].shape[0] == 140
    assert follower.attrs() is not None
    resume_and_abort(aborted)  # the resume cut nothing: both blocks ended on a chamber reading
    again = follower.poll()
    assert again.ready and not again.reset and not again.groups
