"""Derived configurations: set by dotted key, keep the user's text, validate as any configuration."""

from __future__ import annotations

import tomllib

import pytest

from qmg_lab.config.edit import with_values
from qmg_lab.config.schema import parse_config

TEXT = """# bench 3, QMG serial 12
[campaign]
kind = "temperature_sweep"   # the paper's sweep
name = "night run"

[plan]
dwell_s = 20.0
"""


def test_a_value_is_replaced_and_comments_and_other_keys_stay() -> None:
    out = with_values(TEXT, {"campaign.kind": "linearity"})
    assert tomllib.loads(out)["campaign"] == {"kind": "linearity", "name": "night run"}
    assert "# bench 3, QMG serial 12" in out and "dwell_s = 20.0" in out
    assert parse_config(out).campaign.kind == "linearity"


def test_a_missing_section_is_created() -> None:
    out = with_values("[plan]\ndwell_s = 20.0\n", {"campaign.kind": "bandwidth", "dither.frequency_hz": 8.6})
    data = tomllib.loads(out)
    assert data["campaign"]["kind"] == "bandwidth" and data["dither"]["frequency_hz"] == 8.6
    assert data["plan"]["dwell_s"] == 20.0


def test_a_key_under_a_value_that_is_not_a_table_is_refused_by_name() -> None:
    with pytest.raises(ValueError, match=r"campaign\.kind\.x: kind is not a TOML table"):
        with_values(TEXT, {"campaign.kind.x": 1})
