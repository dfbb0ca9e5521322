"""EC1x chamber driver, byte for byte against the documented syntax (docs/instruments.md, chamber section).

Commands: text + CR LF (SET=%.2f, RATE=%.3f, LTL=/UTL= %.2f); every reply one line ending CR LF; settings
answer OK; refusals start with '?'; STATUS? is Y/N flags with char 0 = power, char 8 = ramping.

The real framing is unconfirmed: every dialogue is replayed with replies ending CR LF, CR and LF.
"""

from __future__ import annotations

import pytest

from drivers.chamber import FIRST_CONTACT_ATTEMPTS, SunEC1xChamber
from qmg_lab.instruments import ChamberReading, InstrumentError, LimitError
from tests.support.protocol_serial import ProtocolPort, expected_protocol

OK = b"OK\r\n"

FRAMINGS = {
    "CRLF": lambda r: r,
    "CR": lambda r: r.replace(b"\r\n", b"\r"),
    "LF": lambda r: r.replace(b"\r\n", b"\n"),
}


@pytest.fixture(autouse=True, params=list(FRAMINGS))
def reply_framing(request: pytest.FixtureRequest, monkeypatch: pytest.MonkeyPatch) -> str:
    monkeypatch.setattr(ProtocolPort, "reply_framing", staticmethod(FRAMINGS[request.param]))
    return str(request.param)


def chamber(port: ProtocolPort) -> SunEC1xChamber:
    return SunEC1xChamber(port, min_c=-40.0, max_c=85.0, max_ramp_c_per_min=5.0, safe_setpoint_c=25.0)


def test_set_setpoint_sends_rate_on_set() -> None:
    with expected_protocol(chamber, [(b"RATE=2.000\r\n", OK), (b"ON\r\n", OK), (b"SET=30.00\r\n", OK)]) as c:
        c.set_setpoint(30.0, 2.0)


def test_set_setpoint_negative_and_fractional() -> None:
    with expected_protocol(chamber, [(b"RATE=0.250\r\n", OK), (b"ON\r\n", OK), (b"SET=-12.35\r\n", OK)]) as c:
        c.set_setpoint(-12.345, 0.25)


def test_read_parses_c1_set_status() -> None:
    pairs = [(b"C1?\r\n", b"27.50\r\n"), (b"SET?\r\n", b"28.00\r\n"), (b"STATUS?\r\n", b"YYYNNNNNYNNNNNNN\r\n")]
    with expected_protocol(chamber, pairs) as c:
        assert c.read() == ChamberReading(temperature_c=27.5, setpoint_c=28.0, ramping=True)
    pairs[2] = (b"STATUS?\r\n", b"YYYNNNNNNNNNNNNN\r\n")
    with expected_protocol(chamber, pairs) as c:
        assert c.read().ramping is False


def test_safe_state_powers_on_then_sets_the_safe_setpoint() -> None:
    with expected_protocol(chamber, [(b"ON\r\n", OK), (b"SET=25.00\r\n", OK)] * 2) as c:
        c.safe_state()
        c.safe_state()


def test_write_limits_identify_power() -> None:
    pairs = [
        (b"LTL=-40.00\r\n", OK),
        (b"UTL=85.00\r\n", OK),
        (b"STATUS?\r\n", b"NNNNNNNNNNNNNNNN\r\n"),
        (b"STATUS?\r\n", b"NNNNNNNNNNNNNNNN\r\n"),
        (b"RATE?\r\n", b"2.000\r\n"),
        (b"OFF\r\n", OK),
    ]
    with expected_protocol(chamber, pairs) as c:
        c.write_limits()
        assert "EC1x" in c.identify()
        assert c.power_on() is False
        assert c.ramp_rate() == 2.0
        c.power_off()


def test_refusal_names_the_command() -> None:
    port = ProtocolPort([(b"RATE=2.000\r\n", OK), (b"ON\r\n", OK), (b"SET=30.00\r\n", b"?LIMIT\r\n")])
    with pytest.raises(InstrumentError, match=r"'SET=30\.00' refused: '\?LIMIT'"):
        chamber(port).set_setpoint(30.0, 2.0)
    port.assert_complete()


@pytest.mark.parametrize(
    ("reply", "match"),
    [
        (b"27.5O\r\n", r"garbled reply to 'C1\?'.*27\.5O"),
        (b"27.5", r"truncated reply to 'C1\?'.*b'27\.5'"),
        (b"2\x007.5\r\n", r"garbled reply to 'C1\?'"),
        (None, r"timeout: no reply to 'C1\?'"),
        (b"OK\r\n", r"garbled reply to 'C1\?'.*'OK'"),
    ],
)
def test_bad_query_replies(reply: bytes | None, match: str) -> None:
    port = ProtocolPort([(b"C1?\r\n", reply)])
    with pytest.raises(InstrumentError, match=match):
        chamber(port).read()


@pytest.mark.parametrize(
    ("reply", "match"),
    [
        (b"YYY\r\n", r"garbled reply to 'STATUS\?'.*'YYY'"),
        (b"YYYNNNNNXNNNNNNN\r\n", r"garbled reply to 'STATUS\?'"),
    ],
)
def test_bad_status(reply: bytes, match: str) -> None:
    port = ProtocolPort([(b"STATUS?\r\n", reply)])
    with pytest.raises(InstrumentError, match=match):
        chamber(port).power_on()
    # at first contact, a garbled STATUS? is asked again, FIRST_CONTACT_ATTEMPTS times in all
    port = ProtocolPort([(b"STATUS?\r\n", reply)] * FIRST_CONTACT_ATTEMPTS)
    with pytest.raises(InstrumentError, match=f"after {FIRST_CONTACT_ATTEMPTS} attempts .*" + match):
        chamber(port).identify()
    port.assert_complete()


def test_setting_not_acknowledged_ok() -> None:
    port = ProtocolPort([(b"ON\r\n", OK), (b"SET=25.00\r\n", b"0K\r\n")])
    with pytest.raises(InstrumentError, match=r"garbled reply to 'SET=25\.00'.*'0K'"):
        chamber(port).safe_state()


@pytest.mark.parametrize(
    ("setpoint", "ramp", "match"),
    [
        (90.0, 1.0, r"chamber setpoint = 90 deg C is outside the limit \[-40, 85\]"),
        (-41.0, 1.0, r"chamber setpoint = -41"),
        (30.0, 6.0, r"chamber ramp = 6 deg C/min is outside the limit \[0, 5\]"),
        (30.0, 0.0, r"chamber ramp = 0 deg C/min must be positive"),
        (30.0, -1.0, r"chamber ramp = -1"),
        (30.0, 0.0004, r"chamber ramp = 0 deg C/min must be positive"),  # RATE= 3 decimals would send 0.000
        (85.006, 1.0, r"chamber setpoint = 85.01 deg C is outside"),  # SET= 2 decimals would send 85.01
        (float("inf"), 1.0, r"chamber setpoint = inf is not a finite number"),
    ],
)
def test_limits_refused_before_sending(setpoint: float, ramp: float, match: str) -> None:
    port = ProtocolPort([])
    with pytest.raises(LimitError, match=match):
        chamber(port).set_setpoint(setpoint, ramp)
    assert port.bytes_written == b""


def test_constructor_rejects_inconsistent_limits() -> None:
    with pytest.raises(ValueError, match="min_c"):
        SunEC1xChamber(ProtocolPort([]), min_c=50, max_c=40, max_ramp_c_per_min=1, safe_setpoint_c=45)
    with pytest.raises(ValueError, match="safe_setpoint_c"):
        SunEC1xChamber(ProtocolPort([]), min_c=0, max_c=40, max_ramp_c_per_min=1, safe_setpoint_c=45)


def test_reconnect_identifies_rewrites_limits_and_restores_setpoint() -> None:
    first = ProtocolPort([(b"RATE=1.000\r\n", OK), (b"ON\r\n", OK), (b"SET=30.00\r\n", OK)])
    second = ProtocolPort(
        [
            (b"STATUS?\r\n", b"YYYNNNNNYNNNNNNN\r\n"),
            (b"LTL=-40.00\r\n", OK),
            (b"UTL=85.00\r\n", OK),
            (b"RATE=1.000\r\n", OK),
            (b"ON\r\n", OK),
            (b"SET=30.00\r\n", OK),
        ]
    )
    c = SunEC1xChamber(
        first, min_c=-40.0, max_c=85.0, max_ramp_c_per_min=5.0, safe_setpoint_c=25.0, port_factory=lambda: second
    )
    c.set_setpoint(30.0, 1.0)
    c.reconnect()
    assert not first.is_open
    first.assert_complete()
    second.assert_complete()


@pytest.mark.parametrize("reply", [b"27.50\r", b"27.50\n", b"27.50\r\n", b"  27.50 \r\n", b"\n27.50\r"])
def test_tolerated_framings_parse_the_same_temperature(reply: bytes) -> None:
    with expected_protocol(chamber, [(b"C1?\r\n", reply)]) as c:
        assert c._query("C1?", float) == 27.5
