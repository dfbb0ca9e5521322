"""DS345 over RS-232: replies ending CR, LF or CR LF are all read on a serial (ASRL) resource; GPIB reads to LF.

Three wires: real pyvisa resources of the strict pyvisa-sim model (sims/ds345.yaml, whose RS-232 replies end CR
as public serial DS345 code reads them; the LF and CR LF variants are the same file with that one terminator
changed), the message-level twin behind its VISA-like resource, and the byte-exact fake resource
(tests/support/protocol_visa.py). Expected values are the commands sent (docs/instruments.md, DS345 section).
"""

from __future__ import annotations

import importlib.resources
from collections.abc import Iterator
from pathlib import Path

import pytest
import pyvisa

from drivers.ds345 import DS345
from qmg_lab.config.schema import parse_config
from qmg_lab.instruments import InstrumentError
from qmg_lab.station import connect_instrument
from sims.ds345_twin import DS345Twin
from tests.support.protocol_visa import expected_protocol
from tests.support.twin_params import paper_world

YAML = importlib.resources.files("sims") / "ds345.yaml"
ASRL_REPLY_LINE = '        r: "\\r"\n'  # the RS-232 reply terminator line of sims/ds345.yaml
FRAMINGS = {"CR": "\\r", "LF": "\\n", "CRLF": "\\r\\n"}
SQUARE_7HZ_0V6 = ("square", 7.0, 0.6, 0.0)  # set_square(7, 0.6): function, Hz, Vpp, V


def square_state(generator: DS345) -> tuple[object, ...]:
    st = generator.state()
    return st["function"], st["frequency_hz"], st["amplitude_vpp"], st["offset_v"]


def yaml_with_serial_replies(tmp_path: Path, framing: str) -> Path:
    """sims/ds345.yaml with its RS-232 replies ending `framing` (CR, LF or CRLF)."""
    text = YAML.read_text()
    assert text.count(ASRL_REPLY_LINE) == 1, "sims/ds345.yaml no longer has one RS-232 reply terminator line"
    path = tmp_path / f"ds345_{framing}.yaml"
    path.write_text(text.replace(ASRL_REPLY_LINE, f'        r: "{FRAMINGS[framing]}"\n'))
    return path


@pytest.fixture(params=sorted(FRAMINGS))
def serial_sim(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[pyvisa.resources.MessageBasedResource]:
    rm = pyvisa.ResourceManager(f"{yaml_with_serial_replies(tmp_path, request.param)}@sim")
    resource = rm.open_resource("ASRL1::INSTR", timeout=200)
    yield resource
    resource.close()
    rm.close()


def test_every_serial_framing_identifies_sets_and_reads(serial_sim: pyvisa.resources.MessageBasedResource) -> None:
    generator = DS345(serial_sim)
    assert generator.identify() == "StanfordResearchSystems,DS345,00345,1.04"
    generator.set_square(7, 0.6)
    assert square_state(generator) == SQUARE_7HZ_0V6
    generator.mute()
    assert generator.state()["amplitude_vpp"] == 0.0


def test_the_shipped_model_answers_cr_on_rs232_which_an_lf_reader_never_sees() -> None:
    """The failure the driver fixes: a reader waiting for LF times out on a unit that ends replies with CR."""
    rm = pyvisa.ResourceManager(f"{YAML}@sim")
    resource = rm.open_resource("ASRL1::INSTR", timeout=100, write_termination="\n", read_termination="\n")
    resource.write("*IDN?")
    with pytest.raises(pyvisa.errors.VisaIOError):
        resource.read()
    resource.close()
    rm.close()


def test_gpib_stays_on_lf_and_serial_reads_cr_for_the_raw_console() -> None:
    rm = pyvisa.ResourceManager(f"{YAML}@sim")
    gpib, asrl = rm.open_resource("GPIB0::19::INSTR"), rm.open_resource("ASRL1::INSTR")
    DS345(gpib), DS345(asrl)
    assert (gpib.write_termination, gpib.read_termination) == ("\n", "\n")
    assert (asrl.write_termination, asrl.read_termination) == ("\n", "\r")
    gpib.close(), asrl.close()
    rm.close()


@pytest.mark.parametrize("reply_end", [b"\r", b"\n", b"\r\n"])
def test_twin_on_an_asrl_resource_in_each_framing(reply_end: bytes) -> None:
    twin = DS345Twin(paper_world())
    generator = DS345(twin.resource("ASRL1::INSTR", reply_end=reply_end))
    assert generator.identify().split(",")[1] == "DS345"
    generator.set_square(7, 0.6)
    assert square_state(generator) == SQUARE_7HZ_0V6
    assert twin.esr & 0b0011_0100 == 0  # no query, execution or command error: every reply was read in turn


def test_twin_on_gpib_with_cr_replies_is_not_read_as_serial() -> None:
    """GPIB stays strict: a reply without LF is not a reply there (the driver does not read to CR on GPIB)."""
    generator = DS345(DS345Twin(paper_world()).resource("GPIB0::19::INSTR", reply_end=b"\r"))
    with pytest.raises(InstrumentError, match="no reply to '\\*IDN\\?'"):
        generator.identify()


@pytest.mark.parametrize("end", [b"\r", b"\n", b"\r\n"])
def test_serial_bytes_on_the_wire(end: bytes) -> None:
    """Commands still end LF on RS-232; each reply is read up to its first CR or LF, leftovers skipped."""
    ok = (b"*ESR?", b"0" + end)
    pairs = [(b"OFFS?", b"0" + end), (b"FUNC 1", None), ok, (b"FREQ 7", None), ok]
    pairs += [(b"AMPL 0.6VP", None), ok, (b"OFFS 0", None), ok]
    with expected_protocol(pairs, resource_name="ASRL1::INSTR") as res:
        DS345(res).set_square(7, 0.6)
    assert res.sent[0] == b"OFFS?\n"


def test_serial_timeout_mid_reply_is_an_instrument_error() -> None:
    with expected_protocol([(b"*IDN?", b"StanfordResearchSystems,DS345")], resource_name="ASRL1::INSTR") as res:
        generator = DS345(res)
        with pytest.raises(InstrumentError, match="no reply to '\\*IDN\\?' within the timeout"):
            generator.identify()


def test_station_twin_at_an_rs232_address_answers_cr_and_the_driver_reads_it() -> None:
    cfg = parse_config('[generator]\nsim = true\nresource = "ASRL1::INSTR"\n')
    conn = connect_instrument(cfg, "generator")
    try:
        generator = conn.instrument
        assert isinstance(generator, DS345)
        assert generator.resource.reply_end == b"\r" and generator.resource.read_termination == "\r"
        generator.set_square(7, 0.6)
        assert square_state(generator) == SQUARE_7HZ_0V6
    finally:
        conn.close()
