"""A chamber that starts powered off, the usual morning state, under the whole application:

* a whole campaign on the twins with [sim] chamber_powered_at_start = false (and a controller that answers no
  setting and stays silent for its first two commands, as a GPIB EC13 that is still starting up);
* `qmg-lab chamber setpoint` against a powered-off EC1x twin that the command reaches over a TCP socket as
  hardware (`sim = false`), so that the test holds the twin and looks at it afterwards.

A controller that is off does not ramp, so SET? (the ramping setpoint) stays put until ON: the driver must power
the chamber before it sends and confirms the setpoint (drivers/chamber.py).
"""

from __future__ import annotations

import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import h5py
import numpy as np
import pytest

from sims.chamber_twin import ChamberTwin
from sims.serial_twin import serve_socket
from sims.world import World
from tests.support.campaigns import SHORT_STEPS, SHORT_TOML, config_text, run_inprocess
from tests.support.twin_params import chamber_twin_settings, paper_world_params

ROOT = Path(__file__).resolve().parents[2]
COLD = "chamber_powered_at_start = false\nchamber_acknowledges_settings = false\nchamber_silent_commands = 2\n"


def test_a_whole_campaign_against_a_chamber_that_starts_powered_off(tmp_path: Path) -> None:
    text = config_text(seed=3).replace("[sim]\nseed = 3\n", "[sim]\nseed = 3\n" + COLD)
    assert COLD in text
    outcome = run_inprocess(tmp_path, text)
    assert outcome.error is None, outcome.error
    assert outcome.summary.status == "completed"
    assert outcome.summary.steps_completed == SHORT_STEPS
    assert outcome.world.chamber.heater_on is True  # switched on by the driver, and left on (safe state)
    plan = outcome.cfg.plan
    with h5py.File(outcome.path, "r") as f:
        setpoint = np.asarray(f["chamber/setpoint"])
    # the controller's ramping setpoint went from the start to the end temperature of the plan
    assert setpoint.min() == pytest.approx(plan.chamber_start_c, abs=0.01)
    assert setpoint.max() == pytest.approx(plan.chamber_end_c, abs=0.01)


@pytest.fixture
def cold_chamber() -> Iterator[tuple[ChamberTwin, str]]:
    world = World(paper_world_params(initial_temperature_c=22.0), clock="wall")
    twin = ChamberTwin(
        world, **chamber_twin_settings(powered_at_start=False, acknowledges_settings=False, silent_commands=1)
    )
    url, stop = serve_socket(twin)
    yield twin, url
    stop()


def test_chamber_setpoint_command_against_a_chamber_that_starts_powered_off(
    tmp_path: Path, cold_chamber: tuple[ChamberTwin, str]
) -> None:
    twin, url = cold_chamber
    assert twin.world.chamber.heater_on is False
    text = SHORT_TOML.replace("[chamber]\nsim = true", f'[chamber]\nsim = false\nport = "{url}"\ntimeout_s = 0.5')
    assert f'port = "{url}"' in text
    cfg = tmp_path / "cold.toml"
    cfg.write_text(text, encoding="utf-8")
    proc = subprocess.run(
        [sys.executable, "-m", "qmg_lab", "chamber", "setpoint", str(cfg), "30", "--ramp", "2"],
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stderr
    assert "chamber setpoint 30 degC at 2 degC/min" in proc.stdout
    assert twin.world.chamber.heater_on is True and twin.world.chamber.target_c == 30.0
    assert twin.world.chamber.ramp_c_per_min == 2.0
