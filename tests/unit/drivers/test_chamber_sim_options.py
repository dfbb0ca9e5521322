"""[sim] options of the chamber twin, through the station as a user sets them (each behaviour its own test).

chamber_status_layout: "ec13" (18 Y/N flags + self-test digit, the default) or "flags16"; chamber_self_test:
the digit; chamber_acknowledges_settings: OK to every setting, or nothing (settings then read back).
"""

from __future__ import annotations

from typing import Any

import pytest

from drivers.chamber import SunEC1xChamber
from qmg_lab.config.schema import parse_config
from qmg_lab.instruments import InstrumentError
from qmg_lab.station import connect_instrument


def chamber_with(sim: str, transport: str = "inprocess") -> tuple[SunEC1xChamber, Any]:
    cfg = parse_config(f'[chamber]\nsim = true\nsim_transport = "{transport}"\ntimeout_s = 0.05\n[sim]\n{sim}\n')
    conn = connect_instrument(cfg, "chamber")
    assert isinstance(conn.instrument, SunEC1xChamber)
    return conn.instrument, conn


@pytest.mark.parametrize(
    ("sim", "status"),
    [("", "YNNNYYYNNNNNNNNNNN0"), ('chamber_status_layout = "flags16"', "YYYNNNNNNNNNNNNN")],
)
def test_status_layout(sim: str, status: str) -> None:
    chamber, conn = chamber_with(sim)
    try:
        assert f"STATUS={status}" in chamber.identify()
    finally:
        conn.close()


@pytest.mark.parametrize("transport", ["inprocess", "socket"])
def test_settings_unacknowledged_are_read_back(transport: str) -> None:
    chamber, conn = chamber_with("chamber_acknowledges_settings = false", transport)
    try:
        chamber.set_setpoint(30.0, 2.0)
        assert chamber.ramp_rate() == 2.0 and chamber.read().ramping
        assert chamber.unacknowledged == 5  # LTL=, UTL= at connect; RATE=, ON, SET=
    finally:
        conn.close()


def test_self_test_ram_error_is_in_the_snapshot() -> None:
    chamber, conn = chamber_with("chamber_self_test = 2")
    try:
        state = chamber.snapshot()["state"]
        assert (state["self_test"], state["self_test_meaning"]) == (2, "EE RAM error (check default settings)")
    finally:
        conn.close()


def test_self_test_rom_error_refuses_the_connection() -> None:
    cfg = parse_config("[chamber]\nsim = true\n[sim]\nchamber_self_test = 3\n[recovery]\nreconnect_attempts = 0\n")
    with pytest.raises(InstrumentError, match=r"self-test failed: .*3 \(ROM error"):
        connect_instrument(cfg, "chamber")
