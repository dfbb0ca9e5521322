"""The EC1x chamber twin at the byte level (docs/instruments.md, chamber section): one reply line per command
ending CR LF, settings answer OK, refusals '?' + reason, STATUS? 16 Y/N flags (0 power, 1 heat, 2 cool,
8 ramping)."""

from __future__ import annotations

import pytest

from sims.chamber_twin import ChamberTwin
from sims.world import World
from tests.support.twin_params import chamber_twin_settings, paper_world_params


@pytest.fixture
def twin() -> ChamberTwin:
    return ChamberTwin(
        World(paper_world_params(initial_temperature_c=22.0)),
        max_ramp_c_per_min=10.0,
        **chamber_twin_settings(status_layout="flags16"),
    )


def test_settings_reach_the_world(twin: ChamberTwin) -> None:
    assert twin.respond(b"RATE=3\r") == b"OK\r\n"
    assert twin.respond(b"SET=40.5\r") == b"OK\r\n"
    c = twin.world.chamber
    assert (c.target_c, c.ramp_c_per_min) == (40.5, 3.0)
    assert twin.respond(b"RATE?\r") == b"3.000\r\n"
    assert twin.respond(b"STATUS?\r") == b"YYYNNNNNYNNNNNNN\r\n"
    twin.world.advance(60, 1.0)  # one minute at 3 deg C/min
    assert twin.respond(b"SET?\r") == b"25.00\r\n"
    assert twin.respond(b"C1?\r") == f"{twin.world.chamber.air_c:.2f}\r\n".encode()


@pytest.mark.parametrize(
    ("line", "reply"),
    [
        (b"FOO\r", b"?UNKNOWN COMMAND\r\n"),
        (b"set=30\r", b"?UNKNOWN COMMAND\r\n"),
        (b"C5?\r", b"?UNKNOWN COMMAND\r\n"),
        (b"\xc3\xa9\r", b"?UNKNOWN COMMAND\r\n"),
        (b"SET=abc\r", b"?BAD VALUE\r\n"),
        (b"SET=\r", b"?BAD VALUE\r\n"),
        (b"SET=1e3\r", b"?BAD VALUE\r\n"),
        (b"SET=200\r", b"?LIMIT\r\n"),
        (b"RATE=0\r", b"?RANGE\r\n"),
        (b"RATE=10.5\r", b"?RANGE\r\n"),
        (b"LTL=-80\r", b"?RANGE\r\n"),
        (b"C1?", b"?FRAMING\r\n"),
    ],
)
def test_refusals(twin: ChamberTwin, line: bytes, reply: bytes) -> None:
    assert twin.respond(line) == reply
    assert twin.world.chamber.target_c == 22.0


def test_ltl_utl_bound_the_setpoint(twin: ChamberTwin) -> None:
    assert twin.respond(b"LTL=-40\r") == b"OK\r\n"
    assert twin.respond(b"UTL=85\r") == b"OK\r\n"
    assert twin.respond(b"LTL?\r") == b"-40.00\r\n" and twin.respond(b"UTL?\r") == b"85.00\r\n"
    assert twin.respond(b"SET=85.01\r") == b"?LIMIT\r\n"
    assert twin.respond(b"SET=-40.5\r") == b"?LIMIT\r\n"
    assert twin.respond(b"SET=85\r") == b"OK\r\n"
    assert twin.respond(b"UTL=-50\r") == b"?RANGE\r\n"  # UTL must stay above LTL


def test_off_goes_to_ambient_and_on_resumes(twin: ChamberTwin) -> None:
    twin.respond(b"RATE=10\r")
    twin.respond(b"SET=30\r")
    twin.world.advance(60, 1.0)
    assert twin.respond(b"OFF\r") == b"OK\r\n"
    assert twin.respond(b"STATUS?\r") == b"NNNNNNNNNNNNNNNN\r\n"
    assert twin.respond(b"SET?\r") == b"30.00\r\n"  # the stored setpoint while off
    assert twin.world.chamber.target_c == 22.0 and twin.world.chamber.heater_on is False
    assert twin.respond(b"SET=28\r") == b"OK\r\n"
    assert twin.world.chamber.target_c == 22.0  # waits for ON
    assert twin.respond(b"ON\r") == b"OK\r\n"
    assert twin.world.chamber.target_c == 28.0 and twin.world.chamber.heater_on is True


def test_fault_hook_can_truncate(twin: ChamberTwin) -> None:
    twin.fault_hook = lambda line, reply: reply[:2]
    assert twin.respond(b"C1?\r") == b"22"
