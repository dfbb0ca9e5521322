"""1291BR first contact: the servo command ([table] servo_enable_command, default "SRV") before motion.

Public Aerosmith code enables the servo (SRV) before it commands motion. The driver sends the configured command
once per connection, before the first JOG or SGO, and again after a reconnect; it answers the prompt only
(docs/instruments.md, 1291BR section). The twin refuses JOG/SGO with E06 while its servo is off.
"""

from __future__ import annotations

import pytest

from drivers.aerosmith import Aerosmith1291BR
from qmg_lab.config.schema import parse_config
from qmg_lab.instruments import InstrumentError
from qmg_lab.station import connect_instrument
from sims.serial_twin import InProcessSerial
from sims.table_twin import RateTableTwin
from tests.support.protocol_serial import ProtocolPort, expected_protocol
from tests.support.twin_params import paper_world

P = b">\r"
SERVO_ON_BIT = 8  # STA bit 3 (drivers/aerosmith_commands.py, TableStatus.SERVO_ON)


def table(command: str | None):  # type: ignore[no-untyped-def]
    def build(port: ProtocolPort) -> Aerosmith1291BR:
        return Aerosmith1291BR(port, max_rate_dps=100.0, max_accel_dps2=500.0, servo_enable_command=command)

    return build


def rate_5() -> list[tuple[bytes, bytes | None]]:
    return [(b"ACL100.000\r\n", P), (b"JOG5.000000\r\n", P), (b"STA\r\n", b"9\r" + P)]


def test_servo_command_once_before_the_first_motion() -> None:
    pairs = [(b"SRV\r\n", P), *rate_5(), *rate_5()]
    pairs += [(b"ACL100.000\r\n", P), (b"AMP1.000000\r\n", P), (b"FRQ1.000000\r\n", P), (b"SGO\r\n", P)]
    pairs += [(b"STA\r\n", b"25\r" + P)]
    with expected_protocol(table("SRV"), pairs) as t:
        t.set_rate(5.0, 100.0)
        t.set_rate(5.0, 100.0)
        t.set_sinusoid(1.0, 1.0, 100.0)


def test_servo_command_as_configured_and_again_after_a_reconnect() -> None:
    second = ProtocolPort([(b"STA\r\n", b"8\r" + P), (b"SRV1\r\n", P), *rate_5()])
    first = ProtocolPort([(b"SRV1\r\n", P), *rate_5()])
    t = Aerosmith1291BR(
        first, max_rate_dps=100.0, max_accel_dps2=500.0, servo_enable_command="SRV1", port_factory=lambda: second
    )
    t.set_rate(5.0, 100.0)
    t.reconnect()
    t.set_rate(5.0, 100.0)
    first.assert_complete()
    second.assert_complete()


def test_no_servo_command_when_not_configured_and_none_for_stop() -> None:
    with expected_protocol(table(None), [*rate_5(), (b"STO\r\n", P), (b"STA\r\n", b"8\r" + P)]) as t:
        t.set_rate(5.0, 100.0)
        t.stop()
    with expected_protocol(table("SRV"), [(b"STO\r\n", P)]) as t:
        t.safe_state()  # stopping never waits for a servo command


def test_a_refused_servo_command_names_it() -> None:
    port = ProtocolPort([(b"SRV\r\n", b"E01 UNKNOWN COMMAND\r" + P)])
    with pytest.raises(InstrumentError, match=r"'SRV' refused: E01 UNKNOWN COMMAND \(unknown command\)"):
        table("SRV")(port).set_rate(5.0, 100.0)
    port.assert_complete()


def test_servo_command_must_be_one_printable_word() -> None:
    with pytest.raises(ValueError, match="servo_enable_command"):
        table("SRV 1")(ProtocolPort([]))


def test_twin_refuses_motion_until_the_servo_is_on() -> None:
    twin = RateTableTwin(paper_world(), servo_on=False)
    assert twin.respond(b"STA\r") == b"2\r" + P  # at rate (0), servo off
    assert twin.respond(b"JOG5\r") == b"E06 SERVO OFF\r" + P
    assert twin.respond(b"SRV\r") == P
    assert twin.respond(b"STA\r") == b"10\r" + P
    assert twin.respond(b"SRV0\r") == P and twin.respond(b"SGO\r").startswith(b"E0")
    assert twin.respond(b"SRV2\r") == b"E02 BAD ARGUMENT\r" + P


def test_driver_on_a_twin_whose_servo_is_off() -> None:
    twin = RateTableTwin(paper_world(), servo_on=False)
    t = Aerosmith1291BR(InProcessSerial(twin), max_rate_dps=100.0, max_accel_dps2=500.0, servo_enable_command="SRV")
    t.set_rate(5.0, 300.0)
    assert t.read().status & SERVO_ON_BIT
    bare = Aerosmith1291BR(
        InProcessSerial(RateTableTwin(paper_world(), servo_on=False)), max_rate_dps=100.0, max_accel_dps2=500.0
    )
    with pytest.raises(InstrumentError, match=r"'JOG5\.000000' refused: E06 SERVO OFF \(servo off"):
        bare.set_rate(5.0, 300.0)


@pytest.mark.parametrize(("command", "moves"), [("SRV", True), ("", False)])
def test_station_sends_the_configured_servo_command(command: str, moves: bool) -> None:
    cfg = parse_config(
        f'[table]\nsim = true\nservo_enable_command = "{command}"\n[sim]\ntable_servo_on_at_start = false\n'
    )
    conn = connect_instrument(cfg, "table")
    try:
        if moves:
            conn.instrument.set_rate(5.0, 300.0)
            assert conn.instrument.state()["rate_command_dps"] == 5.0
        else:
            with pytest.raises(InstrumentError, match="E06 SERVO OFF"):
                conn.instrument.set_rate(5.0, 300.0)
    finally:
        conn.close()
