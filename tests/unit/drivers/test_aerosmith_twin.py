"""The real 1291BR driver against its byte-level twin: in-process, over a real pty, over socket://.

Expected numbers come from the table model (sims/world.py docstring): after JOG r at acceleration a the rate
is r0 + sign(r - r0) min(a t, |r - r0|); the delivered rate is that times (1 + e), e = the scale error (60 ppm
by default); position is the integral of the delivered rate, wrapped to [0, 360) by PPO. PVE is written with
6 decimals and PPO with 4, so those are the read-back resolutions.
"""

from __future__ import annotations

import math
from collections.abc import Iterator

import pytest
import serial
from hypothesis import given, settings
from hypothesis import strategies as st

from drivers.aerosmith import Aerosmith1291BR
from qmg_lab.instruments import InstrumentError, InterlockError, LimitError
from sims.serial_twin import InProcessSerial, serve_pty, serve_socket
from sims.table_twin import RateTableTwin
from sims.world import World
from tests.support.twin_params import paper_world, paper_world_params, table_twin_settings

E_PPM = 60.0
SCALE = 1.0 + E_PPM * 1e-6
PVE_RES = 0.5e-6 + 1e-9
PPO_RES = 0.5e-4 + 1e-9


class Bench:
    def __init__(self, world: World, twin: RateTableTwin, table: Aerosmith1291BR) -> None:
        self.world, self.twin, self.table = world, twin, table

    def run(self, seconds: float, dt: float = 1e-3) -> None:
        self.world.advance(round(seconds / dt), dt)


@pytest.fixture(params=["inprocess", "pty", "socket"])
def bench(request: pytest.FixtureRequest) -> Iterator[Bench]:
    world = World(paper_world_params(table_rate_scale_error_ppm=E_PPM, table_rate_ripple_ppm=0.0))  # ripple: tests/sims
    twin = RateTableTwin(world, **table_twin_settings())
    stop = None
    if request.param == "inprocess":
        port = InProcessSerial(twin)
    elif request.param == "pty":
        path, stop = serve_pty(twin)
        port = serial.Serial(path, baudrate=9600, timeout=2.0)
    else:
        url, stop = serve_socket(twin)
        port = serial.serial_for_url(url, timeout=2.0)
    table = Aerosmith1291BR(port, max_rate_dps=100.0, max_accel_dps2=500.0)
    yield Bench(world, twin, table)
    table.close()
    if stop is not None:
        stop()


def test_identify(bench: Bench) -> None:
    assert bench.table.identify() == "Ideal Aerosmith 1291BR (3-letter mnemonic protocol; STA=10)"  # servo|at rate


def test_rate_ramp_then_scaled_rate_and_integrated_position(bench: Bench) -> None:
    a, r = 300.0, 5.0
    bench.table.set_rate(r, a)
    bench.run(0.005)  # inside the ramp (|r|/a = 16.7 ms): rate = a t
    reading = bench.table.read()
    assert reading.rate_dps == pytest.approx(a * 0.005 * SCALE, abs=PVE_RES)
    assert reading.status == 1 | 8  # moving, servo on, not yet at rate
    bench.run(0.005)
    assert bench.table.read().rate_dps == pytest.approx(a * 0.010 * SCALE, abs=PVE_RES)
    bench.run(0.990)  # t = 1 s, well past the ramp
    reading = bench.table.read()
    assert reading.rate_dps == pytest.approx(r * SCALE, abs=PVE_RES)
    assert (reading.rate_dps / r - 1.0) * 1e6 == pytest.approx(E_PPM, abs=0.2)
    assert reading.status == 1 | 2 | 8
    t_ramp = r / a
    angle = (0.5 * a * t_ramp**2 + r * (1.0 - t_ramp)) * SCALE
    # the world integrates with mid-step rates: exact except in the step holding the ramp's end (a dt^2 / 8)
    assert reading.position_deg == pytest.approx(angle, abs=PPO_RES + a * 1e-6 / 8)


def test_rate_reversal_ramps_through_zero(bench: Bench) -> None:
    bench.table.set_rate(5.0, 300.0)
    bench.run(0.1)
    bench.table.set_rate(-5.0, 200.0)
    bench.run(0.02)  # 5 - 200 * 0.02 = 1
    assert bench.table.read().rate_dps == pytest.approx(1.0 * SCALE, abs=PVE_RES)
    bench.run(0.04)  # 5 - 200 * 0.06 = -7 -> clipped at -5 (ramp ended at 0.05 s)
    assert bench.table.read().rate_dps == pytest.approx(-5.0 * SCALE, abs=PVE_RES)


def test_position_wraps_to_360(bench: Bench) -> None:
    bench.table.set_rate(100.0, 500.0)
    bench.run(4.0)
    angle = (0.5 * 500.0 * 0.2**2 + 100.0 * 3.8) * SCALE  # 390.0234
    assert bench.table.read().position_deg == pytest.approx(angle - 360.0, abs=PPO_RES + 500e-6 / 8)


def test_sinusoid(bench: Bench) -> None:
    bench.table.set_sinusoid(5.0, 2.0, 300.0)
    bench.run(0.125)  # a quarter period: 5 sin(pi/2)
    reading = bench.table.read()
    assert reading.rate_dps == pytest.approx(5.0 * SCALE, abs=PVE_RES)
    assert reading.status & 16
    bench.run(0.05)
    assert bench.table.read().rate_dps == pytest.approx(5.0 * math.sin(2 * math.pi * 2.0 * 0.175) * SCALE, abs=PVE_RES)


def test_stop_and_motion_complete(bench: Bench) -> None:
    bench.table.set_rate(10.0, 250.0)
    assert bench.table.motion_complete(0.01) is False
    bench.run(0.1)
    assert bench.table.motion_complete(0.01) is True  # |10.0006 - 10| <= 0.01
    assert bench.table.motion_complete(1e-4) is False  # the 60 ppm scale error is 6e-4 deg/s
    bench.table.stop()
    bench.run(0.02)  # 10 - 250 * 0.02 = 5
    assert bench.table.read().rate_dps == pytest.approx(5.0 * SCALE, abs=PVE_RES)
    bench.run(0.03)
    reading = bench.table.read()
    assert reading.rate_dps == 0.0
    assert reading.status == 2 | 8  # at rate (0), servo on, not moving


def test_interlock(bench: Bench) -> None:
    bench.table.set_rate(5.0, 300.0)
    bench.run(0.1)
    bench.world.trip_interlock()
    bench.run(0.1)
    reading = bench.table.read()
    assert reading.interlock and reading.rate_dps == 0.0
    with pytest.raises(InterlockError, match="E04"):
        bench.table.set_rate(5.0, 300.0)
    bench.table.safe_state()  # STO is accepted while tripped
    bench.world.reset_interlock()
    bench.table.set_rate(1.0, 300.0)


def test_limits_refused_before_the_twin_sees_anything(bench: Bench) -> None:
    seen = bench.twin.commands_seen
    with pytest.raises(LimitError, match="table rate"):
        bench.table.set_rate(150.0, 300.0)
    with pytest.raises(LimitError, match="table acceleration"):
        bench.table.set_rate(5.0, 501.0)
    with pytest.raises(LimitError, match="acceleration limit"):
        bench.table.set_sinusoid(10.0, 10.0, 500.0)
    assert bench.twin.commands_seen == seen
    assert bench.world.table.rate_command_dps == 0.0


def test_state_is_json_like(bench: Bench) -> None:
    bench.table.set_rate(2.0, 100.0)
    st = bench.table.state()
    assert st["rate_command_dps"] == 2.0 and st["accel_dps2"] == 100.0 and st["mode"] == "rate"
    assert st["status_bits"] == ["MOVING", "SERVO_ON"] or st["status_bits"] == ["SERVO_ON"]


# ------------------------------------------------------------------------------------------ faults, reconnect


def _inprocess() -> tuple[World, RateTableTwin, Aerosmith1291BR]:
    world = paper_world()
    twin = RateTableTwin(world, **table_twin_settings())
    return world, twin, Aerosmith1291BR(InProcessSerial(twin), max_rate_dps=100.0, max_accel_dps2=500.0)


@pytest.mark.parametrize(
    ("hook", "match"),
    [
        (lambda line, reply: b"", "timeout: no reply to 'PVE'"),
        (lambda line, reply: reply[:3], "truncated reply to 'PVE'"),
        (lambda line, reply: reply.replace(b".", b"#"), "garbled reply to 'PVE'"),
        (lambda line, reply: reply[:-2], "missing prompt after 'PVE'"),
    ],
)
def test_fault_hook_faults_reach_the_driver_as_instrument_errors(hook, match) -> None:
    _, twin, table = _inprocess()
    twin.fault_hook = lambda line, reply: hook(line, reply) if line == b"PVE\r" else reply
    with pytest.raises(InstrumentError, match=match):
        table.read()
    twin.fault_hook = None
    assert table.read().rate_dps == 0.0  # the link recovers on the next transaction


def test_closed_port_is_an_instrument_error() -> None:
    _, _, table = _inprocess()
    table.close()
    with pytest.raises(InstrumentError, match="cannot send 'PVE'"):
        table.read()


def test_reconnect_over_socket_keeps_the_motion() -> None:
    world = World(paper_world_params(table_rate_scale_error_ppm=E_PPM, table_rate_ripple_ppm=0.0))  # ripple: tests/sims
    twin = RateTableTwin(world, **table_twin_settings())
    url, stop = serve_socket(twin)
    try:
        table = Aerosmith1291BR(
            serial.serial_for_url(url, timeout=2.0),
            max_rate_dps=100.0,
            max_accel_dps2=500.0,
            port_factory=lambda: serial.serial_for_url(url, timeout=2.0),
        )
        table.set_rate(3.0, 300.0)
        world.advance(100, 1e-3)
        table.reconnect()
        assert table.read().rate_dps == pytest.approx(3.0 * SCALE, abs=PVE_RES)
        table.close()
    finally:
        stop()


# ------------------------------------------------------------------------------------------ driver <-> twin syntax


@settings(max_examples=80, deadline=None)
@given(
    rate=st.floats(-100.0, 100.0),
    accel=st.floats(1e-4, 500.0),
    amp=st.floats(1e-4, 100.0),
    headroom=st.floats(0.0, 1.2),
)
def test_every_command_the_driver_accepts_is_understood_by_the_twin(
    rate: float, accel: float, amp: float, headroom: float
) -> None:
    """Two independent implementations of the documented syntax agree. The table receives the values rounded
    to the documented formats (JOG/AMP/FRQ %.6f, ACL %.3f); the driver refuses exactly what the controller
    would refuse on those values (ACL must stay > 0, AMP * 2 pi * FRQ <= ACL), and whatever it sends is
    accepted and reaches the world as the rounded value."""
    freq = min(headroom * accel / (2.0 * math.pi * amp), 100.0)  # around the peak-acceleration boundary
    world, _, table = _inprocess()
    r_q, a_q, amp_q, f_q = float(f"{rate:.6f}"), float(f"{accel:.3f}"), float(f"{amp:.6f}"), float(f"{freq:.6f}")
    if a_q <= 0.0:
        with pytest.raises(LimitError, match="must be positive"):
            table.set_rate(rate, accel)
        return
    table.set_rate(rate, accel)
    assert (world.table.rate_command_dps, world.table.accel_dps2) == (r_q, a_q)
    if amp_q <= 0.0 or f_q <= 0.0 or amp_q * 2.0 * math.pi * f_q > a_q:
        with pytest.raises(LimitError):
            table.set_sinusoid(amp, freq, accel)
        assert world.table.mode == "rate"
        return
    table.set_sinusoid(amp, freq, accel)
    assert (world.table.mode, world.table.sine_amplitude_dps, world.table.sine_frequency_hz) == ("sine", amp_q, f_q)


def test_reconnect_over_pty_reopens_the_same_device() -> None:
    world = World(paper_world_params(table_rate_scale_error_ppm=E_PPM, table_rate_ripple_ppm=0.0))  # ripple: tests/sims
    path, stop = serve_pty(RateTableTwin(world, **table_twin_settings()))
    try:
        table = Aerosmith1291BR(
            serial.Serial(path, 9600, timeout=2.0),
            max_rate_dps=100.0,
            max_accel_dps2=500.0,
            port_factory=lambda: serial.Serial(path, 9600, timeout=2.0),
        )
        table.set_rate(-2.0, 100.0)
        world.advance(100, 1e-3)
        table.reconnect()
        assert table.read().rate_dps == pytest.approx(-2.0 * SCALE, abs=PVE_RES)
        table.close()
    finally:
        stop()
