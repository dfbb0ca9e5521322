"""The EC1x driver against a chamber twin that starts powered off (the usual morning state) and one that stays
silent for its first commands, through the station as a user configures them ([sim] chamber_powered_at_start,
chamber_set_query_while_off, chamber_silent_commands, chamber_acknowledges_settings).

A controller that is off does not ramp, so SET? (the ramping setpoint) cannot confirm a SET= sent before ON: the
driver switches the power on first. First contact asks STATUS? up to FIRST_CONTACT_ATTEMPTS times.
"""

from __future__ import annotations

from typing import Any

import pytest

from drivers.chamber import FIRST_CONTACT_ATTEMPTS, CommandRefused, SunEC1xChamber
from qmg_lab.config.schema import parse_config
from qmg_lab.instruments import InstrumentError
from qmg_lab.station import connect_instrument
from tests.support.protocol_serial import ProtocolPort

AMBIENT_C = 25.0  # the default [sim] initial_temperature_c


def cold_chamber(sim: str = "", recovery: str = "") -> tuple[SunEC1xChamber, Any]:
    cfg = parse_config(
        "[chamber]\nsim = true\ntimeout_s = 0.05\n[sim]\nchamber_powered_at_start = false\n" + sim + recovery
    )
    conn = connect_instrument(cfg, "chamber")
    assert isinstance(conn.instrument, SunEC1xChamber)
    return conn.instrument, conn


@pytest.mark.parametrize("acknowledges", ["true", "false"])
@pytest.mark.parametrize("set_query", ["held", "target"])
def test_setpoint_on_a_chamber_that_starts_powered_off(acknowledges: str, set_query: str) -> None:
    chamber, conn = cold_chamber(
        f'chamber_acknowledges_settings = {acknowledges}\nchamber_set_query_while_off = "{set_query}"\n'
    )
    try:
        assert chamber.power_on() is False
        chamber.set_setpoint(30.0, 2.0)
        assert chamber.power_on() is True
        reading = chamber.read()
        assert reading.ramping is True  # on its way from ambient to 30 deg C
        assert AMBIENT_C - 0.01 <= reading.setpoint_c < 30.0
    finally:
        conn.close()


def test_a_set_read_back_with_the_power_off_names_the_power() -> None:
    chamber, conn = cold_chamber("chamber_acknowledges_settings = false\n")
    try:
        with pytest.raises(InstrumentError, match=r"'SET=30.00' not taken: .*power is off"):
            chamber._command("SET=30.00")  # the order a driver must not use: SET= before ON
    finally:
        conn.close()


def test_safe_state_of_a_cold_chamber_powers_it_and_heads_for_the_safe_setpoint() -> None:
    chamber, conn = cold_chamber("chamber_acknowledges_settings = false\n")
    try:
        chamber.safe_state()
        assert chamber.power_on() is True and chamber._target_c == chamber.safe_setpoint_c
    finally:
        conn.close()


@pytest.mark.parametrize("silent", [1, FIRST_CONTACT_ATTEMPTS - 1])
def test_first_contact_waits_for_a_chamber_that_is_slow_to_answer(silent: int) -> None:
    chamber, conn = cold_chamber(f"chamber_silent_commands = {silent}\n", "[recovery]\nreconnect_attempts = 0\n")
    try:
        assert "STATUS=NNNN" in chamber.identify()
    finally:
        conn.close()


def test_first_contact_gives_up_after_its_attempts() -> None:
    with pytest.raises(InstrumentError, match=f"no STATUS\\? reply in EC1x form after {FIRST_CONTACT_ATTEMPTS} "):
        cold_chamber(f"chamber_silent_commands = {FIRST_CONTACT_ATTEMPTS}\n", "[recovery]\nreconnect_attempts = 0\n")


def test_first_contact_does_not_retry_a_refusal() -> None:
    port = ProtocolPort([(b"STATUS?\r\n", b"?UNKNOWN COMMAND\r\n")])
    chamber = SunEC1xChamber(port, min_c=-40.0, max_c=85.0, max_ramp_c_per_min=5.0, safe_setpoint_c=25.0)
    with pytest.raises(CommandRefused, match=r"'STATUS\?' refused"):
        chamber.identify()
    port.assert_complete()  # one STATUS?, not FIRST_CONTACT_ATTEMPTS
