"""`qmg-lab run CONFIG --sim --realtime`: the lock-in twin is paced to the wall clock (qmg_lab.station
RealTimePacing), so a campaign lasts as long on the wall clock as in campaign time, with hardware-length polls
([lockin] poll_interval_s). Behaviour only, not speed: the run's wall time follows its campaign time within
REALTIME_TOLERANCE_S, where the same run unpaced takes a fraction of it."""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

import h5py
import pytest

from qmg_lab.campaign.pipeline import run_campaign
from qmg_lab.config.schema import parse_config
from qmg_lab.station import RealTimePacing, build_station

ROOT = Path(__file__).resolve().parents[2]

# 10 s of campaign: lock 1 s, dither 3 s, +5 and -5 deg/s for 2 s each, return 2.0167 s
TEN_SECONDS = """
[campaign]
name = "rehearsal"
[loops]
lock_settle_s = 1.0
[clsf]
reference_periods = 7
[plan]
chamber_start_c = 25.0
chamber_end_c = 25.0
chamber_soak_s = 0.0
chamber_end_hold_s = 4.0
dwell_s = 2.0
settle_s = 0.5
[lockin]
sim = true
[generator]
sim = true
[table]
sim = true
[chamber]
sim = true
"""
CAMPAIGN_S = 1.0 + 3.0 + 2.0 + 2.0 + (2.0 + 5.0 / 300.0)
#: the paced wall clock may trail the campaign's by the start-up before the first poll (the station's settings,
#: the lock) and the close after the last one, plus however late a busy host fell behind (the pacing's
#: max_late_s: a late poll is never made to wait); it may not run ahead of it by more than one poll
REALTIME_TOLERANCE_S = 2.0


def test_a_paced_campaign_lasts_its_campaign_time_on_the_wall_clock(tmp_path: Path) -> None:
    cfg = parse_config(TEN_SECONDS)
    pacing = RealTimePacing()
    station = build_station(cfg, pacing=pacing)
    try:
        assert station.poll_interval_s == cfg.lockin.poll_interval_s  # hardware-length blocks, not the twins'
        wall0 = time.monotonic()
        end = run_campaign(cfg, TEN_SECONDS, tmp_path / "paced.h5", station=station)
        wall_s = time.monotonic() - wall0
    finally:
        station.close()
    assert end.ok and end.summary is not None, end.message
    summary = end.summary
    assert summary.status == "completed"
    assert summary.simulated_s == pytest.approx(CAMPAIGN_S, abs=cfg.lockin.poll_interval_s)
    assert summary.simulated_s - cfg.lockin.poll_interval_s <= wall_s
    assert wall_s <= summary.simulated_s + pacing.max_late_s + REALTIME_TOLERANCE_S
    assert pacing.polls >= summary.simulated_s / cfg.lockin.poll_interval_s - 1
    assert pacing.waited_s > 0.0  # the twin was ahead of the wall clock and waited for it, as a data server does
    assert 0.0 < pacing.twin_cpu_s < wall_s


def test_unpaced_the_same_campaign_runs_ahead_of_the_wall_clock(tmp_path: Path) -> None:
    cfg = parse_config(TEN_SECONDS)
    station = build_station(cfg)
    try:
        assert station.poll_interval_s == cfg.lockin.sim_poll_interval_s
        wall0 = time.monotonic()
        end = run_campaign(cfg, TEN_SECONDS, tmp_path / "virtual.h5", station=station)
        wall_s = time.monotonic() - wall0
    finally:
        station.close()
    assert end.ok and end.summary is not None, end.message
    summary = end.summary
    assert summary.status == "completed"
    assert wall_s < summary.simulated_s - REALTIME_TOLERANCE_S  # the flag, not the machine, makes the pace


def test_the_run_command_takes_realtime_and_refuses_it_for_a_hardware_lockin(tmp_path: Path) -> None:
    cfg = tmp_path / "ten.toml"
    cfg.write_text(TEN_SECONDS, encoding="utf-8")
    out = tmp_path / "cli.h5"
    t0 = time.monotonic()
    proc = subprocess.run(
        [sys.executable, "-m", "qmg_lab", "run", str(cfg), "--sim", "--realtime", "-q", "-o", str(out)],
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stderr
    assert time.monotonic() - t0 >= CAMPAIGN_S - 1.0  # the command as a whole cannot be faster than real time
    with h5py.File(out, "r") as f:
        assert f.attrs["status"] == "completed"
    hardware = tmp_path / "hw.toml"
    hardware.write_text(TEN_SECONDS.replace("[lockin]\nsim = true", "[lockin]\nsim = false"), encoding="utf-8")
    proc = subprocess.run(
        [sys.executable, "-m", "qmg_lab", "run", str(hardware), "--realtime", "-q", "-o", str(tmp_path / "h.h5")],
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=300,
    )
    assert proc.returncode == 2 and "--realtime" in proc.stderr
    assert not (tmp_path / "h.h5").exists()
