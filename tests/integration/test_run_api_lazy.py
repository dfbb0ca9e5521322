"""The lazy data API (qmg_lab/data/run.py): `to_xarray()` reads nothing until asked, `chunks=` gives dask arrays,
`.load()` the same values as the file; the datetime coordinate, `long_name`/`units`, the valid-rows rule on fill
rows, `Run` as a context manager and its short repr.

Expected values come from the file itself, read with plain h5py as an outside reader would, and from the
synthetic sweep's equations (tests/support/synthetic_runs.py). The datetime coordinate is t0_unix + time rounded
to the nanosecond: compared with the same sum in integer nanoseconds, within 1 us (float64 at t0 ~ 1.8e9 s
resolves 2.4e-7 s).
"""

from __future__ import annotations

import shutil
from pathlib import Path

import h5py
import numpy as np
import pytest

import qmg_lab
from qmg_lab.storage import runfile
from qmg_lab.storage.layout import DESCRIPTIONS, GROUP_UNITS
from qmg_lab.storage.reader import read_run, valid_rows
from tests.support import synthetic_runs as syn


@pytest.fixture(scope="module")
def sweep(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("lazy") / "sweep.h5"
    syn.write_sweep(path)
    return path


def test_to_xarray_reads_no_column_until_asked_and_loads_the_files_values(sweep: Path) -> None:
    with h5py.File(sweep, "r") as h5:
        raw = {g: {c: h5[g][c][:] for c in GROUP_UNITS[g]} for g in ("lockin", "clsf", "truth")}
    with qmg_lab.open_run(sweep) as run:
        tree = run.to_xarray()
        for g in ("lockin", "clsf", "truth"):
            for c in GROUP_UNITS[g]:
                var = tree[g][c].variable
                if not (c == "time" and g == "clsf"):  # clsf's time is an index: read to build it
                    assert not isinstance(var._data, np.ndarray), f"{g}/{c} was read"
        loaded = tree.load()
        for g, cols in raw.items():
            for c, values in cols.items():
                np.testing.assert_array_equal(loaded[g][c].to_numpy(), values, err_msg=f"{g}/{c}")
        # a slice reads only that slice, equal to the file's rows
        np.testing.assert_array_equal(
            run.to_xarray()["lockin"]["rate_output"][100:200].to_numpy(), raw["lockin"]["rate_output"][100:200]
        )


def test_chunks_give_dask_arrays_whose_mean_agrees_with_the_eager_one(sweep: Path) -> None:
    import dask.array as da

    with qmg_lab.open_run(sweep) as run:
        eager = run.to_xarray(["clsf"]).load()["clsf"]["sf_change_estimate"].to_numpy()
        for chunks in ({}, {"time": 500}, "auto", 700):
            node = run.to_xarray(["clsf", "lockin"], chunks=chunks)
            assert isinstance(node["clsf"]["sf_change_estimate"].data, da.Array)
            mean = float(node["clsf"]["sf_change_estimate"].mean().compute())
            # two summation orders of n values: each sum is within (n - 1) eps sum|s| of the exact one
            n = eager.shape[0]
            bound = 2 * (n - 1) * np.finfo(float).eps * np.abs(eager).max()
            assert abs(mean - eager.mean()) <= bound
        with h5py.File(sweep, "r") as h5:
            on_disk = h5["lockin/time"].chunks[0]
        assert run.to_xarray(["lockin"], chunks={})["lockin"]["x_sense"].data.chunks[0][0] == on_disk


def test_the_lazy_arrays_pickle_for_dask_workers(sweep: Path) -> None:
    """A dask graph of the tree travels to another process as bytes: the column and its file handle pickle (the
    handle as its path) and read the same values after the trip."""
    import pickle

    with qmg_lab.open_run(sweep) as run:
        arr = run.to_xarray(["lockin"], chunks={})["lockin"]["rate_output"].data
        again = pickle.loads(pickle.dumps(arr))
        np.testing.assert_array_equal(again.compute(), arr.compute())


def test_every_variable_has_long_name_units_and_a_datetime_coordinate(sweep: Path) -> None:
    with qmg_lab.open_run(sweep) as run:
        tree = run.to_xarray()
        for g in ("lockin", "clsf", "table", "chamber", "truth"):
            node = tree[g]
            for name in [*node.data_vars, "time"]:
                assert node[name].attrs["long_name"] == DESCRIPTIONS[f"{g}/{name}"]
                assert node[name].attrs["units"] == GROUP_UNITS[g][name]
            t = node["time"].to_numpy()
            expected = np.round((run.t0_unix + t) * 1e9).astype(np.int64)
            got = node["datetime"].to_numpy().astype(np.int64)
            assert np.abs(got - expected).max() <= 1000
            assert node["datetime"].attrs["long_name"]
        for g in ("steps", "events"):
            for name in tree[g].data_vars:
                assert "long_name" in tree[g][name].attrs and "units" in tree[g][name].attrs
        assert "time" in tree["clsf"].indexes and "time" not in tree["lockin"].indexes


def test_fill_rows_with_nan_time_are_not_data(sweep: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Rows a killed writer left allocated hold NaN time: neither to_xarray nor to_pandas returns them; the
    block-by-block scan (blocks of 1000 rows here) keeps exactly the rows storage.reader keeps."""
    copy = tmp_path / "filled.h5"
    shutil.copyfile(sweep, copy)
    with h5py.File(copy, "r+") as h5:
        rows = {}
        for g in ("clsf", "lockin"):
            rows[g] = h5[g]["time"].shape[0]
            for c in h5[g]:
                ds = h5[g][c]
                ds.resize((rows[g] + 37,))
                ds[rows[g] :] = np.nan if ds.dtype.kind == "f" else 0  # pll_locked (uint8) has the fill value 0
    monkeypatch.setattr(runfile, "SCAN_ROWS", 1000)
    with qmg_lab.open_run(copy) as run:
        tree = run.to_xarray(["clsf", "lockin"])
        assert tree["clsf"].sizes["time"] == rows["clsf"] and tree["lockin"].sizes["time"] == rows["lockin"]
        assert np.isfinite(tree["lockin"]["time"].to_numpy()).all()
        assert run.to_pandas("clsf").shape[0] == rows["clsf"]
    kept = read_run(copy, select=("clsf", "lockin"))
    assert kept.groups["lockin"]["time"].shape[0] == rows["lockin"]
    with h5py.File(copy, "r") as h5:
        assert valid_rows(h5["lockin/time"][:]) == rows["lockin"]


def test_run_is_a_context_manager_with_a_short_repr(sweep: Path) -> None:
    with qmg_lab.open_run(sweep) as run:
        tree = run.to_xarray(["clsf"])
        assert run._file.is_open()  # inside `with`, the reads share one handle
        text = repr(run)
    assert not run._file.is_open()  # leaving `with` closed it
    lines = text.splitlines()
    assert len(lines) == 4 and len(text) < 400
    assert lines[0].startswith("<qmg_lab.Run sweep.h5") and "completed" in lines[0]
    assert "groups: lockin, clsf, table, chamber, truth" in text
    # a read after `with` opens the file for itself
    assert tree["clsf"]["eta"].to_numpy().shape[0] == tree["clsf"].sizes["time"]
