"""The serial ports of the table and the chamber default per OS, from one table (config/schema.py
SERIAL_PORT_DEFAULTS): COM ports on Windows (sys.platform "win32"), /dev/ttyUSB<n> elsewhere."""

from __future__ import annotations

import sys

import pytest

from qmg_lab.config.schema import SERIAL_PORT_DEFAULTS, Config, default_serial_port, parse_config


@pytest.mark.parametrize(
    ("platform", "table", "chamber"),
    [
        ("win32", "COM3", "COM4"),
        ("linux", "/dev/ttyUSB0", "/dev/ttyUSB1"),
        ("darwin", "/dev/ttyUSB0", "/dev/ttyUSB1"),
    ],
)
def test_each_os_has_its_own_port_names(platform: str, table: str, chamber: str) -> None:
    assert (default_serial_port("table", platform), default_serial_port("chamber", platform)) == (table, chamber)


def test_a_configuration_without_ports_takes_this_os_defaults() -> None:
    cfg = parse_config('[campaign]\nname = "no ports"\n')
    assert cfg.table.port == default_serial_port("table", sys.platform)
    assert cfg.chamber.port == default_serial_port("chamber", sys.platform)
    assert Config().table.port != Config().chamber.port  # two instruments, two ports


def test_the_two_instruments_never_share_a_default_port() -> None:
    for ports in SERIAL_PORT_DEFAULTS.values():
        assert ports["table"] != ports["chamber"]


def test_a_port_given_in_the_file_wins() -> None:
    assert parse_config('[table]\nport = "COM7"\n').table.port == "COM7"
