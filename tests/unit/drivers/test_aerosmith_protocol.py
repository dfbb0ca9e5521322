"""1291BR driver, byte for byte against the documented command table (docs/instruments.md, 1291BR section).

Expected bytes are written out by hand from the documented syntax: mnemonic + value (ACL %.3f, JOG/AMP/FRQ
%.6f, MCO %.3f) + CR LF; replies are a value line ending CR, then the prompt line ">" CR.

The real framing is unconfirmed, so every dialogue is replayed under each framing the driver must accept
(docs/instruments.md, "Framing"): reply lines ending CR, LF or CR LF, and the prompt with or without its
terminator.
"""

from __future__ import annotations

import math

import pytest

from drivers.aerosmith import Aerosmith1291BR
from drivers.serial_link import Framing
from qmg_lab.instruments import InstrumentError, InterlockError, LimitError, TableReading
from tests.support.protocol_serial import ProtocolPort, expected_protocol

P = b">\r"

# the same dialogue, written with CR line ends, as the table would send it under each framing
FRAMINGS = {
    "CR": lambda r: r,
    "LF": lambda r: r.replace(b"\r", b"\n"),
    "CRLF": lambda r: r.replace(b"\r", b"\r\n"),
    "CR, bare prompt": lambda r: r[:-1] if r.endswith(b">\r") else r,
    "CRLF, bare prompt": lambda r: (r[:-1] if r.endswith(b">\r") else r).replace(b"\r", b"\r\n"),
}


@pytest.fixture(autouse=True, params=list(FRAMINGS))
def reply_framing(request: pytest.FixtureRequest, monkeypatch: pytest.MonkeyPatch) -> str:
    monkeypatch.setattr(ProtocolPort, "reply_framing", staticmethod(FRAMINGS[request.param]))
    return str(request.param)


def table(port: ProtocolPort) -> Aerosmith1291BR:
    return Aerosmith1291BR(port, max_rate_dps=100.0, max_accel_dps2=500.0)


# ------------------------------------------------------------------------------------------ the helper itself


def test_helper_rejects_wrong_bytes_at_once() -> None:
    port = ProtocolPort([(b"STA\r\n", b"8\r>\r")])
    with pytest.raises(AssertionError, match="expected b'STA"):
        port.write(b"STO\r\n")


def test_helper_reports_unused_pairs_and_unread_replies() -> None:
    port = ProtocolPort([(b"STA\r\n", b"8\r>\r"), (b"PVE\r\n", b"0.0\r>\r")])
    port.write(b"STA\r\n")
    with pytest.raises(AssertionError, match="never sent"):
        port.assert_complete()
    port.write(b"PVE\r\n")
    with pytest.raises(AssertionError, match="never read"):
        port.assert_complete()


# ------------------------------------------------------------------------------------------ commands


def test_identify_sends_sta() -> None:
    with expected_protocol(table, [(b"STA\r\n", b"8\r" + P)]) as t:
        ident = t.identify()
    assert "1291BR" in ident and "STA=8" in ident


def test_set_rate_sends_acl_jog_then_sta() -> None:
    pairs = [(b"ACL300.000\r\n", P), (b"JOG5.000000\r\n", P), (b"STA\r\n", b"9\r" + P)]
    with expected_protocol(table, pairs) as t:
        t.set_rate(5.0, 300.0)


def test_set_rate_negative_and_fractional() -> None:
    pairs = [(b"ACL150.250\r\n", P), (b"JOG-12.345678\r\n", P), (b"STA\r\n", b"9\r" + P)]
    with expected_protocol(table, pairs) as t:
        t.set_rate(-12.345678, 150.25)


def test_set_rate_sees_interlock_in_status() -> None:
    pairs = [(b"ACL300.000\r\n", P), (b"JOG5.000000\r\n", P), (b"STA\r\n", b"12\r" + P)]  # 12 = 4 | 8
    with expected_protocol(table, pairs) as t, pytest.raises(InterlockError, match="STA=12"):
        t.set_rate(5.0, 300.0)


def test_jog_refused_with_e04_raises_interlock_error_and_consumes_prompt() -> None:
    pairs = [(b"ACL300.000\r\n", P), (b"JOG5.000000\r\n", b"E04 INTERLOCK\r" + P)]
    with expected_protocol(table, pairs) as t, pytest.raises(InterlockError, match=r"JOG5\.000000.*E04"):
        t.set_rate(5.0, 300.0)


def test_unknown_command_error_names_command_and_code() -> None:
    with (
        expected_protocol(table, [(b"PVE\r\n", b"E01 UNKNOWN COMMAND\r" + P)]) as t,
        pytest.raises(InstrumentError, match=r"'PVE' refused: E01 UNKNOWN COMMAND \(unknown command\)"),
    ):
        t.read()


def test_set_sinusoid_sequence() -> None:
    pairs = [
        (b"ACL300.000\r\n", P),
        (b"AMP5.000000\r\n", P),
        (b"FRQ2.000000\r\n", P),
        (b"SGO\r\n", P),
        (b"STA\r\n", b"25\r" + P),
    ]
    with expected_protocol(table, pairs) as t:
        t.set_sinusoid(5.0, 2.0, 300.0)


def test_set_sinusoid_refused_when_peak_acceleration_exceeds_accel() -> None:
    # peak acceleration of 5 sin(2 pi 10 t) is 5 * 2 pi * 10 = 314.16 deg/s^2 > 300
    with expected_protocol(table, []) as t, pytest.raises(LimitError, match=r"314\.159.*acceleration limit 300"):
        t.set_sinusoid(5.0, 10.0, 300.0)
    assert 5.0 * 2 * math.pi * 10.0 > 300.0


def test_stop_and_safe_state() -> None:
    with expected_protocol(table, [(b"STO\r\n", P), (b"STA\r\n", b"10\r" + P)]) as t:
        t.stop()
    with expected_protocol(table, [(b"STO\r\n", P), (b"STO\r\n", P)]) as t:
        t.safe_state()
        t.safe_state()


def test_read_parses_pve_ppo_sta() -> None:
    pairs = [(b"PVE\r\n", b"5.000300\r" + P), (b"PPO\r\n", b"123.4560\r" + P), (b"STA\r\n", b"15\r" + P)]
    with expected_protocol(table, pairs) as t:
        reading = t.read()
    assert reading == TableReading(rate_dps=5.0003, position_deg=123.456, status=15, interlock=True)


def test_motion_complete() -> None:
    with expected_protocol(table, [(b"MCO0.010\r\n", b"1\r" + P)]) as t:
        assert t.motion_complete(0.01) is True
    with expected_protocol(table, [(b"MCO0.010\r\n", b"0\r" + P)]) as t:
        assert t.motion_complete(0.01) is False


# ------------------------------------------------------------------------------------------ bad replies


@pytest.mark.parametrize(
    ("reply", "match"),
    [
        (b"5.0O03\r" + P, r"garbled reply to 'PVE'.*5\.0O03"),
        (b"5.00", r"truncated reply to 'PVE'.*b'5\.00'"),
        (b"5.0\xff3\r" + P, r"garbled reply to 'PVE'.*xff"),
        (b"5.000300\r", r"missing prompt after 'PVE'.*timeout: no reply"),
        (b"5.000300\r<\r", r"missing prompt after 'PVE'.*'<'"),
        (None, r"timeout: no reply to 'PVE'"),
        (b"\r" + P, r"garbled reply to 'PVE'"),
    ],
)
def test_bad_replies_raise_instrument_error_naming_the_command(reply: bytes | None, match: str) -> None:
    port = ProtocolPort([(b"PVE\r\n", reply)])
    with pytest.raises(InstrumentError, match=match):
        table(port).read()


def test_prompt_only_command_answered_with_a_value_is_refused() -> None:
    port = ProtocolPort([(b"STO\r\n", b"1\r" + P)])
    with pytest.raises(InstrumentError, match=r"missing prompt after 'STO'.*'1'"):
        table(port).safe_state()


def test_stale_bytes_are_discarded_before_the_next_command() -> None:
    port = ProtocolPort([(b"PVE\r\n", b"5.000300\r"), (b"STA\r\n", b"8\r" + P)])
    t = table(port)
    with pytest.raises(InstrumentError):
        t.read()
    assert "STA=8" in t.identify()
    port.assert_complete()


# ------------------------------------------------------------------------------------------ limits


@pytest.mark.parametrize(
    ("rate", "accel", "match"),
    [
        (100.5, 300.0, r"table rate = 100\.5 deg/s is outside the limit \[-100, 100\]"),
        (-101.0, 300.0, r"table rate = -101"),
        (5.0, 600.0, r"table acceleration = 600 deg/s\^2 is outside the limit \[0, 500\]"),
        (5.0, 0.0, r"table acceleration = 0 deg/s\^2 must be positive"),
        (5.0, 0.0004, r"table acceleration = 0 deg/s\^2 must be positive"),  # ACL 3 decimals would send 0.000
        (float("nan"), 300.0, r"table rate = nan is not a finite number"),
    ],
)
def test_set_rate_outside_limits_sends_nothing(rate: float, accel: float, match: str) -> None:
    port = ProtocolPort([])
    with pytest.raises(LimitError, match=match):
        table(port).set_rate(rate, accel)
    assert port.bytes_written == b""


@pytest.mark.parametrize(
    ("amp", "freq", "accel", "match"),
    [
        (150.0, 0.1, 300.0, "sinusoid amplitude"),
        (5.0, 0.0, 300.0, "must be positive"),
        (5.0, 1.0, 900.0, "table acceleration"),
    ],
)
def test_set_sinusoid_outside_limits_sends_nothing(amp: float, freq: float, accel: float, match: str) -> None:
    port = ProtocolPort([])
    with pytest.raises(LimitError, match=match):
        table(port).set_sinusoid(amp, freq, accel)
    assert port.bytes_written == b""


def test_constructor_rejects_bad_limits() -> None:
    with pytest.raises(ValueError, match="max_rate_dps"):
        Aerosmith1291BR(ProtocolPort([]), max_rate_dps=0.0, max_accel_dps2=300.0)
    with pytest.raises(ValueError, match="max_accel_dps2"):
        Aerosmith1291BR(ProtocolPort([]), max_rate_dps=10.0, max_accel_dps2=float("inf"))


# ------------------------------------------------------------------------------------------ reconnect


def test_reconnect_closes_reopens_and_identifies() -> None:
    first = ProtocolPort([])
    second = ProtocolPort([(b"STA\r\n", b"8\r" + P)])
    t = Aerosmith1291BR(first, max_rate_dps=100.0, max_accel_dps2=500.0, port_factory=lambda: second)
    t.reconnect()
    assert not first.is_open
    second.assert_complete()


def test_reconnect_without_factory_is_an_instrument_error() -> None:
    with pytest.raises(InstrumentError, match="no port_factory"):
        table(ProtocolPort([])).reconnect()


# ------------------------------------------------------------------------------------------ framing


@pytest.mark.parametrize(
    "reply",
    [
        b"5.000300\r>",  # prompt without its terminator
        b" 5.000300 \r> \r",  # blanks around the content
        b"\r\n5.000300\r\n>\r\n",  # a blank line first
        b"5.000300\n\r>\n\r",  # LF CR
    ],
)
def test_tolerated_framings_parse_the_same_value(reply: bytes) -> None:
    with expected_protocol(table, [(b"PVE\r\n", reply)]) as t:
        assert t._transact("velocity") == 5.0003


@pytest.mark.parametrize(
    ("reply", "match"),
    [
        (b"5.0 03\r" + P, r"garbled reply to 'PVE'.*'5\.0 03'"),  # content still strict: no inner blank
        (b"+5.0003e0x\r" + P, r"garbled reply to 'PVE'"),
        (b"> 5.0\r", r"garbled reply to 'PVE'.*'>'"),  # a prompt where the value belongs
    ],
)
def test_content_is_still_parsed_strictly(reply: bytes, match: str) -> None:
    with pytest.raises(InstrumentError, match=match):
        table(ProtocolPort([(b"PVE\r\n", reply)])).read()


@pytest.mark.parametrize(("terminator", "sent"), [("CR", b"STA\r"), ("LF", b"STA\n"), ("CRLF", b"STA\r\n")])
def test_command_terminator_from_the_framing(terminator: str, sent: bytes) -> None:
    def build(port: ProtocolPort) -> Aerosmith1291BR:
        return Aerosmith1291BR(
            port, max_rate_dps=100.0, max_accel_dps2=500.0, framing=Framing(command_terminator=terminator, prompt=">")
        )

    with expected_protocol(build, [(sent, b"8\r" + P)]) as t:
        assert "STA=8" in t.identify()


@pytest.mark.parametrize(("reply_terminator", "reply"), [("CR", b"8\r>\r"), ("LF", b"8\n>\n"), ("CRLF", b"8\r\n>\r\n")])
def test_an_exact_reply_terminator_is_honoured(
    reply_terminator: str, reply: bytes, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(ProtocolPort, "reply_framing", None)

    def build(port: ProtocolPort) -> Aerosmith1291BR:
        return Aerosmith1291BR(
            port,
            max_rate_dps=100.0,
            max_accel_dps2=500.0,
            framing=Framing(reply_terminator=reply_terminator, prompt=">"),
        )

    with expected_protocol(build, [(b"STA\r\n", reply)]) as t:
        assert "STA=8" in t.identify()
    # a CR-only reply never ends a line when LF is required: the driver says so instead of guessing
    if reply_terminator == "LF":
        port = ProtocolPort([(b"STA\r\n", b"8\r>\r")])
        with pytest.raises(InstrumentError, match=r"truncated reply to 'STA'.*without a terminator \(LF\)"):
            build(port).identify()
