"""Configuration validation: every error names the field and what is allowed."""

from __future__ import annotations

from pathlib import Path

import pytest

from qmg_lab.config.schema import ConfigError, config_fingerprint, load_config, parse_config

ROOT = Path(__file__).resolve().parents[2]


@pytest.mark.parametrize("name", ["paper_campaign.toml", "clsf_adev.toml", "station.example.toml"])
def test_shipped_configs_validate(name):
    cfg, text = load_config(ROOT / "configs" / name)
    assert text and cfg.device.f0_hz > 0


@pytest.mark.parametrize(
    "text, fragment",
    [
        ("[loops]\nrate_bandwidth_hz = -1\n", "loops.rate_bandwidth_hz"),
        ("[loops]\nrate_bandwidth_hz = 8\n", "must be below dither.frequency_hz"),
        ("[plan]\ndwell_s = 5\nsettle_s = 10\n", "plan.settle_s"),
        ("[plan]\nbogus = 1\n", "plan.bogus: unknown key"),
        ("[nosuchsection]\n", "nosuchsection: unknown key"),
        ("[clsf]\nmode = 'sometimes'\n", "clsf.mode"),
        ("[lockin]\ndevice = 'hf2'\n", "lockin.device"),
        ("[lockin]\nrate_auxin = 1\ndither_auxin = 1\n", "must be different AuxIn"),
        ("[chamber]\nmin_c = 50\nmax_c = 40\n", "chamber.min_c"),
        ("[device]\nf0_hz = 'fast'\n", "device.f0_hz"),
        ("[table\n", "not valid TOML"),
    ],
)
def test_bad_values_name_the_field(text, fragment):
    with pytest.raises(ConfigError) as err:
        parse_config(text, "x.toml")
    assert fragment in str(err.value)
    assert "x.toml" in str(err.value)


def test_missing_file_is_named(tmp_path):
    with pytest.raises(ConfigError, match="not found"):
        load_config(tmp_path / "nope.toml")


def test_with_all_sim_sets_every_instrument():
    cfg = parse_config("").with_all_sim()
    assert cfg.all_sim and cfg.lockin.sim and cfg.table.sim


def test_fingerprint_changes_with_text():
    assert config_fingerprint("a") != config_fingerprint("b")
    assert len(config_fingerprint("a")) == 64


def test_configuration_reference_matches_the_schema():
    from qmg_lab.config.docs import reference_markdown

    doc = (ROOT / "docs" / "configuration.md").read_text(encoding="utf-8")
    assert doc == reference_markdown(), "regenerate: python -m qmg_lab.config.docs > docs/configuration.md"


def test_line_endings_follow_toml(tmp_path):
    """TOML allows LF and CRLF; a bare CR is not a newline (found by the bad-input property test)."""
    crlf = tmp_path / "crlf.toml"
    crlf.write_bytes(b"[plan]\r\ndwell_s = 60\r\n")
    assert load_config(crlf)[0].plan.dwell_s == 60
    cr = tmp_path / "cr.toml"
    cr.write_bytes(b"x=1\r")
    with pytest.raises(ConfigError, match="not valid TOML"):
        load_config(cr)
