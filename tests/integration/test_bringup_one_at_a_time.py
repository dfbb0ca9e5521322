"""Bring-up one instrument at a time (issue 12): a bench where only the rate table is real.

The "real" 1291BR is the table twin on its own World, served on socket://127.0.0.1 (a separate TCP endpoint,
exactly as a serial-over-Ethernet server would be); qmg-lab runs in a subprocess as a user runs it. Expected
values come from the documented protocol: JOG r sets the commanded rate r, STO commands rest (0), and the
twin's STA/PVE answers are what the driver reads back.
"""

from __future__ import annotations

import json
import socket
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import h5py
import numpy as np
import pytest

from sims.serial_twin import serve_socket
from sims.table_twin import RateTableTwin
from sims.world import World
from tests.support.campaigns import SHORT_TOML
from tests.support.twin_params import paper_world_params, table_twin_settings

ROOT = Path(__file__).resolve().parents[2]


def qmg(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "qmg_lab", *args], capture_output=True, text=True, cwd=ROOT, timeout=300
    )


class AnsweringTable(RateTableTwin):
    """The 1291BR twin, keeping every rate it answered to PVE (what a driver can only have read from it)."""

    def __init__(self, world: World) -> None:
        super().__init__(world, **table_twin_settings())
        self.rates_answered: list[float] = []

    def _pve(self, arg: str) -> str:
        reply = super()._pve(arg)
        self.rates_answered.append(float(reply))
        return reply


class RealTable:
    """The bench's table: a 1291BR twin with its own wall-clock world, on a loopback TCP port."""

    def __init__(self) -> None:
        self.world = World(paper_world_params(), clock="wall")
        self.twin = AnsweringTable(self.world)
        self.url, self.stop = serve_socket(self.twin, "127.0.0.1")

    def commanded_dps(self) -> float:
        with self.world.lock:
            return float(self.world.table.rate_command_dps)


@pytest.fixture
def real_table() -> Iterator[RealTable]:
    t = RealTable()
    yield t
    t.stop()


def closed_port() -> int:
    """A loopback TCP port nobody listens on (connection refused)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def only_table_real(tmp: Path, url: str, others: str = "") -> Path:
    text = SHORT_TOML.replace("[table]\nsim = true", f'[table]\nsim = false\nport = "{url}"\ntimeout_s = 2.0')
    assert f'port = "{url}"' in text
    path = tmp / "table-real.toml"
    path.write_text(text + others, encoding="utf-8")
    return path


def test_table_rate_and_stop_reach_the_real_table_over_socket(tmp_path: Path, real_table: RealTable) -> None:
    cfg = only_table_real(tmp_path, real_table.url)
    proc = qmg("table", "rate", str(cfg), "5", "--accel", "300")
    assert proc.returncode == 0, proc.stderr
    assert "table commanded to 5 deg/s at 300 deg/s^2" in proc.stdout
    assert real_table.commanded_dps() == 5.0  # JOG5.000000 arrived
    proc = qmg("table", "stop", str(cfg))
    assert proc.returncode == 0, proc.stderr
    assert real_table.commanded_dps() == 0.0  # STO arrived
    assert real_table.twin.commands_seen >= 6  # ACL, JOG, STA, PVE, PPO, STA, then STO, STA, ...


def test_table_bring_up_connects_nothing_else(tmp_path: Path, real_table: RealTable) -> None:
    """The other three are 'hardware' at addresses where nothing answers: table rate must not touch them."""
    dead = closed_port()
    text = (
        f'[campaign]\nname = "table only"\n[lockin]\nsim = false\nhost = "127.0.0.1"\nport = {dead}\n'
        f'[generator]\nsim = false\nresource = "ASRL/dev/nonexistent-qmg::INSTR"\nvisa_backend = "@py"\n'
        f'[chamber]\nsim = false\nport = "socket://127.0.0.1:{dead}"\n'
        f'[table]\nsim = false\nport = "{real_table.url}"\n'
    )
    cfg = tmp_path / "bench.toml"
    cfg.write_text(text, encoding="utf-8")
    proc = qmg("table", "rate", str(cfg), "--", "-2.5")
    assert proc.returncode == 0, proc.stderr
    assert real_table.commanded_dps() == -2.5
    proc = qmg("table", "stop", str(cfg))
    assert proc.returncode == 0, proc.stderr
    assert real_table.commanded_dps() == 0.0
    # the chamber's bring-up, on the other hand, names its own unreachable port and nothing else
    proc = qmg("chamber", "setpoint", str(cfg), "30")
    assert proc.returncode == 3
    assert "could not connect the chamber" in proc.stderr and f"127.0.0.1:{dead}" in proc.stderr
    assert "Traceback" not in proc.stderr


# a 10 s plan (lock 1 s, dither 3 s, +5 and -5 deg/s for 2 s each, return 2.0167 s): with a real instrument on
# the bench the lock-in twin runs in real time, so that the dwell times are the real table's too
TEN_SECONDS = """
[campaign]
name = "mixed"
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
[chamber]
sim = true
"""
TEN_SECONDS_DURATION_S = 1.0 + 3.0 + 2.0 + 2.0 + (2.0 + 5.0 / 300.0)


def test_a_whole_run_with_only_the_table_real(tmp_path: Path, real_table: RealTable) -> None:
    cfg = tmp_path / "mixed.toml"
    cfg.write_text(TEN_SECONDS + f'[table]\nsim = false\nport = "{real_table.url}"\n', encoding="utf-8")
    out = tmp_path / "mixed.h5"
    proc = qmg("run", str(cfg), "-o", str(out), "-q")
    assert proc.returncode == 0, proc.stderr
    with h5py.File(out, "r") as f:
        assert f.attrs["status"] == "completed"
        assert f.attrs["mode"] == "hardware"  # a real instrument took part
        assert json.loads(f.attrs["instrument_modes"]) == {
            "lockin": "twin",
            "generator": "twin",
            "table": "hardware",
            "chamber": "twin",
        }
        measured = f["table/rate_measured"][:]
        command = f["table/rate_command"][:]
        assert f["steps/status"].shape[0] == 5
        assert float(f["lockin/time"][-1]) == pytest.approx(TEN_SECONDS_DURATION_S, abs=1.0)
        # real time: the real table's own clock ran as long as the campaign
        wall_s = real_table.world.now()
    # the rates logged are the socket table's answers to PVE, each one of them (on a wall clock, which instant of
    # a ramp or dwell a reading catches depends on the machine's load; that the answer is logged does not); they
    # never exceed the commanded 5 deg/s by more than the 60 ppm scale error and the 100 ppm once-per-revolution
    # ripple of the default table
    answered = set(real_table.twin.rates_answered)
    assert measured.size > 0 and all(float(r) in answered for r in measured)
    assert np.max(np.abs(measured)) <= 5.0 * (1 + 60e-6 + 100e-6) + 1e-6
    assert set(np.unique(command)) == {-5.0, 0.0, 5.0}
    assert real_table.commanded_dps() == 0.0  # the safe state reached the real table
    assert wall_s >= TEN_SECONDS_DURATION_S


def test_instruments_names_the_unreachable_one_and_reports_all_four(tmp_path: Path) -> None:
    dead = closed_port()
    text = SHORT_TOML.replace("[chamber]\nsim = true", f'[chamber]\nsim = false\nport = "socket://127.0.0.1:{dead}"')
    cfg = tmp_path / "chamber-dead.toml"
    cfg.write_text(text, encoding="utf-8")
    proc = qmg("instruments", str(cfg), "--json")
    assert proc.returncode == 3, proc.stderr
    report = json.loads(proc.stdout)
    assert set(report) == {"lockin", "generator", "table", "chamber"}
    assert [n for n, e in report.items() if not e["ok"]] == ["chamber"]
    assert report["chamber"]["simulated"] is False and report["chamber"]["identity"] is None
    assert f"socket://127.0.0.1:{dead}" in report["chamber"]["error"]
    for name in ("lockin", "generator", "table"):
        assert report[name]["identity"] and report[name]["simulated"] is True
    assert "chamber" in proc.stderr and "could not connect" in proc.stderr
    assert "Traceback" not in proc.stderr
