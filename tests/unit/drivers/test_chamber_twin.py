"""The real EC1x driver against its byte-level twin: in-process, over a real pty, over socket://.

Expected numbers from the chamber model (sims/world.py): the controller setpoint ramps at the commanded rate
k (deg C/min), s(t) = s0 + k t / 60 until the target; the air follows with a first-order lag tau:
for the ramp from rest, air(t) = s0 + (k/60) (t - tau (1 - exp(-t/tau))); after the ramp ends at T, the air
relaxes as target - (target - air(T)) exp(-(t - T)/tau). The world holds the setpoint over each step (ZOH), so
the sampled air lags the continuous solution by at most (k/60) dt; C1?/SET? have 2 decimals.
"""

from __future__ import annotations

import math
from collections.abc import Iterator

import pytest
import serial

from drivers.chamber import SunEC1xChamber
from qmg_lab.instruments import LimitError
from sims.chamber_twin import ChamberTwin
from sims.serial_twin import InProcessSerial, serve_pty, serve_socket
from sims.world import World
from tests.support.twin_params import chamber_twin_settings, paper_world_params

TAU = 60.0
DT = 0.1
RES = 0.005 + 1e-9


class Bench:
    def __init__(self, world: World, twin: ChamberTwin, chamber: SunEC1xChamber) -> None:
        self.world, self.twin, self.chamber = world, twin, chamber

    def run_to(self, t_s: float) -> None:
        n = round((t_s - self.world.t) / DT)
        if n > 0:
            self.world.advance(n, DT)


@pytest.fixture(params=["inprocess", "pty", "socket"])
def bench(request: pytest.FixtureRequest) -> Iterator[Bench]:
    world = World(paper_world_params(chamber_time_constant_s=TAU, initial_temperature_c=25.0))
    twin = ChamberTwin(world, **chamber_twin_settings(status_layout="flags16"))
    stop = None
    if request.param == "inprocess":
        port = InProcessSerial(twin)
    elif request.param == "pty":
        path, stop = serve_pty(twin)
        port = serial.Serial(path, baudrate=9600, timeout=2.0)
    else:
        url, stop = serve_socket(twin)
        port = serial.serial_for_url(url, timeout=2.0)
    chamber = SunEC1xChamber(port, min_c=-40.0, max_c=85.0, max_ramp_c_per_min=5.0, safe_setpoint_c=25.0)
    yield Bench(world, twin, chamber)
    chamber.close()
    if stop is not None:
        stop()


def air_during_ramp(s0: float, k_c_per_min: float, t: float) -> float:
    return s0 + k_c_per_min / 60.0 * (t - TAU * (1.0 - math.exp(-t / TAU)))


def test_setpoint_ramps_at_the_commanded_rate_and_air_follows_first_order(bench: Bench) -> None:
    k = 2.0
    bench.chamber.set_setpoint(30.0, k)
    bench.run_to(60.0)
    reading = bench.chamber.read()
    assert reading.setpoint_c == pytest.approx(25.0 + k * 60.0 / 60.0, abs=RES)  # 27.00
    assert reading.temperature_c == pytest.approx(air_during_ramp(25.0, k, 60.0), abs=RES + k / 60 * DT)  # 25.736
    assert reading.ramping is True
    bench.run_to(120.0)
    assert bench.chamber.read().setpoint_c == pytest.approx(29.0, abs=RES)
    bench.run_to(210.0)  # ramp ended at T = 150 s
    reading = bench.chamber.read()
    air_t = air_during_ramp(25.0, k, 150.0)
    expected = 30.0 - (30.0 - air_t) * math.exp(-(210.0 - 150.0) / TAU)  # 29.325
    assert reading.setpoint_c == pytest.approx(30.0, abs=RES)
    assert reading.temperature_c == pytest.approx(expected, abs=RES + k / 60 * DT)
    assert reading.ramping is False
    assert bench.chamber.ramp_rate() == k


def test_safe_state_ramps_back_to_the_safe_setpoint(bench: Bench) -> None:
    bench.chamber.set_setpoint(35.0, 5.0)
    bench.run_to(120.0)  # 35 reached at 120 s
    bench.chamber.safe_state()
    bench.run_to(180.0)  # 35 - 5 * 1 = 30
    assert bench.chamber.read().setpoint_c == pytest.approx(30.0, abs=RES)
    assert bench.chamber.power_on() is True


def test_off_drifts_to_ambient_and_remembers_the_setpoint(bench: Bench) -> None:
    bench.chamber.set_setpoint(26.0, 5.0)
    bench.run_to(600.0)
    assert bench.chamber.read().temperature_c == pytest.approx(26.0, abs=0.01)
    bench.chamber.power_off()
    assert bench.chamber.power_on() is False
    reading = bench.chamber.read()
    assert reading.setpoint_c == pytest.approx(26.0, abs=RES) and reading.ramping is False
    bench.run_to(1200.0)
    assert bench.chamber.read().temperature_c == pytest.approx(25.0, abs=0.01)
    assert bench.world.chamber.heater_on is False


def test_limits_refused_before_the_twin_sees_anything(bench: Bench) -> None:
    seen = bench.twin.commands_seen
    with pytest.raises(LimitError, match="chamber setpoint"):
        bench.chamber.set_setpoint(86.0, 1.0)
    with pytest.raises(LimitError, match="chamber ramp"):
        bench.chamber.set_setpoint(30.0, 5.5)
    assert bench.twin.commands_seen == seen
    assert bench.world.chamber.target_c == 25.0


def test_write_limits_then_identify_and_state(bench: Bench) -> None:
    bench.chamber.write_limits()
    assert (bench.twin.ltl_c, bench.twin.utl_c) == (-40.0, 85.0)
    assert bench.chamber.identify() == "Sun Electronic Systems EC1x (ASCII protocol; STATUS=YYYNNNNNNNNNNNNN)"
    st = bench.chamber.state()
    assert st["temperature_c"] == 25.0 and st["setpoint_c"] == 25.0 and st["ramping"] is False
