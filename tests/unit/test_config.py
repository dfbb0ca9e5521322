"""Configuration validation: every error names the field and what is allowed."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from qmg_lab.config.schema import ConfigError, config_fingerprint, load_config, parse_config
from tests.support.schema_fields import schema_fields

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
        ("[loops]\nrate_zero_offset_hz = 0.05\n", 'set loops.sense_pi_design = "zero_on_pole"'),
        ("[loops]\nsense_pi_design = 'pd'\n", "loops.sense_pi_design"),
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


# ====================================================================================== finite floats, times >= 0
def _float_fields() -> list[tuple[str, str, bool]]:
    """(TOML section, key, is a list) of every float-valued field of the schema."""
    out = []
    for section, key, info in schema_fields():
        ann = info.annotation
        args = getattr(ann, "__args__", ())
        is_list = getattr(ann, "__origin__", None) is list
        item = getattr(args[0], "__origin__", args[0]) if is_list else None
        if ann is float or float in args or item is float:
            out.append((section, key, is_list))
    return out


FLOATS = _float_fields()


def test_the_float_fields_are_found():
    # the walk must see the fields the issue named, or the tests below prove nothing
    names = {f"{s}.{k}" for s, k, _ in FLOATS}
    assert {"sim.arw_dps_per_rt_hz", "sim.faults.interlock_trip_at_s", "sim.faults.disconnect_at_s"} <= names
    assert len(FLOATS) > 100


@pytest.mark.parametrize("value", ["inf", "-inf", "nan"])
@pytest.mark.parametrize("section, key, is_list", FLOATS, ids=[f"{s}.{k}" for s, k, _ in FLOATS])
def test_every_float_is_finite(section, key, is_list, value):
    toml_value = f"[{value}]" if is_list else value
    with pytest.raises(ConfigError) as err:
        parse_config(f"[{section}]\n{key} = {toml_value}\n", "x.toml")
    assert f"{section}.{key}" in str(err.value)


TIMES = [(s, k, lst) for s, k, lst in FLOATS if k.endswith("_s")]


@pytest.mark.parametrize("section, key, is_list", TIMES, ids=[f"{s}.{k}" for s, k, _ in TIMES])
def test_every_time_is_non_negative(section, key, is_list):
    toml_value = "[-1.0]" if is_list else "-1.0"
    with pytest.raises(ConfigError) as err:
        parse_config(f"[{section}]\n{key} = {toml_value}\n", "x.toml")
    message = str(err.value)
    assert f"{section}.{key}" in message and re.search(r"allowed: [^;]*>=? 0", message), message


@pytest.mark.parametrize(
    "text, fragment",
    [
        ("[sim]\narw_dps_per_rt_hz = inf\n", "sim.arw_dps_per_rt_hz: Input should be a finite number"),
        ("[sim.faults]\ninterlock_trip_at_s = inf\n", "sim.faults.interlock_trip_at_s"),
        ("[sim.faults]\nchamber_dropout_at_s = inf\n", "sim.faults.chamber_dropout_at_s"),
        ("[sim.faults]\ndisconnect_at_s = [10.0, -5.0]\n", "sim.faults.disconnect_at_s.1"),
        ("[sim.faults]\nsample_loss_at_s = [-1.0]\n", "allowed: a list of finite numbers >= 0"),
    ],
)
def test_the_values_the_issue_found_are_refused(text, fragment):
    with pytest.raises(ConfigError) as err:
        parse_config(text, "x.toml")
    assert fragment in str(err.value)


# ====================================================================================== TOML syntax in words
@pytest.mark.parametrize(
    "text, words",
    [
        ("[plan]\ndwell_s = 60\nsettle_s = 5\ndwell_s = 70\n", "line 4: plan.dwell_s is set twice (first on line 2)"),
        (
            "[plan]\ndwell_s = 60\n[sim]\ndwell_s = 1\ndwell_s = 2\n",
            "line 5: sim.dwell_s is set twice (first on line 4)",
        ),
        ("[plan]\ndwell_s = 60\n[table]\nsim = true\n[plan]\n", "line 5: the section [plan] appears twice (first on"),
        ("\ufeff[plan]\ndwell_s = 60\n", "UTF-8 byte-order mark (BOM)"),
        ("[plan]\ndwéll_s = 60\n", "line 2: key 'dwéll_s' contains 'é': configuration keys and sections are ASCII"),
        ("[plän]\n", "line 1: section 'plän' contains 'ä'"),
        ("[plan]\ndwell_s = sixty\n", "line 2, column 11: invalid value: a value is a number"),
        ("[campaign]\nname = 'open\n", "at the end of the file"),
    ],
)
def test_toml_syntax_errors_are_worded(text, words):
    with pytest.raises(ConfigError) as err:
        parse_config(text, "x.toml")
    message = str(err.value)
    assert message.startswith("x.toml: not valid TOML: ") and words in message, message
    assert "(at line" not in message  # tomllib's bare position is replaced, not repeated


def test_a_bom_file_is_refused_with_what_to_do(tmp_path):
    path = tmp_path / "bom.toml"
    path.write_bytes(b"\xef\xbb\xbf[plan]\ndwell_s = 60\n")
    with pytest.raises(ConfigError, match="save it as UTF-8 without BOM"):
        load_config(path)
