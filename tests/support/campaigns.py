"""Shared helpers for the reliability tests (faults, resume, interrupt): a short campaign run in-process on the
twins, with the test holding the World so it can look at the physical state afterwards.

The short plan (qmg_lab.campaign.plan.build_plan of SHORT_TOML): lock 2 s, dither 21/7 + 2 = 5 s, soak 20 s, 4 pairs of
10 s table steps at +-5 deg/s, return 2.0167 s (5/300 + 2): 12 steps, 109.0167 s. The twins' blocks are pinned at
2 s (lockin.sim_poll_interval_s = 2.0, the default, pinned here), so block edges fall at 0, 2, 4, 6, 7, 9, ..., 27, 29,
... (odd seconds from 7 s on): the fault tests' arithmetic needs several blocks per 10 s step.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from qmg_lab.campaign.pipeline import RunHooks, run_campaign
from qmg_lab.campaign.runner import RunSummary
from qmg_lab.config.schema import Config, parse_config
from qmg_lab.instruments import Station
from qmg_lab.station import build_station, make_world
from qmg_lab.storage.runfile import open_run_file
from qmg_lab.storage.writer import RunData, RunWriter, StorageError, read_run
from sims.world import World

SAFE_SETPOINT_C = 20.0
SHORT_TOML = f"""
[campaign]
name = "short"
[loops]
lock_settle_s = 2.0
[clsf]
reference_periods = 21
[plan]
chamber_start_c = 25.0
chamber_end_c = 26.0
chamber_ramp_c_per_min = 2.0
chamber_soak_s = 20.0
chamber_end_hold_s = 50.0
dwell_s = 10.0
settle_s = 2.0
[chamber]
sim = true
safe_setpoint_c = {SAFE_SETPOINT_C}
[lockin]
sim = true
sim_poll_interval_s = 2.0
[generator]
sim = true
[table]
sim = true
"""
SHORT_STEPS = 12
SHORT_DURATION_S = 2.0 + 5.0 + 20.0 + 8 * 10.0 + (5.0 / 300.0 + 2.0)


def config_text(faults: str = "", extra: str = "", seed: int = 3) -> str:
    """SHORT_TOML with every instrument a twin, `extra` TOML sections and a [sim.faults] section."""
    text = SHORT_TOML + extra
    return text + f"\n[sim]\nseed = {seed}\n[sim.faults]\n{faults}\n"


@dataclass
class Outcome:
    cfg: Config
    world: World
    station: Station
    path: Path
    summary: RunSummary
    error: BaseException | None
    lockin_state: dict[str, Any]

    def run(self) -> RunData:
        return read_run(self.path)

    def world_is_safe(self) -> bool:
        """Safe state on the twins: table commanded to 0, DS345 muted, chamber at its safe setpoint, HF2
        signal outputs off."""
        return (
            self.world.table.rate_command_dps == 0.0
            and self.world.dither.amplitude_vpp == 0.0
            and self.world.chamber.target_c == SAFE_SETPOINT_C
            and self.lockin_state["sigouts_on"] == {"drive": 0, "forcer": 0}
        )


def run_inprocess(
    tmp_path: Path,
    text: str,
    *,
    name: str = "run.h5",
    resume: bool = False,
    progress: Any = None,
    writer_cls: type[RunWriter] = RunWriter,
) -> Outcome:
    """Run the campaign of `text` on the twins in this process, through the pipeline `qmg-lab run` takes
    (qmg_lab.campaign.pipeline.run_campaign), on a station built here on a World the test keeps; never raises (the
    error is returned). writer_cls: a RunWriter subclass the opened file is given (tests inject faults in writes)."""
    cfg = parse_config(text)
    world = make_world(cfg)
    station = build_station(cfg, world)
    path = tmp_path / name

    def file_open(writer: RunWriter) -> None:
        if writer_cls is not RunWriter:
            writer.__class__ = writer_cls

    try:
        end = run_campaign(
            cfg,
            text,
            path,
            resume=resume,
            station=station,
            t0_unix=0.0,
            software_version="test",
            hooks=RunHooks(progress=progress, file_open=file_open),
        )
        lockin_state = station.lockin.state()
    finally:
        station.close()
    assert end.summary is not None, end.message  # the checks before the run passed
    return Outcome(cfg, world, station, path, end.summary, end.error, lockin_state)


def long_config() -> str:
    """The short plan with 17 pairs of 10 s table steps (ceil((30 s ramp + 300 s hold) / 20 s)) and lock,
    dither, soak, return: 38 steps."""
    text = config_text()
    return text.replace("chamber_end_hold_s = 50.0", "chamber_end_hold_s = 300.0")


def qmg(*args: str) -> list[str]:
    return [sys.executable, "-m", "qmg_lab", *args]


def completed_steps(path: Path) -> int:
    """The run file's completed_steps attribute, read as a SWMR reader; -1 while it cannot be read yet. The file is
    a live campaign's, polled every few ms: opened without open_run_file's child walk (probe=False), whose start
    would let a short campaign finish between two polls."""
    try:
        with open_run_file(path, probe=False) as run:
            return int(run.attrs["completed_steps"])
    except (StorageError, OSError, RuntimeError, KeyError):  # HDF5's own errors while the writer lays it out
        return -1
