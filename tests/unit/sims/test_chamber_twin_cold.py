"""The EC1x twin's [sim] start-up options at the byte level, modelled from the documented protocol and not from
the driver (docs/instruments.md, chamber section):

* chamber_powered_at_start = false: STATUS? char 0 (power) N until ON; SET? is the ramping setpoint, which does not
  move while the power is off (set_query_while_off = "held"), or echoes the last SET= ("target");
* chamber_silent_commands = N: the first N command lines are neither answered nor executed.
"""

from __future__ import annotations

import pytest

from sims.chamber_twin import ChamberTwin
from sims.world import World
from tests.support.twin_params import chamber_twin_settings, paper_world_params

AMBIENT_C = 22.0


def cold_twin(**overrides: object) -> ChamberTwin:
    settings = chamber_twin_settings(status_layout="ec13", powered_at_start=False) | overrides
    return ChamberTwin(World(paper_world_params(initial_temperature_c=AMBIENT_C)), **settings)


def test_a_cold_chamber_reports_power_off_and_does_not_heat() -> None:
    twin = cold_twin()
    status = twin.respond(b"STATUS?\r").decode()
    assert status[0] == "N" and status[4:6] == "NN"  # power, heat and cool outputs off
    assert twin.world.chamber.heater_on is False


def test_set_while_off_does_not_move_the_held_ramping_setpoint() -> None:
    twin = cold_twin(set_query_while_off="held")
    assert twin.respond(b"RATE=10\r") == b"OK\r\n"
    assert twin.respond(b"SET=30\r") == b"OK\r\n"  # taken (stored) ...
    assert twin.respond(b"SET?\r") == f"{AMBIENT_C:.2f}\r\n".encode()  # ... but the ramping setpoint holds
    assert twin.respond(b"STATUS?\r").decode()[8] == "N"  # and nothing ramps
    assert twin.world.chamber.target_c == AMBIENT_C
    assert twin.respond(b"ON\r") == b"OK\r\n"  # power: the stored target is now headed for
    twin.world.advance(30, 1.0)  # 30 s at 10 deg C/min: the ramping setpoint is 5 deg C on
    assert twin.respond(b"SET?\r") == f"{AMBIENT_C + 5.0:.2f}\r\n".encode()
    assert twin.respond(b"STATUS?\r").decode()[0::8][:2] == "YY"  # power on, ramping


def test_set_while_off_echoes_the_target_when_so_configured() -> None:
    twin = cold_twin(set_query_while_off="target")
    twin.respond(b"SET=30\r")
    assert twin.respond(b"SET?\r") == b"30.00\r\n"


@pytest.mark.parametrize("silent", [1, 3])
def test_the_first_commands_are_neither_answered_nor_executed(silent: int) -> None:
    twin = cold_twin(silent_commands=silent)
    for _ in range(silent):
        assert twin.respond(b"ON\r") == b""
    assert twin.world.chamber.heater_on is False  # the ONs went nowhere
    assert twin.respond(b"STATUS?\r").decode()[0] == "N"
