"""The EC1x driver against an EC13 as the public Sun EC13 driver (achim1/skippylab) shows it answering.

STATUS? = 18 Y/N flags + one self-test digit (YNNNYYYNNNNNNNNNNN0: power on, heat and cool enabled, valid set
temperature, not ramping, self-test 0); settings (SET=, RATE=, ON, LTL=, UTL=) answer nothing. The driver must
identify, set and read such a controller, confirming each unanswered setting by reading it back (RATE?, SET?,
LTL?, UTL?, STATUS? char 0), and still refuse what the controller did not take. Byte-exact dialogues first
(tests/support/protocol_serial.py), then the chamber twin in its EC13 behaviour over real pyserial transports.
"""

from __future__ import annotations

import logging
from collections.abc import Iterator

import pytest
import serial

from drivers.chamber import ChamberStatus, SunEC1xChamber, parse_status
from qmg_lab.instruments import ChamberReading, InstrumentError
from sims.chamber_twin import ChamberTwin
from sims.serial_twin import InProcessSerial, serve_socket
from sims.world import World
from tests.support.protocol_serial import ProtocolPort, expected_protocol
from tests.support.twin_params import chamber_twin_settings, paper_world_params

ON_IDLE = b"YNNNYYYNNNNNNNNNNN0\r\n"  # power, heat, cool, valid set temperature; not ramping; self-test ok
ON_RAMPING = b"YNNNYYYNYNNNNNNNNN0\r\n"  # the same, ramping (char 8)
OFF_IDLE = b"NNNNNNYNNNNNNNNNNN0\r\n"


def ec13(ack: str = "auto"):  # type: ignore[no-untyped-def]
    def build(port: ProtocolPort) -> SunEC1xChamber:
        return SunEC1xChamber(port, min_c=-40.0, max_c=85.0, max_ramp_c_per_min=5.0, safe_setpoint_c=25.0, ack=ack)

    return build


# ------------------------------------------------------------------------------------------ STATUS? layouts
@pytest.mark.parametrize(
    ("text", "flags", "self_test"),
    [
        ("YNNNYYYNNNNNNNNNNN0", "YNNNYYYNNNNNNNNNNN", 0),
        ("YNNNYYYNYNNNNNNNNN2", "YNNNYYYNYNNNNNNNNN", 2),
        ("YYYNNNNNYNNNNNNN", "YYYNNNNNYNNNNNNN", None),  # the 16-flag layout accepted before
        ("NNNNNNNNN", "NNNNNNNNN", None),  # 9 flags: the shortest with char 8
        ("Y" * 32, "Y" * 32, None),
    ],
)
def test_status_layouts_accepted(text: str, flags: str, self_test: int | None) -> None:
    assert parse_status(text) == ChamberStatus(flags=flags, self_test=self_test)


@pytest.mark.parametrize("text", ["YNNNYYYNNNNNNNNNNN00", "YNNNYYYN0", "YNNNYYYNNNNNNNNNNNX", "0YNNNYYYNNN", "Y" * 33])
def test_status_layouts_refused(text: str) -> None:
    with pytest.raises(ValueError, match="not a Y/N status string"):
        parse_status(text)


# ------------------------------------------------------------------------------------------ byte for byte
def no_ack_setpoint_30_at_2() -> list[tuple[bytes, bytes | None]]:
    """set_setpoint(30, 2) on a controller that answers no setting: each one confirmed by reading it back."""
    return [
        (b"RATE=2.000\r\n", None),
        (b"RATE?\r\n", b"2.000\r\n"),
        (b"ON\r\n", None),
        (b"STATUS?\r\n", ON_IDLE),
        (b"SET=30.00\r\n", None),
        (b"SET?\r\n", b"30.00\r\n"),
    ]


@pytest.mark.parametrize("ack", ["auto", "none"])
def test_identifies_sets_and_reads_an_ec13_that_acknowledges_nothing(ack: str) -> None:
    pairs = [
        (b"STATUS?\r\n", ON_IDLE),
        (b"LTL=-40.00\r\n", None),
        (b"LTL?\r\n", b"-40.00\r\n"),
        (b"UTL=85.00\r\n", None),
        (b"UTL?\r\n", b"85.00\r\n"),
        *no_ack_setpoint_30_at_2(),
        (b"C1?\r\n", b"24.87\r\n"),
        (b"SET?\r\n", b"25.40\r\n"),
        (b"STATUS?\r\n", ON_RAMPING),
    ]
    with expected_protocol(ec13(ack), pairs) as chamber:
        identity = chamber.identify()
        chamber.write_limits()
        chamber.set_setpoint(30.0, 2.0)
        assert chamber.read() == ChamberReading(temperature_c=24.87, setpoint_c=25.4, ramping=True)
    assert identity.endswith("STATUS=YNNNYYYNNNNNNNNNNN0; self-test 0 (system self test ok))")
    assert chamber.unacknowledged == 5


def test_an_ok_that_does_come_is_consumed_and_nothing_is_read_back() -> None:
    pairs = [(b"RATE=2.000\r\n", b"OK\r\n"), (b"ON\r\n", b"OK\r\n"), (b"SET=30.00\r\n", b"OK\r\n")]
    with expected_protocol(ec13(), pairs) as chamber:
        chamber.set_setpoint(30.0, 2.0)
    assert chamber.unacknowledged == 0


def test_set_read_back_on_the_ramping_setpoint_is_confirmed_by_the_ramping_flag() -> None:
    pairs = [(b"ON\r\n", None), (b"STATUS?\r\n", ON_RAMPING)]
    pairs += [(b"SET=25.00\r\n", None), (b"SET?\r\n", b"27.31\r\n"), (b"STATUS?\r\n", ON_RAMPING)]
    with expected_protocol(ec13(), pairs) as chamber:
        chamber.safe_state()


@pytest.mark.parametrize(
    ("pairs", "match"),
    [
        (
            [(b"RATE=2.000\r\n", None), (b"RATE?\r\n", b"1.000\r\n")],
            r"'RATE=2\.000' not taken: RATE\? = 1",
        ),
        (
            [
                *no_ack_setpoint_30_at_2()[:4],
                (b"SET=30.00\r\n", None),
                (b"SET?\r\n", b"25.00\r\n"),
                (b"STATUS?\r\n", ON_IDLE),
            ],
            r"'SET=30\.00' not taken: SET\? = 25 and STATUS\? = 'YNNNYYYNNNNNNNNNNN0' \(not ramping\)",
        ),
        (
            [*no_ack_setpoint_30_at_2()[:3], (b"STATUS?\r\n", OFF_IDLE)],
            r"'ON' not taken: STATUS\? = 'NNNNNNYNNNNNNNNNNN0'",
        ),
        (
            [*no_ack_setpoint_30_at_2()[:4], (b"SET=30.00\r\n", b"?LIMIT\r\n")],
            r"'SET=30\.00' refused: '\?LIMIT'",
        ),
        (
            [*no_ack_setpoint_30_at_2()[:4], (b"SET=30.00\r\n", b"0K\r\n")],
            r"garbled reply to 'SET=30\.00': received '0K' instead of 'OK'",
        ),
    ],
)
def test_a_setting_not_taken_is_still_an_error(pairs: list[tuple[bytes, bytes | None]], match: str) -> None:
    port = ProtocolPort(pairs)
    with pytest.raises(InstrumentError, match=match):
        ec13()(port).set_setpoint(30.0, 2.0)
    port.assert_complete()


def test_ack_ok_makes_silence_a_fault() -> None:
    port = ProtocolPort([(b"RATE=2.000\r\n", None)])
    with pytest.raises(InstrumentError, match=r"timeout: no reply to 'RATE=2\.000'"):
        ec13("ok")(port).set_setpoint(30.0, 2.0)


# ------------------------------------------------------------------------------------------ self-test digit
@pytest.mark.parametrize("code", [1, 2])
def test_ram_self_test_errors_are_reported_not_refused(code: int, caplog: pytest.LogCaptureFixture) -> None:
    status = b"YNNNYYYNNNNNNNNNNN" + str(code).encode() + b"\r\n"
    pairs = [
        (b"STATUS?\r\n", status),
        (b"C1?\r\n", b"25.00\r\n"),
        (b"SET?\r\n", b"25.00\r\n"),
        (b"STATUS?\r\n", status),
    ]
    with caplog.at_level(logging.WARNING, logger="drivers.chamber"), expected_protocol(ec13(), pairs) as chamber:
        assert f"self-test {code} (" in chamber.identify()
        state = chamber.state()
    assert state["self_test"] == code and "RAM error" in state["self_test_meaning"]
    assert any(f"self-test reports {code}" in r.getMessage() for r in caplog.records)


@pytest.mark.parametrize(("code", "meaning"), [(3, "ROM error"), (7, "undocumented self-test code")])
def test_rom_and_undocumented_self_test_codes_are_faults(code: int, meaning: str) -> None:
    port = ProtocolPort([(b"STATUS?\r\n", b"YNNNYYYNNNNNNNNNNN" + str(code).encode() + b"\r\n")])
    with pytest.raises(InstrumentError, match=f"self-test failed: .*{code} \\({meaning}"):
        ec13()(port).identify()


# ------------------------------------------------------------------------------------------ the twin as an EC13
@pytest.fixture(params=["inprocess", "socket"])
def twin_bench(request: pytest.FixtureRequest) -> Iterator[tuple[ChamberTwin, SunEC1xChamber]]:
    world = World(paper_world_params(initial_temperature_c=25.0))
    twin = ChamberTwin(world, **chamber_twin_settings(status_layout="ec13", acknowledges_settings=False))
    stop = None
    if request.param == "inprocess":
        port = InProcessSerial(twin)
    else:  # a real pyserial port over loopback; its timeout is how long the driver waits for an OK
        # and for each read-back's reply: 0.05 s lost replies to the twin's server thread on a loaded machine
        url, stop = serve_socket(twin)
        port = serial.serial_for_url(url, timeout=0.5)
    chamber = SunEC1xChamber(port, min_c=-40.0, max_c=85.0, max_ramp_c_per_min=5.0, safe_setpoint_c=25.0)
    yield twin, chamber
    chamber.close()
    if stop is not None:
        stop()


def test_twin_as_ec13_identifies_sets_and_reads(twin_bench: tuple[ChamberTwin, SunEC1xChamber]) -> None:
    twin, chamber = twin_bench
    assert chamber.identify() == (
        "Sun Electronic Systems EC1x (ASCII protocol; STATUS=YNNNYYYNNNNNNNNNNN0; self-test 0 (system self test ok))"
    )
    chamber.write_limits()
    assert (twin.ltl_c, twin.utl_c) == (-40.0, 85.0)
    chamber.set_setpoint(30.0, 2.0)
    reading = chamber.read()
    assert reading.ramping and reading.setpoint_c == pytest.approx(25.0, abs=0.005)  # no virtual time has passed
    assert chamber.ramp_rate() == 2.0 and chamber.power_on()
    assert chamber.unacknowledged == 5  # LTL=, UTL=, RATE=, ON, SET=: all confirmed by read-back


def test_twin_refusal_without_a_reply_shows_in_the_read_back_and_the_error_flag(
    twin_bench: tuple[ChamberTwin, SunEC1xChamber],
) -> None:
    twin, chamber = twin_bench
    twin.utl_c = 28.0  # the controller's own limit, tighter than the driver's max_c
    with pytest.raises(InstrumentError, match=r"'SET=30\.00' not taken: SET\? = 25 .*\(not ramping\)"):
        chamber.set_setpoint(30.0, 2.0)
    assert twin.last_command_error
    assert chamber._status().flags[1] == "Y"  # char 1: last command error


def watched_safe_state() -> list[tuple[bytes, bytes | None]]:
    """safe_state() (ON, SET=25.00) while the chamber ramps: SET? = 27.31, confirmed by the ramping flag only."""
    return [
        (b"ON\r\n", None),
        (b"STATUS?\r\n", ON_RAMPING),
        (b"SET=25.00\r\n", None),
        (b"SET?\r\n", b"27.31\r\n"),
        (b"STATUS?\r\n", ON_RAMPING),
    ]


def test_a_set_confirmed_by_the_ramping_flag_is_watched_until_the_ramp_ends_there() -> None:
    reads = [(b"C1?\r\n", b"26.90\r\n"), (b"SET?\r\n", b"26.10\r\n"), (b"STATUS?\r\n", ON_RAMPING)]
    reads += [(b"C1?\r\n", b"25.30\r\n"), (b"SET?\r\n", b"25.00\r\n"), (b"STATUS?\r\n", ON_IDLE)]
    reads += [(b"C1?\r\n", b"25.10\r\n"), (b"SET?\r\n", b"25.02\r\n"), (b"STATUS?\r\n", ON_IDLE)]
    with expected_protocol(ec13(), watched_safe_state() + reads) as chamber:
        chamber.safe_state()
        assert chamber.read().setpoint_c == 26.1  # 1.21 from 25: closing in
        assert chamber.read().setpoint_c == 25.0  # there, ramp over: the watch ends
        assert chamber.read().setpoint_c == 25.02  # a later drift is not a lost setting


def test_a_set_lost_while_ramping_elsewhere_is_found_by_the_watch() -> None:
    """The controller keeps ramping to an earlier target (35): the setpoint moves away from 25."""
    reads = [(b"C1?\r\n", b"27.00\r\n"), (b"SET?\r\n", b"27.32\r\n"), (b"STATUS?\r\n", ON_RAMPING)]
    reads += [(b"C1?\r\n", b"27.10\r\n"), (b"SET?\r\n", b"27.33\r\n"), (b"STATUS?\r\n", ON_RAMPING)]
    with expected_protocol(ec13(), watched_safe_state() + reads) as chamber:
        chamber.safe_state()
        chamber.read()  # 2.32 from 25: within two resolution steps of 2.31 (the reading's own rounding)
        with pytest.raises(InstrumentError, match=r"'SET=25\.00' not taken: the ramping setpoint \(SET\? = 27\.33\)"):
            chamber.read()  # 2.33: it grows beyond 2.31 + 0.01
