"""The EC1x chamber at a VISA address (GPIB0::6::INSTR), chosen by the station from the address's form.

Two VISA paths: real pyvisa resources of the pyvisa-sim model sims/ec13.yaml (an EC13 on GPIB and on RS-232
through VISA: STATUS? 18 flags + self-test digit, no setting answered), and the chamber twin behind its VISA-like
resource (sims/visa_line_twin.py) when [chamber] sim = true. Expected values are those set (SET=, RATE=) and
the fixed replies of the model (C1? 24.50).
"""

from __future__ import annotations

import importlib.resources
from pathlib import Path

import pytest

from drivers.chamber import SunEC1xChamber
from drivers.line_transport import VisaLineTransport
from qmg_lab.config.schema import parse_config
from qmg_lab.instruments import InstrumentError
from qmg_lab.station import connect_instrument, is_visa_address, open_raw_serial

YAML = importlib.resources.files("sims") / "ec13.yaml"


@pytest.mark.parametrize(
    ("address", "visa"),
    [
        ("GPIB0::6::INSTR", True),
        ("ASRL3::INSTR", True),
        ("TCPIP0::192.168.1.5::5025::SOCKET", True),
        ("/dev/ttyUSB1", False),
        ("COM3", False),
        ("socket://127.0.0.1:5000", False),
        ("rfc2217://host:2217", False),
    ],
)
def test_the_address_form_picks_the_transport(address: str, visa: bool) -> None:
    assert is_visa_address(address) is visa


@pytest.mark.parametrize("resource", ["GPIB0::6::INSTR", "ASRL2::INSTR"])
@pytest.mark.parametrize("ack", ["auto", "none"])
def test_ec13_through_pyvisa_identifies_sets_and_reads(resource: str, ack: str) -> None:
    """timeout_s is how long `auto` waits for an OK that this controller never sends (pyvisa-sim waits it)."""
    cfg = parse_config(
        f'[chamber]\nport = "{resource}"\nvisa_backend = "{YAML.as_posix()}@sim"\ntimeout_s = 0.05\n'
        f'setting_ack = "{ack}"\n'
    )
    conn = connect_instrument(cfg, "chamber")  # identify, then LTL=/UTL= confirmed by LTL?/UTL?
    chamber = conn.instrument
    try:
        assert isinstance(chamber, SunEC1xChamber)
        assert chamber.identify().endswith("STATUS=YNNNYYYNNNNNNNNNNN0; self-test 0 (system self test ok))")
        chamber.set_setpoint(30.0, 2.0)
        reading = chamber.read()
        assert (reading.temperature_c, reading.setpoint_c, reading.ramping) == (24.5, 30.0, False)
        assert chamber.ramp_rate() == 2.0
        snapshot = chamber.snapshot()
        assert snapshot["settings"]["framing"]["transport"] == "visa"
        assert snapshot["settings"]["settings_confirmed_by_read_back"] == 5  # LTL=, UTL=, RATE=, ON, SET=
    finally:
        conn.close()


def test_a_setting_the_controller_refuses_silently_is_not_taken(tmp_path: Path) -> None:
    fresh = tmp_path / "ec13.yaml"  # pyvisa-sim keeps a model's state per file: a fresh copy has the defaults
    fresh.write_text(YAML.read_text())
    cfg = parse_config(
        f'[chamber]\nport = "GPIB0::6::INSTR"\nvisa_backend = "{fresh.as_posix()}@sim"\ntimeout_s = 0.05\n'
        'setting_ack = "none"\nmin_c = -100.0\n'
    )
    with pytest.raises(InstrumentError, match=r"'LTL=-100\.00' not taken: LTL\? = -70"):
        connect_instrument(cfg, "chamber")  # the model's range ends at -70 degC: it keeps its LTL


@pytest.mark.parametrize("acknowledges", [True, False])
def test_the_twin_at_a_gpib_address(acknowledges: bool) -> None:
    cfg = parse_config(
        '[chamber]\nsim = true\nport = "GPIB0::6::INSTR"\n'
        f"[sim]\nchamber_acknowledges_settings = {str(acknowledges).lower()}\n"
    )
    conn = connect_instrument(cfg, "chamber")
    chamber = conn.instrument
    try:
        assert isinstance(chamber, SunEC1xChamber)
        assert isinstance(chamber._link, VisaLineTransport)
        assert "STATUS=YNNNYYYNNNNNNNNNNN0" in chamber.identify()  # [sim] chamber_status_layout = "ec13" by default
        chamber.set_setpoint(30.0, 2.0)
        assert chamber.read().ramping
        assert chamber.unacknowledged == (0 if acknowledges else 5)
    finally:
        conn.close()


def test_the_serial_raw_console_names_a_visa_chamber() -> None:
    cfg = parse_config('[chamber]\nport = "GPIB0::6::INSTR"\n')
    with pytest.raises(InstrumentError, match="VISA address 'GPIB0::6::INSTR'"):
        open_raw_serial(cfg, "chamber")
