"""DS345 twin: the message-level protocol, and the real driver making the World's dither through it.

Expected numbers: the DS345 protocol (docs/instruments.md) and the World's dither equation
v(t) = offset + (Vpp/2) w(f (t - t0) + phase/360), square w = +1 on the first half period, -1 on the second
(sims/world.py), sampled at mid-step.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import pyvisa.errors

import drivers.ds345
from drivers.ds345 import DS345
from qmg_lab.instruments import InstrumentError
from sims.ds345_twin import DS345Twin, VisaTwinResource
from sims.world import DITHER_SQUARE, World
from tests.support.twin_params import paper_world_params

DT = 1.0 / 1400.0  # 200 steps per 7 Hz period
# The protocol tests look at what the twin tells the World; the DS345's own timebase (offset, wander, command
# latency: tests/unit/sims/test_world.py) is set ideal here so that levels and periods land on the step grid.
IDEAL = paper_world_params(ds345_timebase_offset_ppm=0.0, ds345_timebase_wander_ppm=0.0, ds345_command_latency_s=0.0)


def bench() -> tuple[World, DS345Twin, VisaTwinResource]:
    world = World(IDEAL)
    twin = DS345Twin(world)
    res = twin.resource()
    res.write_termination = res.read_termination = "\n"
    res.query("*ESR?")  # clear the power-on bit
    return world, twin, res


# ---------------------------------------------------------------------------- driver -> twin -> World


def test_set_square_7hz_makes_the_world_dither() -> None:
    world = World(IDEAL)
    gen = DS345(DS345Twin(world).resource())
    gen.set_square(7.0, 0.6)
    v = world.advance(2800, DT).dither_v  # 2 s = 14 periods
    assert set(np.unique(np.round(v, 9))) == {-0.3, 0.3}  # levels +-Vpp/2 (step means, exact to rounding)
    # first half period high, then low: 100 steps each
    assert np.allclose(v[:100], 0.3, atol=1e-9) and np.allclose(v[100:200], -0.3, atol=1e-9)
    rising = np.flatnonzero((v[1:] > 0) & (v[:-1] < 0)) + 1
    assert np.all(np.diff(rising) == 200)  # period = 200 steps = 1/7 s
    assert v.mean() == pytest.approx(0.0, abs=1e-12)


def test_offset_and_mute() -> None:
    world = World(IDEAL)
    gen = DS345(DS345Twin(world).resource())
    gen.set_square(7.0, 2.0, 1.0)
    v = world.advance(200, DT).dither_v
    assert set(np.unique(np.round(v, 9))) == {0.0, 2.0}  # 1 V +- 1 V
    gen.set_square(7.0, 2.0)
    gen.mute()
    assert np.all(world.advance(400, DT).dither_v == 0.0)
    gen.safe_state()
    assert world.dither.amplitude_vpp == 0.0


def test_sine_follows_the_equation() -> None:
    world = World(IDEAL)
    gen = DS345(DS345Twin(world).resource())
    gen.set_sine(7.0, 2.0)
    v = world.advance(400, DT).dither_v
    t_mid = (np.arange(400) + 0.5) * DT
    # each step's mean of sin(2 pi f t): sin(2 pi f t_mid) sin(pi f dt) / (pi f dt)
    x = np.pi * 7.0 * DT
    np.testing.assert_allclose(v, np.sin(2 * np.pi * 7.0 * t_mid) * np.sin(x) / x, atol=1e-9)


def test_driver_identify_and_state_against_twin() -> None:
    world = World(IDEAL)
    gen = DS345(DS345Twin(world, serial="77777").resource())
    assert gen.identify() == "StanfordResearchSystems,DS345,77777,1.04"
    gen.set_square(7.0, 0.6)
    st = gen.state()
    assert (st["function"], st["frequency_hz"], st["amplitude"], st["amplitude_unit"], st["offset_v"]) == (
        "square",
        7.0,
        0.6,
        "VP",
        0.0,
    )


def test_reconnect_restores_the_dither_after_a_reset() -> None:
    world = World(IDEAL)
    twin = DS345Twin(world)
    gen = DS345(twin.resource(), reopen=twin.resource)
    gen.identify()
    gen.set_square(7.0, 0.6)
    other = twin.resource()
    other.write("*RST\n")  # the unit lost its settings (sine 1 kHz 1 Vpp)
    assert (world.dither.function, world.dither.amplitude_vpp) == (0, 1.0)
    gen.reconnect()
    d = world.dither
    assert (d.function, d.frequency_hz, d.amplitude_vpp, d.offset_v) == (DITHER_SQUARE, 7.0, 0.6, 0.0)


def test_dropped_garbled_and_truncated_replies_are_instrument_errors() -> None:
    world = World(IDEAL)
    twin = DS345Twin(world)
    gen = DS345(twin.resource(), reopen=twin.resource)
    twin.reply_hook = lambda framed: None  # dropped
    with pytest.raises(InstrumentError, match="no reply"):
        gen.mute()
    twin.reply_hook = lambda framed: b"0\x85x\n"  # garbled
    with pytest.raises(InstrumentError, match="garbled"):
        gen.mute()
    twin.reply_hook = lambda framed: framed[:-1]  # truncated: the LF never comes
    with pytest.raises(InstrumentError, match="no reply"):
        gen.mute()
    twin.reply_hook = None
    assert twin.esr & 4  # the timed-out reads left the query-error bit set
    gen.reconnect()  # fresh link, *IDN?, *CLS
    gen.mute()


def test_driver_surfaces_twin_range_error(monkeypatch: pytest.MonkeyPatch) -> None:
    world = World(IDEAL)
    gen = DS345(DS345Twin(world).resource())
    gen.set_square(7.0, 0.6)
    monkeypatch.setattr(drivers.ds345, "FREQ_MAX_HZ", 1e9)  # relax the driver: the twin must refuse
    with pytest.raises(InstrumentError, match=r"'FREQ 40000000'.*bit 4 \(execution/range error\)"):
        gen.set_square(40e6, 0.6)
    assert world.dither.frequency_hz == 7.0


def test_device_clear_flushes_a_partial_reply() -> None:
    _world, twin, res = bench()
    twin.reply_hook = lambda framed: framed[:-1]  # LF lost
    with pytest.raises(pyvisa.errors.VisaIOError):
        res.query("FREQ?")
    twin.reply_hook = None
    res.clear()
    assert res.query("FUNC?") == "0"  # not "1000" + "0"


# ---------------------------------------------------------------------------- message-level protocol


def test_power_on_bit_then_esr_reads_and_clears() -> None:
    world = World(IDEAL)
    res = DS345Twin(world).resource()
    res.write_termination = "\n"
    assert res.query("*ESR?") == "128"
    assert res.query("*ESR?") == "0"


def test_twin_creation_keeps_the_world_dither() -> None:
    world = World(IDEAL)
    world.set_dither(function=1, frequency_hz=7.0, amplitude_vpp=0.6)
    twin = DS345Twin(world)
    d = world.dither
    assert (d.function, d.frequency_hz, d.amplitude_vpp) == (1, 7.0, 0.6)
    assert twin.settings.frequency_hz == 7.0


def test_several_commands_per_line() -> None:
    world, _twin, res = bench()
    res.write("FUNC 1;FREQ 7;AMPL 2.5VP;OFFS 0")
    assert res.query("*ESR?") == "0"
    d = world.dither
    assert (d.function, d.frequency_hz, d.amplitude_vpp, d.offset_v) == (1, 7.0, 2.5, 0.0)
    res.write("FUNC?;FREQ?;AMPL?;OFFS?")
    assert [res.read() for _ in range(4)] == ["1", "7", "2.5VP", "0"]


@pytest.mark.parametrize(
    ("message", "esr"),
    [
        ("OUTX 1", 32),  # no output switch: command error
        ("FREQ", 32),  # missing argument
        ("FREQ 7 Hz", 32),  # malformed number
        ("AMPL 1", 32),  # unit required
        ("FREQ 30300000", 16),  # above 30.2 MHz
        ("FREQ 0", 16),  # below 1 uHz
        ("AMPL 0.005VP", 16),  # between mute and 10 mVpp
        ("AMPL 10.5VP", 16),
        ("OFFS 5.5", 16),
        ("PHSE 7200", 16),
        ("FUNC 6", 16),
        ("INVT 2", 16),
        ("*IDN", 32),
        ("PCLR?", 32),
    ],
)
def test_errors_set_the_documented_bits_and_leave_state(message: str, esr: int) -> None:
    world, _twin, res = bench()
    before = (world.dither.frequency_hz, world.dither.amplitude_vpp, world.dither.offset_v)
    res.write(message)
    assert res.query("*ESR?") == str(esr)
    assert (world.dither.frequency_hz, world.dither.amplitude_vpp, world.dither.offset_v) == before


def test_ac_peak_plus_dc_rule_both_ways() -> None:
    world, _twin, res = bench()
    res.write("AMPL 4VP;OFFS 3")  # 2 + 3 = 5 V: allowed
    assert res.query("*ESR?") == "0"
    res.write("OFFS 3.5")  # 2 + 3.5 > 5 V
    assert res.query("*ESR?") == "16"
    res.write("AMPL 6VP")  # 3 + 3 > 5 V
    assert res.query("*ESR?") == "16"
    assert (world.dither.amplitude_vpp, world.dither.offset_v) == (4.0, 3.0)


def test_mute_is_accepted_exactly() -> None:
    world, _twin, res = bench()
    res.write("AMPL 0VP")
    assert res.query("*ESR?") == "0" and res.query("AMPL?") == "0VP"
    assert world.dither.amplitude_vpp == 0.0


def test_amplitude_units() -> None:
    world, _twin, res = bench()
    res.write("FUNC 0;AMPL 1VR")  # sine: Vpp = 2 sqrt 2 Vrms
    assert world.dither.amplitude_vpp == pytest.approx(2 * math.sqrt(2), rel=1e-12)
    assert res.query("AMPL?") == "1VR"
    assert float(res.query("AMPL? VP")[:-2]) == pytest.approx(2 * math.sqrt(2), rel=1e-6)
    res.write("AMPL 10DB")  # 10 mW into 50 ohm: Vrms = sqrt(0.5), sine Vpp = 2
    assert world.dither.amplitude_vpp == pytest.approx(2.0, rel=1e-12)
    res.write("FUNC 1;AMPL 1VR")  # square: Vpp = 2 Vrms
    assert world.dither.amplitude_vpp == pytest.approx(2.0, rel=1e-12)
    assert res.query("*ESR?") == "0"


def test_triangle_frequency_limit() -> None:
    world, _twin, res = bench()
    res.write("FREQ 200000")
    res.write("FUNC 2")  # triangle only to 100 kHz
    assert res.query("*ESR?") == "16" and world.dither.function == 0
    res.write("FREQ 100000;FUNC 2")
    assert res.query("*ESR?") == "0" and world.dither.function == 2


def test_invert_and_phase() -> None:
    world, _twin, res = bench()
    res.write("FUNC 1;FREQ 7;AMPL 2VP;INVT 1")
    v = world.advance(200, DT).dither_v
    assert np.allclose(v[:100], -1.0, atol=1e-9) and np.allclose(v[100:], 1.0, atol=1e-9)  # inverted: low first
    res.write("INVT 0;PHSE 90")
    assert world.dither.phase_deg == 90.0
    res.write("PCLR")  # present phase becomes 0: output unchanged
    assert res.query("PHSE?") == "0" and world.dither.phase_deg == 90.0
    res.write("PHSE 90")
    assert world.dither.phase_deg == 180.0


def test_reset_and_lower_case() -> None:
    world, _twin, res = bench()
    res.write("func 1;freq 7;ampl 0.6vp")
    res.write("*RST")
    d = world.dither
    assert (d.function, d.frequency_hz, d.amplitude_vpp, d.offset_v) == (0, 1000.0, 1.0, 0.0)


def test_empty_read_times_out_and_sets_query_error() -> None:
    _world, _twin, res = bench()
    with pytest.raises(pyvisa.errors.VisaIOError) as err:
        res.read()
    assert err.value.error_code == pyvisa.constants.StatusCode.error_timeout
    assert res.query("*ESR?") == "4"


def test_status_byte() -> None:
    _world, _twin, res = bench()
    assert res.query("*STB?") == "128"  # idle, nothing pending
    res.write("*ESE 16;FREQ 0")  # execution error, enabled in ESE -> ESB
    assert res.query("*STB?") == str(128 | 32)
    assert res.query("*ESR? 4") == "1" and res.query("*ESR?") == "0"


def test_closed_resource_raises() -> None:
    _world, _twin, res = bench()
    res.close()
    with pytest.raises(pyvisa.errors.InvalidSession):
        res.write("*IDN?")
