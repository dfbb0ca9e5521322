"""The data API (`qmg_lab.open_run`, qmg_lab/data/run.py) and `qmg-lab runs` on a finished, a running and a
resumed run file.

Finished: the synthetic temperature sweep of tests/support/synthetic_runs.py, whose chamber temperature and
CLSF estimate follow stated equations. Running: a RunWriter open in this process, appending while the API
reads. Resumed: a twin campaign interrupted at 30 s of run time and resumed (as `qmg-lab run --resume` does).

Tolerances: chamber and gyro temperatures are piecewise-linear in t with their kinks on sample times, so the
linear interpolation reproduces temperature(t) up to rounding: a few ulp of 35 degC (~1e-14); 1e-9 degC is far
above that and far below any real misalignment (the ramp moves 10/320 degC per s, 3e-5 degC in 1 ms).
The 60 s moving mean from one cumulative sum against a direct mean per row: the cumulative sum of n <= 2300
values of |s| <= 1e-2 carries at most n eps max|sum| ~ 2300 x 1.1e-16 x 25 ~ 6e-12 absolute, divided by the
window's >= 1 rows; 1e-10 bounds it.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import qmg_lab
from tests.support import synthetic_runs as syn
from tests.support.live_runs import append_block, interrupted_then_resumed, live_writer


def test_import_qmg_lab_stays_light() -> None:
    """`import qmg_lab` loads none of h5py, pandas, xarray until open_run is used."""
    code = "import sys, qmg_lab; print(sorted(m for m in ('h5py', 'pandas', 'xarray') if m in sys.modules))"
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert done.stdout.strip() == "[]", done.stderr


def test_a_finished_file(tmp_path: Path) -> None:
    path = tmp_path / "sweep.h5"
    syn.write_sweep(path)
    run = qmg_lab.open_run(path)
    assert run.status == "completed"
    assert run.config["campaign"]["kind"] == "temperature_sweep"
    assert run.config["plan"]["dwell_s"] == syn.DWELL
    assert list(run.steps["kind"]) == ["lock", "dither"] + ["rate"] * (2 * syn.N_PAIRS)
    assert run.steps["status"].eq("completed").all()
    assert run.steps.attrs["units"]["t_start"] == "s"

    tree = run.to_xarray()
    sf = tree["clsf"]["sf_change_estimate"]
    assert sf.attrs["units"] == "1" and "SF/SF0" in sf.attrs["description"]
    assert tree["clsf"]["time"].attrs["units"] == "s"
    assert tree["chamber"]["temperature"].attrs["units"] == "degC"
    assert tree.attrs["format"] == "qmg-lab/2"
    chamber = run.to_pandas("chamber")
    np.testing.assert_allclose(chamber["temperature"], syn.temperature(chamber.index.to_numpy()), rtol=0, atol=1e-12)
    assert tree["chamber"].sizes["time"] == chamber.shape[0]

    df = run.clsf_with_temperatures()
    t = df.index.to_numpy()
    inside = (t >= chamber.index[0]) & (t <= chamber.index[-1])
    assert inside.sum() > 2000 and not inside.all()  # the first CLSF periods come before the first chamber reading
    np.testing.assert_allclose(df["chamber_temperature"][inside], syn.temperature(t[inside]), rtol=0, atol=1e-9)
    assert df["chamber_temperature"][~inside].isna().all()
    # /truth is sampled at 1400 Sa/s up to 324 - 1/1400 s: the CLSF row at 324 s lies after it, and gets NaN
    in_truth = t <= syn.T_PRE + 2 * syn.N_PAIRS * syn.DWELL - 0.5 / syn.FS
    np.testing.assert_allclose(df["gyro_temperature"][in_truth], syn.temperature(t[in_truth]), rtol=0, atol=1e-9)
    assert df["gyro_temperature"][~in_truth].isna().all() and (~in_truth).sum() == 1
    s = df["sf_change_estimate"].to_numpy()
    direct = np.array([s[(t >= ti - 60.0) & (t <= ti)].mean() for ti in t])  # the closed window [t - 60, t]
    np.testing.assert_allclose(df["sf_change_estimate_60s"], direct, rtol=0, atol=1e-10)


def test_a_running_file(tmp_path: Path) -> None:
    """A writer open in this process (SWMR): the API sees what was flushed, and more after the next flush."""
    path = tmp_path / "running.h5"
    w = live_writer(path, "live", ["lock", "soak", "return"])
    try:
        for k in range(2):
            append_block(w, k, ("lock", "soak")[k])
            run = qmg_lab.open_run(path)
            assert run.status == "running" and run.name == "live"
            assert run.steps.shape[0] == k + 1
            tree = run.to_xarray()
            assert tree["clsf"].sizes["time"] == 70 * (k + 1)
            df = run.clsf_with_temperatures()
            t = df.index.to_numpy()
            inside = t <= 10.0 * k + 9.5
            np.testing.assert_allclose(df["chamber_temperature"][inside], 25 + 0.1 * t[inside], rtol=0, atol=1e-12)
            assert df["gyro_temperature"].isna().all()  # no /truth: the bench has no gyro thermometer
    finally:
        w.set_status("completed")
        w.close()
    assert qmg_lab.open_run(path).status == "completed"


def test_a_resumed_twin_campaign(tmp_path: Path) -> None:
    def aborted(path: Path) -> None:
        run = qmg_lab.open_run(path)
        assert run.status == "aborted" and run.events["kind"].iloc[-1] in ("interrupted", "safe_state")
        assert run.to_xarray(["clsf"])["clsf"]["time"].to_numpy()[-1] >= 30.0

    second = interrupted_then_resumed(tmp_path, aborted)
    run = qmg_lab.open_run(second.path)
    assert run.status == "completed" and run.attrs["resume_count"] == 1
    assert [s["occasion"] for s in run.snapshots].count("resume") == 4
    assert {s["instrument"] for s in run.snapshots} == {"lockin", "generator", "table", "chamber"}
    assert all(isinstance(s["document"], dict) for s in run.snapshots)
    assert "interrupted" in set(run.events["kind"])
    tree = run.to_xarray(["clsf", "chamber", "truth"])
    t = tree["clsf"]["time"].to_numpy()
    assert np.all(np.diff(t) > 0)  # one continuous, increasing run-time axis across the resume
    assert t[0] < 30.0 < t[-1]
    df = run.clsf_with_temperatures()
    assert df["gyro_temperature"].notna().mean() > 0.9  # the twins record the gyro's temperature in /truth


def test_runs_lists_a_folder(tmp_path: Path) -> None:
    syn.write_sweep(tmp_path / "a_sweep.h5")
    (tmp_path / "notes.h5").write_bytes(b"not hdf5")
    done = subprocess.run(
        [sys.executable, "-m", "qmg_lab", "runs", str(tmp_path), "--json"], capture_output=True, text=True
    )
    assert done.returncode == 0, done.stderr
    rows = {Path(r["file"]).name: r for r in json.loads(done.stdout)["runs"]}
    assert rows["notes.h5"]["status"].startswith("unreadable")
    r = rows["a_sweep.h5"]
    assert r["status"] == "completed" and r["kind"] == "temperature_sweep"
    assert r["steps_completed"] == 2 + 2 * syn.N_PAIRS
    assert r["duration_s"] == pytest.approx(syn.T_PRE + 2 * syn.N_PAIRS * syn.DWELL, abs=1e-9)
    # the estimate follows (ALPHA + BETA) (T(t) - 25) + 20 ppm white noise, T linear in t over the last 60 s,
    # sampled every 1/7 s from 264 + 1/7 to 324 s: its mean is at the middle of the first and last samples
    end = syn.T_PRE + 2 * syn.N_PAIRS * syn.DWELL
    want = (syn.ALPHA + syn.BETA) * (syn.temperature(end - 30.0 + 0.5 / syn.F_D) - 25.0) * 1e6
    assert r["sf_change_60s_ppm"] == pytest.approx(want, abs=5 * 20 / np.sqrt(60 * syn.F_D) + 1e-6)
    table = subprocess.run(
        [sys.executable, "-m", "qmg_lab", "runs", str(tmp_path)],
        capture_output=True,
        text=True,
        env={**os.environ, "COLUMNS": "80"},
    )
    assert table.returncode == 0 and "a_sweep.h5" in table.stdout
    missing = subprocess.run(
        [sys.executable, "-m", "qmg_lab", "runs", str(tmp_path / "nope")], capture_output=True, text=True
    )
    assert missing.returncode == 2 and "no such" in missing.stderr and "Traceback" not in missing.stderr
