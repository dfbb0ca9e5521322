"""The lock-in wiring is declared once: qmg_lab/config/schema.py LockInSection holds its defaults, bounds and the
pairs that must differ; the driver (drivers/hf2_nodes.py `LockInWiring`) takes that validated section and checks
only what the instrument reports.

The bounds below are the HF2LI's channels (HF2 user manual: two signal inputs and outputs, four AuxOuts, two
AuxIns, eight output mixer channels with the MF option, six oscillators); a value outside them, or two signals on
one channel, is refused by the configuration with the key named, before any driver exists.
"""

from __future__ import annotations

import inspect

import pytest

from drivers import hf2_nodes
from qmg_lab.config.schema import ConfigError, LockInSection, parse_config


@pytest.mark.parametrize(
    ("toml", "named"),
    [
        ("drive_sigin = 2", "lockin.drive_sigin"),
        ("sense_sigin = -1", "lockin.sense_sigin"),
        ("drive_sigout = 2", "lockin.drive_sigout"),
        ("forcer_sigout = 2", "lockin.forcer_sigout"),
        ("rate_auxout = 4", "lockin.rate_auxout"),
        ("quadrature_auxout = 4", "lockin.quadrature_auxout"),
        ("rate_auxin = 2", "lockin.rate_auxin"),
        ("dither_auxin = 2", "lockin.dither_auxin"),
        ("rate_auxin = 1.5", "lockin.rate_auxin"),
        ("drive_mixer_channel = 8", "lockin.drive_mixer_channel"),
        ("forcer_mixer_channel = -1", "lockin.forcer_mixer_channel"),
        ("fixed_channel_oscillators = [0, 6]", "lockin.fixed_channel_oscillators"),
        ("fixed_channel_oscillators = [0]", "lockin.fixed_channel_oscillators"),
        ("fixed_channel_oscillators = [0, 1, 2]", "lockin.fixed_channel_oscillators"),
        ("forcer_carrier_amplitude = 0.0", "lockin.forcer_carrier_amplitude"),
        ("forcer_carrier_amplitude = 1.01", "lockin.forcer_carrier_amplitude"),
        ("drive_sigin = 1\nsense_sigin = 1", "lockin.drive_sigin and lockin.sense_sigin"),
        ("rate_auxin = 0\ndither_auxin = 0", "lockin.rate_auxin and lockin.dither_auxin"),
        ("rate_auxout = 2\nquadrature_auxout = 2", "lockin.rate_auxout and lockin.quadrature_auxout"),
    ],
)
def test_the_configuration_refuses_an_impossible_wiring_naming_the_key(toml: str, named: str) -> None:
    with pytest.raises(ConfigError) as err:
        parse_config(f"[lockin]\n{toml}\n")
    assert named in str(err.value)


def test_the_driver_reads_only_fields_the_schema_declares_and_declares_none_itself() -> None:
    wiring = {n for n, _ in inspect.getmembers(hf2_nodes.LockInWiring) if isinstance(_, property)}
    assert wiring, "LockInWiring lists the fields the driver reads"
    assert wiring <= set(LockInSection.model_fields), wiring - set(LockInSection.model_fields)
    section = LockInSection()
    for name in wiring:  # each has its default in the schema (a required field would have none)
        assert not LockInSection.model_fields[name].is_required(), name
        assert hasattr(section, name)
    assert not hasattr(hf2_nodes, "check_wiring")  # the driver re-checks no wiring the schema validated


def test_the_driver_takes_the_validated_sections_values() -> None:
    """Non-default wiring flows from the configuration to the driver's mixer layout unchanged (no driver default
    in between): without MF, output 2 carries channel 7, and a configured override wins."""
    lk = parse_config("[lockin]\ndrive_sigout = 1\nforcer_sigout = 0\nfixed_channel_oscillators = [2, 3]\n").lockin
    layout = hf2_nodes.mixer_layout(("PLL", "PID"), lk)
    assert (layout.drive, layout.forcer) == (7, 6)
    assert hf2_nodes.fixed_channel_oscillators(lk) == {6: 2, 7: 3}
    lk = parse_config("[lockin]\nforcer_mixer_channel = 5\n").lockin
    assert hf2_nodes.mixer_layout(("MF", "PLL", "PID"), lk).forcer == 5
