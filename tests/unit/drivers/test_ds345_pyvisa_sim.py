"""DS345 driver against the strict pyvisa-sim model sims/ds345.yaml, through pyvisa's own ResourceManager."""

from __future__ import annotations

import importlib.resources
from collections.abc import Iterator

import pytest
import pyvisa

import drivers.ds345
from drivers.ds345 import DS345
from qmg_lab.instruments import InstrumentError

YAML = importlib.resources.files("sims") / "ds345.yaml"
RESOURCES = ("GPIB0::19::INSTR", "ASRL1::INSTR")


@pytest.fixture
def rm() -> Iterator[pyvisa.ResourceManager]:
    manager = pyvisa.ResourceManager(f"{YAML}@sim")
    yield manager
    manager.close()


@pytest.fixture(params=RESOURCES)
def generator(rm: pyvisa.ResourceManager, request: pytest.FixtureRequest) -> Iterator[DS345]:
    resource = rm.open_resource(request.param, timeout=200)
    gen = DS345(resource)
    yield gen
    gen.close()


def test_yaml_ships_with_sims_and_lists_gpib_and_serial(rm: pyvisa.ResourceManager) -> None:
    assert YAML.is_file()
    assert set(RESOURCES) <= set(rm.list_resources())


def test_serial_framing_is_8n2(rm: pyvisa.ResourceManager) -> None:
    resource = rm.open_resource("ASRL1::INSTR")
    DS345(resource)
    assert (resource.data_bits, resource.parity, resource.stop_bits) == (
        8,
        pyvisa.constants.Parity.none,
        pyvisa.constants.StopBits.two,
    )
    resource.close()


def test_identify(generator: DS345) -> None:
    assert generator.identify().split(",")[:2] == ["StanfordResearchSystems", "DS345"]


def test_settings_round_trip(generator: DS345) -> None:
    generator.set_square(7, 0.6)
    assert generator.state() == {
        "function": "square",
        "function_code": 1,
        "frequency_hz": 7.0,
        "amplitude": 0.6,
        "amplitude_unit": "VP",
        "amplitude_vpp": 0.6,
        "offset_v": 0.0,
    }
    generator.set_sine(1234.5, 2.5, -1.25)
    st = generator.state()
    assert (st["function"], st["frequency_hz"], st["amplitude_vpp"], st["offset_v"]) == ("sine", 1234.5, 2.5, -1.25)
    generator.set_square(1e-6, 10.0)  # the documented extremes, in the documented number format
    st = generator.state()
    assert (st["frequency_hz"], st["amplitude_vpp"], st["offset_v"]) == (1e-6, 10.0, 0.0)
    generator.set_phase(7199.999)
    assert float(generator.resource.query("PHSE?")) == 7199.999


def test_mute_is_amplitude_zero(generator: DS345) -> None:
    generator.set_square(7, 2.0)
    generator.mute()
    generator.safe_state()
    assert generator.state()["amplitude_vpp"] == 0.0


def test_out_of_range_past_the_driver_limit_surfaces_through_esr(
    generator: DS345, monkeypatch: pytest.MonkeyPatch
) -> None:
    generator.set_sine(1000.0, 1.0)
    monkeypatch.setattr(drivers.ds345, "FREQ_MAX_HZ", 1e9)  # relax the driver's own limit
    with pytest.raises(InstrumentError) as err:
        generator.set_sine(40e6, 1.0)
    # pyvisa-sim flags a refused value with the command-error bit 5 (32), see sims/ds345.yaml
    assert "'FREQ 40000000'" in str(err.value) and "bit 5" in str(err.value)
    assert generator.state()["frequency_hz"] == 1000.0  # the setting was refused


def test_unknown_command_sets_command_error_bit(generator: DS345) -> None:
    generator.read_esr()
    generator.resource.write("OUTX 1")  # the DS345 has no output switch
    assert generator.read_esr() == 32
    assert generator.read_esr() == 0  # *ESR? reads and clears
