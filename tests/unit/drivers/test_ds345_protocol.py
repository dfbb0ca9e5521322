"""DS345 driver, message by message against the documented protocol (tests/protocol_visa.py fake resource).

Expected bytes come from docs/instruments.md (DS345 section) and the formatting documented in
drivers/ds345.py: one setting per LF-terminated message, each followed by *ESR?.
"""

from __future__ import annotations

import math

import pytest

from drivers.ds345 import DS345, amplitude_to_vpp, format_number
from qmg_lab.instruments import InstrumentError, LimitError
from tests.support.protocol_visa import TIMEOUT, ProtocolResource, expected_protocol

OK = (b"*ESR?", b"0")


def square_7hz_0v6() -> list[tuple[bytes, bytes | None]]:
    """A fresh driver's set_square(7, 0.6): OFFS? once (offset unknown), then FUNC, FREQ, AMPL, OFFS."""
    return [
        (b"OFFS?", b"0"),
        (b"FUNC 1", None),
        OK,
        (b"FREQ 7", None),
        OK,
        (b"AMPL 0.6VP", None),
        OK,
        (b"OFFS 0", None),
        OK,
    ]


def test_set_square_sends_documented_bytes() -> None:
    with expected_protocol(square_7hz_0v6()) as res:
        DS345(res).set_square(7, 0.6)
    assert res.sent[1] == b"FUNC 1\n"


def test_second_setting_needs_no_offset_query_and_formats_numbers() -> None:
    pairs = [
        *square_7hz_0v6(),
        *[(b"FUNC 0", None), OK, (b"FREQ 0.333333", None), OK],
        *[(b"AMPL 0.01VP", None), OK, (b"OFFS -0.5", None), OK],
    ]
    with expected_protocol(pairs) as res:
        gen = DS345(res)
        gen.set_square(7, 0.6)
        gen.set_sine(1 / 3, 0.01, -0.5)


def test_offset_goes_first_when_amplitude_first_would_exceed_5v() -> None:
    # present offset 4 V; new 8 Vpp at 0 V: AMPL first would give 4 + 4 = 8 V > 5 V, so OFFS 0 first
    pairs = [
        (b"OFFS?", b"4.0000"),
        (b"FUNC 1", None),
        OK,
        (b"FREQ 7", None),
        OK,
        (b"OFFS 0", None),
        OK,
        (b"AMPL 8VP", None),
        OK,
    ]
    with expected_protocol(pairs) as res:
        DS345(res).set_square(7, 8.0, 0.0)


@pytest.mark.parametrize(
    ("value", "decimals", "text"),
    [
        (7, 6, "7"),
        (7.25, 6, "7.25"),
        (1e-6, 6, "0.000001"),
        (30.2e6, 6, "30200000"),
        (1 / 3, 6, "0.333333"),
        (0.6, 4, "0.6"),
        (0, 4, "0"),
        (-0.00001, 4, "0"),
        (-1.25, 4, "-1.25"),
        (9.99996, 4, "10"),
        (7199.999, 3, "7199.999"),
        (1234.56789012, 6, "1234.56789"),
    ],
)
def test_number_format(value: float, decimals: int, text: str) -> None:
    assert format_number(value, decimals) == text


@pytest.mark.parametrize(
    ("esr", "bit_text"),
    [
        (b"16", "bit 4 (execution/range error)"),
        (b"32", "bit 5 (command error)"),
        (b"4", "bit 2 (query error)"),
    ],
)
def test_error_bit_raises_naming_command_and_bit(esr: bytes, bit_text: str) -> None:
    pairs = [(b"OFFS?", b"0"), (b"FUNC 1", None), OK, (b"FREQ 7", None), (b"*ESR?", esr)]
    with expected_protocol(pairs) as res, pytest.raises(InstrumentError) as err:
        DS345(res).set_square(7, 0.6)
    assert "'FREQ 7'" in str(err.value) and bit_text in str(err.value)


def test_power_on_bit_is_not_an_error() -> None:
    with expected_protocol([(b"AMPL 0VP", None), (b"*ESR?", b"128")]) as res:
        DS345(res).mute()


def test_mute_and_safe_state_are_idempotent() -> None:
    pairs = [(b"AMPL 0VP", None), OK] * 3
    with expected_protocol(pairs) as res:
        gen = DS345(res)
        gen.mute()
        gen.safe_state()
        gen.safe_state()


@pytest.mark.parametrize(("command", "reply"), [(b"*ESR?", b"1x"), (b"*ESR?", b"256"), (b"*ESR?", b"")])
def test_garbled_esr_reply(command: bytes, reply: bytes) -> None:
    with expected_protocol([(b"AMPL 0VP", None), (command, reply)]) as res, pytest.raises(InstrumentError) as err:
        DS345(res).mute()
    assert "*ESR?" in str(err.value) and repr(reply) in str(err.value)


def test_non_ascii_reply_is_garbled() -> None:
    with (
        expected_protocol([(b"AMPL 0VP", None), (b"*ESR?", b"0\x85")]) as res,
        pytest.raises(InstrumentError, match=r"garbled reply to '\*ESR\?': b'0\\x85'"),
    ):
        DS345(res).mute()


def test_phase_limits() -> None:
    with expected_protocol([(b"PHSE 7199.999", None), OK]) as res:
        gen = DS345(res)
        gen.set_phase(7199.999)
        for bad in (-0.1, 7200.0, float("nan")):
            with pytest.raises(LimitError, match="phase"):
                gen.set_phase(bad)


def test_timeout_becomes_instrument_error() -> None:
    with (
        expected_protocol([(b"AMPL 0VP", None), (b"*ESR?", TIMEOUT)]) as res,
        pytest.raises(InstrumentError, match=r"no reply to '\*ESR\?'"),
    ):
        DS345(res).mute()


def test_identify() -> None:
    idn = b"StanfordResearchSystems,DS345,12345,1.04"
    with expected_protocol([(b"*IDN?", idn + b"\r")]) as res:
        assert DS345(res).identify() == idn.decode()
    with (
        expected_protocol([(b"*IDN?", b"StanfordResearchSystems,DS335,1,1.0")]) as res,
        pytest.raises(InstrumentError, match="DS335"),
    ):
        DS345(res).identify()
    with expected_protocol([(b"*IDN?", b"DS345")]) as res, pytest.raises(InstrumentError, match="garbled"):
        DS345(res).identify()


def test_state_parses_replies() -> None:
    pairs = [(b"FUNC?", b"1"), (b"FREQ?", b"7.000000"), (b"AMPL?", b"0.6000VP"), (b"OFFS?", b"-0.2500")]
    with expected_protocol(pairs) as res:
        st = DS345(res).state()
    assert st == {
        "function": "square",
        "function_code": 1,
        "frequency_hz": 7.0,
        "amplitude": 0.6,
        "amplitude_unit": "VP",
        "amplitude_vpp": 0.6,
        "offset_v": -0.25,
    }


@pytest.mark.parametrize(
    ("func", "ampl", "vpp"),
    [
        (b"0", b"1VR", 2 * math.sqrt(2)),  # sine: Vpp = 2 sqrt 2 Vrms
        (b"1", b"1VR", 2.0),  # square: Vpp = 2 Vrms
        (b"2", b"1VR", 2 * math.sqrt(3)),  # triangle: Vpp = 2 sqrt 3 Vrms
        (b"0", b"10DB", 2.0),  # 10 dBm into 50 ohm: 10 mW, Vrms = sqrt(0.5), sine Vpp = 2
        (b"4", b"1VR", None),  # noise: no crest factor
    ],
)
def test_state_converts_amplitude_units(func: bytes, ampl: bytes, vpp: float | None) -> None:
    pairs = [(b"FUNC?", func), (b"FREQ?", b"1000"), (b"AMPL?", ampl), (b"OFFS?", b"0")]
    with expected_protocol(pairs) as res:
        st = DS345(res).state()
    assert st["amplitude_vpp"] == (None if vpp is None else pytest.approx(vpp, rel=1e-12))
    assert amplitude_to_vpp(1.0, "VP", 4) == 1.0


@pytest.mark.parametrize(
    ("query", "reply"),
    [
        (b"FUNC?", b"9"),
        (b"FUNC?", b"1.0"),
        (b"FREQ?", b"7 Hz"),
        (b"AMPL?", b"0.6"),
        (b"AMPL?", b"0.6VPP"),
    ],
)
def test_state_rejects_garbled_replies(query: bytes, reply: bytes) -> None:
    pairs = {
        b"FUNC?": [(b"FUNC?", reply)],
        b"FREQ?": [(b"FUNC?", b"1"), (b"FREQ?", reply)],
        b"AMPL?": [(b"FUNC?", b"1"), (b"FREQ?", b"7"), (b"AMPL?", reply)],
    }[query]
    with expected_protocol(pairs) as res, pytest.raises(InstrumentError) as err:
        DS345(res).state()
    assert query.decode() in str(err.value) and repr(reply) in str(err.value)


@pytest.mark.parametrize(
    ("args", "kwargs", "limit"),
    [
        ((30.3e6, 1.0), {}, "frequency"),
        ((0.0, 1.0), {}, "frequency"),
        ((7, 0.005), {}, "amplitude"),
        ((7, 10.5), {}, "amplitude"),
        ((7, 3.0), {"max_amplitude_vpp": 2.0}, "amplitude"),
        ((7, 1.0, 5.5), {}, "offset"),
        ((7, 6.0, 2.5), {}, r"\|AC peak\| \+ \|DC\|"),
        ((7, 6.0, -2.5), {}, r"\|AC peak\| \+ \|DC\|"),
        ((float("nan"), 1.0), {}, "frequency"),
        ((7, float("inf")), {}, "amplitude"),
    ],
)
def test_limits_refused_before_anything_is_sent(args: tuple, kwargs: dict, limit: str) -> None:
    res = ProtocolResource([])
    gen = DS345(res, **kwargs)
    for call in (gen.set_square, gen.set_sine):
        with pytest.raises(LimitError, match=limit):
            call(*args)
    assert res.sent == []


def test_limits_are_inclusive() -> None:
    pairs = [
        (b"OFFS?", b"0"),
        (b"FUNC 1", None),
        OK,
        (b"FREQ 30200000", None),
        OK,
        (b"AMPL 4VP", None),
        OK,
        (b"OFFS 3", None),
        OK,
        (b"FUNC 0", None),
        OK,
        (b"FREQ 0.000001", None),
        OK,
        (b"OFFS 0", None),
        OK,
        (b"AMPL 10VP", None),
        OK,
    ]
    with expected_protocol(pairs) as res:
        gen = DS345(res)
        gen.set_square(30.2e6, 4.0, 3.0)  # 2 + 3 = 5 V exactly
        gen.set_sine(1e-6, 10.0)  # from offset 3 V: 5 + 3 > 5 V, so OFFS 0 goes before AMPL 10VP


def test_constructor_sets_lf_terminations_and_sends_nothing() -> None:
    res = ProtocolResource([])
    DS345(res)
    assert (res.write_termination, res.read_termination, res.sent) == ("\n", "\n", [])
    with pytest.raises(ValueError, match="max_amplitude_vpp"):
        DS345(res, max_amplitude_vpp=20.0)


def test_reconnect_checks_identity_and_reapplies_settings() -> None:
    idn = b"StanfordResearchSystems,DS345,12345,1.04"
    first = ProtocolResource([(b"*IDN?", idn), *square_7hz_0v6()])
    second = ProtocolResource([(b"*IDN?", idn), (b"*CLS", None), *square_7hz_0v6()])
    gen = DS345(first, reopen=lambda: second)
    gen.identify()
    gen.set_square(7, 0.6)
    gen.reconnect()
    first.check_done()
    second.check_done()
    assert first.closed and not second.closed


def test_reconnect_refuses_another_unit_and_needs_a_factory() -> None:
    first = ProtocolResource([(b"*IDN?", b"StanfordResearchSystems,DS345,12345,1.04")])
    other = ProtocolResource([(b"*IDN?", b"StanfordResearchSystems,DS345,99999,1.04")])
    gen = DS345(first, reopen=lambda: other)
    gen.identify()
    with pytest.raises(InstrumentError, match="different unit"):
        gen.reconnect()
    with pytest.raises(InstrumentError, match="reopen"):
        DS345(ProtocolResource([])).reconnect()


def test_closed_driver_raises() -> None:
    gen = DS345(ProtocolResource([]))
    gen.close()
    gen.close()
    with pytest.raises(InstrumentError, match="closed"):
        gen.mute()
