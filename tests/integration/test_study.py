"""Design studies: the study storage level, the study file's grid and validation, and a two-worker Dask study that
is killed (kill -9 of the driver) and resumed."""

from __future__ import annotations

import csv
import json
import math
import os
import signal
import subprocess
import sys
import tomllib
from collections import Counter
from pathlib import Path
from typing import Any

import h5py
import pytest
import tomlkit

from qmg_lab.study.spec import StudyError, load_study

ROOT = Path(__file__).resolve().parents[2]
INSTRUMENTS = ("lockin", "generator", "table", "chamber")


def short_sweep(**plan: float) -> dict[str, Any]:
    """The paper campaign shortened to about two simulated minutes: a 1 degC ramp, four +-5 deg/s pairs."""
    doc = tomllib.loads((ROOT / "configs" / "paper_campaign.toml").read_text())
    doc["plan"].update(
        chamber_end_c=26.0,
        chamber_ramp_c_per_min=1.0,
        chamber_soak_s=20.0,
        chamber_end_hold_s=20.0,
        dwell_s=15.0,
        settle_s=3.0,
    )
    doc["plan"].update(plan)
    doc["loops"]["lock_settle_s"] = 2.0
    for name in INSTRUMENTS:
        doc[name]["sim"] = True
    return doc


def qmg(*args: str, cwd: Path = ROOT) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "qmg_lab", *args], cwd=cwd, capture_output=True, text=True, timeout=600, check=False
    )


def _same(a: Any, b: Any, path: str = "") -> list[str]:
    """Differences between two analyze --json documents (floats to 1e-9 relative: summation order only)."""
    if isinstance(a, dict):
        return [d for k in a if k not in ("file", "notes") for d in _same(a[k], b.get(k), f"{path}/{k}")]
    if isinstance(a, list):
        if len(a) != len(b):
            return [f"{path}: {len(a)} vs {len(b)} items"]
        return [d for i, (x, y) in enumerate(zip(a, b, strict=True)) for d in _same(x, y, f"{path}[{i}]")]
    if isinstance(a, float) and isinstance(b, float):
        return [] if math.isclose(a, b, rel_tol=1e-9, abs_tol=1e-12) else [f"{path}: {a!r} vs {b!r}"]
    return [] if a == b else [f"{path}: {a!r} vs {b!r}"]


# ---- the study storage level ------------------------------------------------------------------------------------


def test_study_level_file_gives_the_same_analysis_as_a_full_file_of_the_same_seed(tmp_path: Path) -> None:
    results = {}
    for level in ("full", "study"):
        doc = short_sweep()
        doc["storage"] = {"level": level}
        doc["table"]["encoder_on_dio"] = False  # a study-level file has no encoder stream: both on the host's steps
        cfg = tmp_path / f"{level}.toml"
        cfg.write_text(tomlkit.dumps(doc))
        run = qmg("run", str(cfg), "-o", str(tmp_path / f"{level}.h5"), "-q")
        assert run.returncode == 0, run.stderr
        ana = qmg("analyze", str(tmp_path / f"{level}.h5"), "--json")
        assert ana.returncode == 0, ana.stderr
        results[level] = json.loads(ana.stdout)
    full, study = results["full"], results["study"]
    assert full["n_step_pairs"] >= 3 and math.isfinite(full["clsf_accuracy_rms_ppm"])
    assert full["truth_check_rms_ppm"] is not None and full["settling_time_s"] is not None
    assert _same(full, study) == []
    with h5py.File(tmp_path / "full.h5") as f_full, h5py.File(tmp_path / "study.h5") as f_study:
        assert f_study.attrs["storage_level"] == "study" and "truth" not in f_study and "truth" in f_full
        n_full, n_study = f_full["lockin/time"].shape[0], f_study["lockin/time"].shape[0]
        # the study file keeps the settling step's samples only: its 15 s dwell and 2.5 s before it
        rate = 1.0 / (f_full["lockin/time"][1] - f_full["lockin/time"][0])
        assert n_study <= (15.0 + 2.5 + 2.5) * rate < n_full / 5
        # one /edges row per dither period from the dither step's start, one /windows row per completed step
        kinds = [k.decode() for k in f_study["steps/kind"][:]]
        t_dither = f_study["steps/t_start"][kinds.index("dither")]
        assert abs(f_study["edges/time"].shape[0] - 7.0 * (f_full["lockin/time"][-1] - t_dither)) <= 2
        assert f_study["windows/index"].shape[0] == f_study["steps/index"].shape[0]
    again = qmg("run", str(tmp_path / "study.toml"), "--resume", str(tmp_path / "study.h5"))
    assert again.returncode == 2 and "cannot be resumed" in again.stderr


def test_the_bandwidth_campaign_needs_the_full_level(tmp_path: Path) -> None:
    doc = short_sweep()
    doc["campaign"]["kind"] = "bandwidth"
    doc["storage"] = {"level": "study"}
    cfg = tmp_path / "bw.toml"
    cfg.write_text(tomlkit.dumps(doc))
    r = qmg("check", str(cfg))
    assert r.returncode == 2 and "storage.level" in r.stderr and "bandwidth" in r.stderr


# ---- the study file ---------------------------------------------------------------------------------------------


def _study(tmp_path: Path, axes: str, extra: str = "", seeds: str = "[1, 2]", **plan: float) -> Path:
    (tmp_path / "base.toml").write_text(tomlkit.dumps(short_sweep(**plan)))
    path = tmp_path / "s.toml"
    path.write_text(f'[study]\nname = "t"\nbase = "base.toml"\nseeds = {seeds}\n{extra}\n[axes]\n{axes}\n')
    return path


def test_the_grid_is_the_product_of_the_axes_times_the_seeds(tmp_path: Path) -> None:
    study = load_study(
        _study(tmp_path, '"dither.virtual_rate_dps" = [2.5, 5.0, 10.0]\n"clsf.hold_s" = [0.5, 1.0]', seeds="[4, 9]")
    )
    assert len(study.points) == 3 * 2 * 2
    assert len({p.id for p in study.points}) == 12
    p = study.points[-1]
    cfg = tomllib.loads(p.config_text)
    assert p.axes == {"dither.virtual_rate_dps": 10.0, "clsf.hold_s": 1.0} and p.seed == 9
    assert cfg["dither"]["virtual_rate_dps"] == 10.0 and cfg["clsf"]["hold_s"] == 1.0 and cfg["sim"]["seed"] == 9
    assert cfg["storage"]["level"] == "study" and all(cfg[n]["sim"] for n in INSTRUMENTS)
    assert cfg["plan"]["dwell_s"] == 15.0  # the base's own values stay


@pytest.mark.parametrize(
    ("axes", "point", "field"),
    [
        ('"dither.virtual_rate_dps" = [5.0, -1.0]', "p0001-s1", "dither.virtual_rate_dps"),
        ('"dither.virtual_rat" = [5.0]', "p0000-s1", "dither.virtual_rat: unknown key"),
        # 1400 Sa/s / 7 Hz = 200 samples per period: the edges lock to the sample grid
        ('"lockin.demod_rate_hz" = [1800.0, 1400.0]', "p0001-s1", "lockin.demod_rate_hz = 1400"),
        ('"plan.table_rate_dps" = [5.0, 500.0]', "p0001-s1", "table"),
    ],
)
def test_every_point_is_validated_before_anything_runs(tmp_path: Path, axes: str, point: str, field: str) -> None:
    path = _study(tmp_path, axes, extra='[set]\n"sim.hf2_rate_set" = "ticks"', seeds="[1]")
    with pytest.raises(StudyError) as err:
        load_study(path)
    assert f"point {point}" in str(err.value) and field in str(err.value)
    r = qmg("study", str(path), "-o", str(tmp_path / "out"))
    assert r.returncode == 2 and point in r.stderr and "Traceback" not in r.stderr
    assert not (tmp_path / "out").exists()  # nothing ran, nothing was created


# ---- a two-worker study, killed and resumed --------------------------------------------------------------------

KILL_AXES = '"dither.virtual_rate_dps" = [2.5, 10.0]\n"sim.faults.interlock_trip_at_s" = [100000.0, 40.0]'


def _results(out: Path) -> list[dict[str, str]]:
    with (out / "results.csv").open() as f:
        rows = list(csv.DictReader(f))
    for r in rows:
        r.pop("wall_s")
    return rows


def _runlog(out: Path) -> list[dict[str, Any]]:
    return [json.loads(line) for line in (out / "runlog.jsonl").read_text().splitlines()]


def test_a_killed_and_resumed_two_worker_study_ends_as_an_uninterrupted_one(tmp_path: Path) -> None:
    study = _study(tmp_path, KILL_AXES, chamber_end_c=25.5)  # about 70 simulated seconds per campaign
    # uninterrupted
    whole = tmp_path / "whole"
    r = qmg("study", str(study), "-o", str(whole), "--workers", "2", "-q")
    assert r.returncode == 0, r.stderr
    rows = _results(whole)
    assert len(rows) == 8
    # the interlock trips at 40 s in half the grid cells: those points are recorded failed, the others ran on
    tripped = [row for row in rows if row["sim.faults.interlock_trip_at_s"] == "40.0"]
    assert {row["status"] for row in tripped} == {"failed"} and all("interlock" in row["error"] for row in tripped)
    assert {row["status"] for row in rows if row not in tripped} == {"ok"}
    assert all(float(row["clsf_accuracy_rms_ppm"]) > 0 for row in rows if row["status"] == "ok")
    assert Counter(e["event"] for e in _runlog(whole)) == {"start": 8, "done": 8}

    # killed with SIGKILL once two points are complete, then resumed
    killed = tmp_path / "killed"
    proc = subprocess.Popen(
        [sys.executable, "-m", "qmg_lab", "study", str(study), "-o", str(killed), "--workers", "2", "-q"],
        cwd=ROOT,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    points = killed / "points"
    try:
        while len(list(points.glob("*.json"))) < 2:
            try:
                proc.wait(timeout=0.05)  # waiting on the real process: its campaigns take real time
            except subprocess.TimeoutExpired:
                continue
            pytest.fail(f"the study ended (exit {proc.returncode}) before it could be killed")
    finally:
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait()
    done_at_kill = {p.stem for p in points.glob("*.json")}
    assert 2 <= len(done_at_kill) < 8, "the kill must land mid-study"
    assert not (killed / "results.csv").exists()
    log_at_kill = _runlog(killed)

    r = qmg("study", str(study), "-o", str(killed), "--resume", "--workers", "2", "-q")
    assert r.returncode == 0, r.stderr
    assert _results(killed) == rows
    log = _runlog(killed)
    # no point ran twice: at most one "done" per point (a kill between a record's rename and its "done" line leaves
    # a complete point without one), and no point complete at the kill was started again
    done = Counter(e["point"] for e in log if e["event"] == "done")
    assert max(done.values()) == 1 and {r["point"] for r in rows} - set(done) <= done_at_kill
    assert not [e for e in log[len(log_at_kill) :] if e["point"] in done_at_kill]
    # a point killed mid-campaign (started, never done) runs again from the start after the resume
    interrupted = {e["point"] for e in log_at_kill if e["event"] == "start"} - done_at_kill
    resumed_starts = Counter(e["point"] for e in log[len(log_at_kill) :] if e["event"] == "start")
    assert set(resumed_starts) == {r["point"] for r in rows} - done_at_kill and max(resumed_starts.values()) == 1
    assert interrupted <= set(resumed_starts)

    # a third run finds nothing to do; without --resume the directory is refused
    r = qmg("study", str(study), "-o", str(killed), "--resume", "--workers", "2", "-q")
    assert r.returncode == 0 and "0 points run" in r.stderr and _runlog(killed) == log
    r = qmg("study", str(study), "-o", str(killed), "-q")
    assert r.returncode == 2 and "--resume" in r.stderr

    # the study directory's outputs: a figure per varying metric and axis, and the summary table
    figures = {p.name for p in (killed / "figures").glob("*.png")}
    assert "clsf_accuracy_rms_ppm__vs__dither.virtual_rate_dps.png" in figures
    a = qmg("analyze", str(killed))
    assert a.returncode == 0 and "8 points" in a.stdout and "4 ok" in a.stdout and "4 failed" in a.stdout
