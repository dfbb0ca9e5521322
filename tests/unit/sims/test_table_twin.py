"""The 1291BR twin at the byte level, and the serial plumbing (in-process port, pty, loopback socket).

Expected bytes follow the documented protocol (docs/instruments.md): prompt b">\\r"; value line + CR + prompt;
refusals "E<nn> <text>" CR + prompt; STA bits 1 moving, 2 at rate, 4 interlock, 8 servo on, 16 sine.
"""

from __future__ import annotations

import os
import select

import pytest
import serial

from sims.serial_twin import InProcessSerial, LineFramer, serve_pty, serve_socket
from sims.table_twin import RateTableTwin
from sims.world import World
from tests.support.twin_params import paper_world_params, table_twin_settings

P = b">\r"


@pytest.fixture
def twin() -> RateTableTwin:
    return RateTableTwin(
        World(paper_world_params(table_rate_scale_error_ppm=100.0, table_rate_ripple_ppm=0.0)),
        max_rate_dps=500.0,
        max_accel_dps2=800.0,
        **table_twin_settings(),
    )


def test_settings_answer_the_prompt_and_reach_the_world(twin: RateTableTwin) -> None:
    assert twin.respond(b"ACL250.000\r") == P
    assert twin.respond(b"JOG-7.5\r") == P
    tab = twin.world.table
    assert (tab.mode, tab.rate_command_dps, tab.accel_dps2) == ("rate", -7.5, 250.0)
    twin.world.advance(100, 1e-3)  # 0.1 s > 7.5 / 250 = 0.03 s
    assert twin.respond(b"PVE\r") == b"-7.500750\r" + P  # -7.5 * (1 + 100 ppm)
    assert twin.respond(b"STA\r") == b"11\r" + P  # moving | at rate | servo on
    assert twin.respond(b"STO\r") == P
    assert tab.rate_command_dps == 0.0 and tab.accel_dps2 == 250.0


@pytest.mark.parametrize(
    ("line", "reply"),
    [
        (b"XYZ\r", b"E01 UNKNOWN COMMAND\r" + P),
        (b"jog5\r", b"E01 UNKNOWN COMMAND\r" + P),
        (b"\xff\xfe\r", b"E01 UNKNOWN COMMAND\r" + P),
        (b"JOG\r", b"E02 BAD ARGUMENT\r" + P),
        (b"JOG5,0\r", b"E02 BAD ARGUMENT\r" + P),
        (b"JOG 5\r", b"E02 BAD ARGUMENT\r" + P),
        (b"JOGnan\r", b"E02 BAD ARGUMENT\r" + P),
        (b"STO1\r", b"E02 BAD ARGUMENT\r" + P),
        (b"JOG500.1\r", b"E03 RANGE\r" + P),
        (b"ACL0\r", b"E03 RANGE\r" + P),
        (b"ACL800.5\r", b"E03 RANGE\r" + P),
        (b"FRQ0\r", b"E03 RANGE\r" + P),
        (b"MCO-1\r", b"E03 RANGE\r" + P),
        (b"JOG5", b"E05 FRAMING\r" + P),
    ],
)
def test_refusals(twin: RateTableTwin, line: bytes, reply: bytes) -> None:
    assert twin.respond(line) == reply
    assert twin.world.table.rate_command_dps == 0.0


def test_sine_needs_acceleration_headroom(twin: RateTableTwin) -> None:
    assert twin.respond(b"ACL100\r") == P
    assert twin.respond(b"AMP10\r") == P
    assert twin.respond(b"FRQ2\r") == P
    assert twin.respond(b"SGO\r") == b"E03 RANGE\r" + P  # 10 * 2 pi * 2 = 125.7 > 100
    assert twin.respond(b"FRQ1.5\r") == P
    assert twin.respond(b"SGO\r") == P  # 94.2 <= 100
    tab = twin.world.table
    assert (tab.mode, tab.sine_amplitude_dps, tab.sine_frequency_hz) == ("sine", 10.0, 1.5)
    twin.world.advance(1, 1.0 / 6.0)  # a quarter period of 1.5 Hz
    assert twin.respond(b"PVE\r") == b"10.001000\r" + P
    assert twin.respond(b"STA\r") == b"25\r" + P  # moving | servo | sine
    assert twin.respond(b"MCO1\r") == b"0\r" + P


def test_interlock_refuses_motion_but_accepts_stop(twin: RateTableTwin) -> None:
    twin.world.trip_interlock()
    assert twin.respond(b"JOG5\r") == b"E04 INTERLOCK\r" + P
    assert twin.respond(b"ACL300\r") == P
    assert twin.respond(b"AMP1\r") == P and twin.respond(b"FRQ1\r") == P
    assert twin.respond(b"SGO\r") == b"E04 INTERLOCK\r" + P
    assert twin.respond(b"STO\r") == P
    assert twin.respond(b"STA\r") == b"14\r" + P  # at rate (0) | interlock | servo


def test_position_wraps(twin: RateTableTwin) -> None:
    twin.world.table.angle_deg = 725.5
    assert twin.respond(b"PPO\r") == b"5.5000\r" + P
    twin.world.table.angle_deg = -1.0
    assert twin.respond(b"PPO\r") == b"359.0000\r" + P
    twin.world.table.angle_deg = -1e-9  # would print as 360.0000
    assert twin.respond(b"PPO\r") == b"0.0000\r" + P


def test_motion_complete_uses_the_delivered_rate(twin: RateTableTwin) -> None:
    twin.respond(b"ACL500\r")
    twin.respond(b"JOG10\r")
    twin.world.advance(10, 0.01)
    assert twin.respond(b"MCO0.001\r") == b"1\r" + P  # |10.001 - 10| = 0.001
    assert twin.respond(b"MCO0.0009\r") == b"0\r" + P


def test_fault_hook_sees_the_line_and_can_drop_the_reply(twin: RateTableTwin) -> None:
    seen: list[bytes] = []

    def hook(line: bytes, reply: bytes) -> bytes:
        seen.append(line)
        return b""

    twin.fault_hook = hook
    assert twin.respond(b"STA\r") == b""
    assert seen == [b"STA\r"]


# ------------------------------------------------------------------------------------------ plumbing


def test_line_framer_splits_and_flushes_overlong_lines() -> None:
    fr = LineFramer()
    assert fr.feed(b"ST") == []
    assert fr.feed(b"A\r\nPVE\r\nPP") == [b"STA\r", b"PVE\r"]
    assert fr.feed(b"O\r\n") == [b"PPO\r"]
    assert fr.feed(b"x" * 1025) == [b"x" * 1025]
    assert fr.feed(b"\n") == [b""]


def test_inprocess_port_behaves_like_pyserial(twin: RateTableTwin) -> None:
    port = InProcessSerial(twin)
    assert port.is_open and port.in_waiting == 0
    port.write(b"STA\r\nPV")  # one whole command and half of the next
    assert port.in_waiting == len(b"10\r" + P)
    port.write(b"E\r\n")
    assert port.read_until(b"\r") == b"10\r"
    assert port.read(2) == P
    assert port.read_until(b"\r", 3) == b"0.0"  # size limit
    assert port.readline() == b"00000\r>\r"  # no LF: everything there is, at once (a timed-out read)
    assert port.read() == b""
    port.write(b"STA\r\n")
    port.reset_input_buffer()
    assert port.in_waiting == 0
    port.close()
    with pytest.raises(serial.SerialException):
        port.write(b"STA\r\n")
    port.open()
    port.write(b"STA\r\n")
    assert port.read_until(b">\r") == b"10\r" + P


def test_pty_serves_a_real_tty(twin: RateTableTwin) -> None:
    path, stop = serve_pty(twin)
    try:
        with serial.Serial(path, 9600, timeout=2.0) as port:
            assert os.isatty(port.fileno())
            port.write(b"JOG1.5\r\nSTA\r\n")
            assert port.read_until(P) == P
            assert port.read_until(P) == b"8\r" + P  # no time has passed: at rest, not at rate, servo on
    finally:
        stop()
    thread = stop.__self__._thread
    assert not thread.is_alive()


def test_socket_serves_several_connections_and_stops(twin: RateTableTwin) -> None:
    url, stop = serve_socket(twin)
    try:
        assert url.startswith("socket://127.0.0.1:")
        a = serial.serial_for_url(url, timeout=2.0)
        b = serial.serial_for_url(url, timeout=2.0)
        a.write(b"ST")
        b.write(b"PVE\r\n")
        assert b.read_until(P) == b"0.000000\r" + P
        a.write(b"A\r\n")
        assert a.read_until(P) == b"10\r" + P
        a.close()
        b.write(b"STA\r\n")
        assert b.read_until(P) == b"10\r" + P
        b.close()
    finally:
        stop()
    assert not stop.__self__._thread.is_alive()
    stop()  # idempotent


def test_socket_refuses_non_loopback_hosts(twin: RateTableTwin) -> None:
    with pytest.raises(ValueError, match="loopback"):
        serve_socket(twin, host="192.0.2.1")  # checked before any socket is bound


def test_pty_master_sees_nothing_unrequested(twin: RateTableTwin) -> None:
    path, stop = serve_pty(twin)
    try:
        with serial.Serial(path, 9600, timeout=2.0) as port:
            port.write(b"STA\r\n")
            assert port.read_until(P) == b"10\r" + P
            r, _, _ = select.select([port.fileno()], [], [], 0)
            assert r == []  # no echo, no extra bytes
    finally:
        stop()
