"""Bad input: wrong types, out-of-range values, unknown keys, sections that are not tables, unreadable files and bad
CLI arguments are all answered with exit code 2 and a message that names what is wrong (the field and what it
accepts), never a traceback.

Property tests run the CLI in-process (typer.testing.CliRunner) over values drawn from the configuration schema
itself (qmg_lab.config.schema); a few subprocess runs check the real exit codes.
"""

from __future__ import annotations

import json
import math
import subprocess
import sys
import tomllib
from pathlib import Path
from typing import Any

import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st
from typer.testing import CliRunner

from qmg_lab.cli.main import app
from qmg_lab.config.schema import Config
from tests.support.schema_fields import schema_fields

RUNNER = CliRunner()
PROPERTY = settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])


def _numeric_fields() -> list[tuple[str, str, type, dict[str, float]]]:
    """(section, key, int|float, bounds) of every bounded numeric field of the schema ([sim.faults] as sim.faults)."""
    out = []
    for prefix, key, info in schema_fields():
        ann = info.annotation
        base = [a for a in getattr(ann, "__args__", (ann,)) if a is not type(None)]
        if len(base) != 1 or base[0] not in (int, float) or not prefix:
            continue
        bounds = {
            attr: getattr(m, attr)
            for m in info.metadata
            for attr in ("ge", "gt", "le", "lt")
            if getattr(m, attr, None) is not None
        }
        if bounds:
            out.append((prefix, key, base[0], bounds))
    return out


NUMERIC = _numeric_fields()
SECTIONS = list(Config.model_fields)


def _toml_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, str):  # a TOML basic string: JSON's escapes are TOML's, plus DEL
        return json.dumps(v, ensure_ascii=False).replace("\x7f", "\\u007f")
    if isinstance(v, float) and math.isinf(v):
        return "inf" if v > 0 else "-inf"
    if isinstance(v, float) and math.isnan(v):
        return "nan"
    if isinstance(v, list):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{k} = {_toml_value(x)}" for k, x in v.items()) + "}"
    return repr(v)


def _check(tmp_path: Path, text: str, name: str = "bad.toml") -> Any:
    path = tmp_path / name
    path.write_text(text, encoding="utf-8")
    return RUNNER.invoke(app, ["check", str(path)])


def _assert_bad_input(result: Any, *fragments: str) -> None:
    out = result.output
    assert result.exit_code == 2, out
    assert "Traceback" not in out and not isinstance(result.exception, (AttributeError, TypeError, KeyError))
    for f in fragments:
        assert f in " ".join(out.split()), (f, out)  # rich may wrap long lines


@st.composite
def out_of_range(draw: Any) -> tuple[str, str, Any, str]:
    """A field and a value just outside one of its bounds; the bound's text as the message shows it."""
    section, key, kind, bounds = draw(st.sampled_from(NUMERIC))
    side = draw(st.sampled_from(sorted(bounds)))
    limit = bounds[side]
    step = draw(st.sampled_from([1, 10, 1000])) if kind is int else draw(st.floats(1e-3, 1e6))
    value = limit - step if side in ("ge", "gt") else limit + step
    if side == "gt" and kind is float:
        value = draw(st.sampled_from([limit, limit - step]))
    if side == "lt":
        value = draw(st.sampled_from([limit, limit + step]))
    value = int(value) if kind is int else float(value)
    sym = {"ge": ">=", "gt": ">", "le": "<=", "lt": "<"}[side]
    return section, key, value, f"{sym} {limit:g}"


@PROPERTY
@given(case=out_of_range())
def test_out_of_range_values_name_the_field_and_the_range(tmp_path, case):
    section, key, value, bound = case
    result = _check(tmp_path, f"[{section}]\n{key} = {_toml_value(value)}\n")
    _assert_bad_input(result, f"{section}.{key}", bound, "allowed:")


WRONG_TYPES = st.one_of(
    st.text(max_size=8),  # strict: even "10" is a string, not a number
    st.booleans(),
    st.lists(st.integers(-5, 5), max_size=3),
    st.dictionaries(st.sampled_from(["a", "b"]), st.integers(0, 3), max_size=2),
)


@PROPERTY
@given(field=st.sampled_from(NUMERIC), value=WRONG_TYPES)
def test_wrong_types_for_numbers_name_the_field(tmp_path, field, value):
    section, key, _, _ = field
    result = _check(tmp_path, f"[{section}]\n{key} = {_toml_value(value)}\n")
    _assert_bad_input(result, f"{section}.{key}", "allowed:")


BOOL_FIELDS = [(s, "sim") for s in ("lockin", "generator", "table", "chamber")]


@PROPERTY
@given(field=st.sampled_from(BOOL_FIELDS), value=st.one_of(st.integers(), st.text(max_size=5), st.floats()))
def test_wrong_types_for_switches_name_the_field(tmp_path, field, value):
    section, key = field
    result = _check(tmp_path, f"[{section}]\n{key} = {_toml_value(value)}\n")
    _assert_bad_input(result, f"{section}.{key}", "true or false")


IDENT = st.from_regex(r"[a-z][a-z0-9_]{0,15}", fullmatch=True)


@PROPERTY
@given(section=st.sampled_from(SECTIONS), key=IDENT)
def test_unknown_keys_are_named(tmp_path, section, key):
    model = Config.model_fields[section].annotation
    assume(key not in model.model_fields)
    result = _check(tmp_path, f"[{section}]\n{key} = 1\n")
    _assert_bad_input(result, f"{section}.{key}", "unknown key")


@PROPERTY
@given(name=IDENT)
def test_unknown_sections_are_named(tmp_path, name):
    assume(name not in SECTIONS)
    _assert_bad_input(_check(tmp_path, f"[{name}]\nx = 1\n"), f"{name}: unknown key")


@PROPERTY
@given(section=st.sampled_from(SECTIONS), value=st.one_of(st.integers(), st.text(max_size=4), st.booleans()))
def test_a_section_that_is_not_a_table_is_named(tmp_path, section, value):
    _assert_bad_input(_check(tmp_path, f"{section} = {_toml_value(value)}\n"), section, f"a [{section}] section")


@PROPERTY
@given(data=st.binary(max_size=200))
def test_arbitrary_bytes_never_give_a_traceback(tmp_path, data):
    path = tmp_path / "junk.toml"
    path.write_bytes(data)
    result = RUNNER.invoke(app, ["check", str(path)])
    try:
        tomllib.loads(data.decode("utf-8"))
        valid_toml = True
    except (UnicodeDecodeError, tomllib.TOMLDecodeError):
        valid_toml = False
    if not valid_toml:
        _assert_bad_input(result, str(path))
    else:  # valid TOML: either a usable configuration or a schema error, never a crash
        assert result.exit_code in (0, 2) and "Traceback" not in result.output


def test_missing_sections_take_the_documented_defaults(tmp_path):
    # every section is optional: an empty file is the paper's campaign with the documented defaults
    result = _check(tmp_path, "")
    assert result.exit_code == 0 and "temperature_sweep" in result.output


def test_unreadable_configuration_files(tmp_path):
    _assert_bad_input(RUNNER.invoke(app, ["check", str(tmp_path / "nope.toml")]), "not found")
    _assert_bad_input(RUNNER.invoke(app, ["check", str(tmp_path)]), "is a directory")
    bad = tmp_path / "latin1.toml"
    bad.write_bytes("[campaign]\nname = 'caf\xe9'\n".encode("latin-1"))
    _assert_bad_input(RUNNER.invoke(app, ["check", str(bad)]), "cannot read configuration")


# ====================================================================================== CLI arguments
@pytest.fixture(scope="module")
def good_config(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("cfg") / "good.toml"
    path.write_text("[campaign]\nname = 'x'\n")
    return path


@settings(max_examples=15, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(rate=st.one_of(st.floats(allow_nan=True, allow_infinity=True), st.integers(-(10**6), 10**6)))
def test_manual_table_rate_outside_the_limits_is_refused(good_config, rate):
    assume(not (isinstance(rate, (int, float)) and math.isfinite(rate) and abs(rate) <= 100.0))
    # "--" ends the options, so that a negative rate is not read as an option
    result = RUNNER.invoke(app, ["table", "rate", "--sim", "--", str(good_config), str(rate)])
    _assert_bad_input(result, "table rate")
    if math.isfinite(rate):
        assert "[-100, 100] deg/s" in " ".join(result.output.split())


@settings(max_examples=15, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(word=st.text(alphabet="abcxyz_-%", min_size=1, max_size=6))
def test_non_numeric_cli_arguments_are_usage_errors(good_config, word):
    result = RUNNER.invoke(app, ["chamber", "setpoint", str(good_config), word, "--sim"])
    assert result.exit_code == 2 and "setpoint_c" in result.output and "Traceback" not in result.output


@pytest.mark.parametrize(
    "args, fragment",
    [
        (["run", "{cfg}", "--sim", "--resume", "{tmp}/missing.h5"], "no such run file"),
        (["run", "{cfg}", "--sim", "--resume", "{cfg}"], "not an HDF5 file"),
        (["run", "{cfg}", "--sim", "-o", "{tmp}/a.h5", "--resume", "{tmp}/b.h5"], "name different files"),
        (["run", "{cfg}", "--sim", "--bogus"], "No such option"),
        (["analyze", "{tmp}/missing.h5"], "no such run file"),
        (["analyze", "{cfg}"], "not an HDF5 file"),
        (["characterize", "sideways", "{cfg}"], "sideways"),
    ],
)
def test_bad_arguments_and_files(tmp_path, good_config, args, fragment):
    argv = [a.format(cfg=good_config, tmp=tmp_path) for a in args]
    _assert_bad_input(RUNNER.invoke(app, argv), fragment)


def test_existing_output_is_not_overwritten(tmp_path, good_config):
    out = tmp_path / "exists.h5"
    out.write_bytes(b"precious")
    _assert_bad_input(RUNNER.invoke(app, ["run", str(good_config), "--sim", "-o", str(out)]), "exists")
    assert out.read_bytes() == b"precious"


@pytest.mark.parametrize(
    "text, fragment",
    [
        ("[plan]\ndwell_s = 'long'\n", "plan.dwell_s"),
        ("[sim.faults]\nserial_timeout_prob = 2\n", "sim.faults.serial_timeout_prob"),
        ("[recovery]\ntimeout_s = -1\n", "recovery.timeout_s"),
    ],
)
def test_real_exit_code_2_from_the_installed_command(tmp_path, text, fragment):
    path = tmp_path / "c.toml"
    path.write_text(text)
    done = subprocess.run(
        [sys.executable, "-m", "qmg_lab", "run", str(path), "--sim", "-o", str(tmp_path / "r.h5")],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert done.returncode == 2
    assert fragment in done.stderr and "allowed:" in done.stderr and "Traceback" not in done.stderr
    assert not (tmp_path / "r.h5").exists()


# ====================================================================================== issue 27: finite, >= 0, TOML
@pytest.mark.parametrize(
    "text, fragments",
    [
        ("[sim]\narw_dps_per_rt_hz = inf\n", ["sim.arw_dps_per_rt_hz", "finite number"]),
        ("[sim.faults]\ninterlock_trip_at_s = inf\n", ["sim.faults.interlock_trip_at_s", "finite number"]),
        ("[sim.faults]\ndisconnect_at_s = [-5.0]\n", ["sim.faults.disconnect_at_s", ">= 0"]),
        ("[sim.faults]\nchamber_dropout_at_s = inf\n", ["sim.faults.chamber_dropout_at_s", "finite number"]),
        ("[sim.faults]\nsample_loss_at_s = [-1.0]\n", ["sim.faults.sample_loss_at_s", ">= 0"]),
        ("[plan]\ndwell_s = 60\ndwell_s = 70\n", ["line 3: plan.dwell_s is set twice (first on line 2)"]),
        ("\ufeff[plan]\ndwell_s = 60\n", ["byte-order mark", "without BOM"]),
        ("[plan]\nrätsel = 1\n", ["line 2: key 'rätsel' contains 'ä'", "ASCII"]),
        ("[plan]\nchamber_end_c = 120\n", ["plan.chamber_end_c = 120 is outside [-40, 85]", "chamber.max_c"]),
    ],
)
def test_values_check_used_to_pass_are_refused_by_check(tmp_path, text, fragments):
    _assert_bad_input(_check(tmp_path, text), *fragments)
    assert "(at line" not in _check(tmp_path, text).output


def test_an_infinite_noise_is_bad_input_for_run_too(tmp_path):
    """`run` used to accept it and fail in the twin with exit 3; now it is exit 2 before anything starts."""
    path = tmp_path / "inf.toml"
    path.write_text("[sim]\narw_dps_per_rt_hz = inf\n")
    done = subprocess.run(
        [sys.executable, "-m", "qmg_lab", "run", str(path), "--sim", "-o", str(tmp_path / "r.h5")],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert done.returncode == 2, done.stderr
    assert "sim.arw_dps_per_rt_hz" in done.stderr and "finite" in done.stderr and "Traceback" not in done.stderr
    assert not (tmp_path / "r.h5").exists()


def test_the_limit_message_says_outside(tmp_path):
    # a derived limit that the schema leaves to `check`: 90 deg/s of virtual rate needs 2*90*0.06 = 10.8 Vpp > 10
    result = _check(tmp_path, "[dither]\nvirtual_rate_dps = 90\n")
    _assert_bad_input(result, "dither amplitude = 10.8 Vpp outside [0.01, 10] Vpp")
    assert "within" not in result.output.split("breaks instrument limits")[-1]


# ====================================================================================== issue 26: negative arguments
@pytest.mark.parametrize(
    "argv, said",
    [
        (["table", "rate", "{cfg}", "-5", "--sim"], "table commanded to -5 deg/s"),
        (["table", "rate", "--sim", "{cfg}", "-2.5e0", "--accel", "50"], "table commanded to -2.5 deg/s at 50 deg/s^2"),
        (["chamber", "setpoint", "{cfg}", "-10", "--sim"], "chamber setpoint -10 degC"),
    ],
)
def test_negative_numbers_are_arguments_without_a_double_dash(good_config, argv, said):
    result = RUNNER.invoke(app, [a.format(cfg=good_config) for a in argv])
    assert result.exit_code == 0, result.output
    assert said in result.output


@pytest.mark.parametrize(
    "argv, fragment",
    [
        (["table", "rate", "{cfg}", "-500", "--sim"], "table rate = -500 deg/s is outside the limit [-100, 100]"),
        (["table", "rate", "{cfg}", "5", "--acel", "3", "--sim"], "--acel"),  # a mistyped option is still refused
        (["table", "rate", "{cfg}", "--acel", "--sim"], "rate_dps"),
    ],
)
def test_negative_number_arguments_keep_the_checks(good_config, argv, fragment):
    _assert_bad_input(RUNNER.invoke(app, [a.format(cfg=good_config) for a in argv]), fragment)


def test_a_study_file_syntax_error_is_worded_like_a_configuration(tmp_path):
    (tmp_path / "base.toml").write_bytes(b"\xef\xbb\xbf[plan]\ndwell_s = 60\n")
    dup = tmp_path / "dup.toml"
    dup.write_text('[study]\nname = "x"\nbase = "base.toml"\nbase = "other.toml"\n')
    _assert_bad_input(
        RUNNER.invoke(app, ["study", str(dup), "-o", str(tmp_path / "out")]),
        "not valid TOML: line 4: study.base is set twice (first on line 3)",
    )
    bom = tmp_path / "bom.toml"
    bom.write_text('[study]\nname = "x"\nbase = "base.toml"\n')
    _assert_bad_input(
        RUNNER.invoke(app, ["study", str(bom), "-o", str(tmp_path / "out")]), "base configuration", "without BOM"
    )
    assert not (tmp_path / "out").exists()


def test_a_path_longer_than_the_terminal_is_printed_whole(tmp_path):
    """An error naming a path longer than the console's width (80 columns here) is soft-wrapped: the terminal
    folds it, no newline is written inside the path, so it copies whole."""
    deep = tmp_path / ("a" * 60) / ("b" * 60)
    deep.mkdir(parents=True)
    path = deep / "junk.toml"
    path.write_bytes(b"\x00")
    result = RUNNER.invoke(app, ["check", str(path)])
    assert result.exit_code == 2
    assert str(path) in result.output
