"""Who ran a campaign, on which device, and why: `[campaign] operator`, `device_serial`, `notes` and `run --note`
are stored as root attributes of the new file, shown by `runs` (and found with `--where`), `analyze` and the watch
page; piped `runs` output is one tab-separated line per file (`runs DIR | grep aborted` finds whole rows)."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import h5py
import pytest

from qmg_lab.config.schema import NOTES_MAX_CHARS, ConfigError, parse_config
from qmg_lab.storage.layout import RUN_CONTEXT_ATTRS
from qmg_lab.watch.page import _run_context
from tests.support import synthetic_runs as syn
from tests.support.campaigns import config_text, qmg

WHO = 'operator = "Ada Lovelace"\ndevice_serial = "QMG-0042"\nnotes = "tempco after re-bonding"\n'


@pytest.fixture(scope="module")
def folder(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """One twin campaign with the run context, and one synthetic sweep without (a file from before the keys)."""
    d = tmp_path_factory.mktemp("context")
    cfg = d / "short.toml"
    cfg.write_text(config_text().replace('[campaign]\nname = "short"\n', '[campaign]\nname = "short"\n' + WHO))
    done = subprocess.run(
        qmg("run", str(cfg), "-o", str(d / "who.h5"), "-q", "--note", "first light, new mount"),
        capture_output=True,
        text=True,
    )
    assert done.returncode == 0, done.stderr
    syn.write_sweep(d / "older.h5")
    return d


def test_the_context_is_stored_as_root_attributes(folder: Path) -> None:
    with h5py.File(folder / "who.h5", "r") as h5:
        stored = {k: h5.attrs[k] for k in RUN_CONTEXT_ATTRS}
    assert stored == {
        "operator": "Ada Lovelace",
        "device_serial": "QMG-0042",
        "notes": "tempco after re-bonding",
        "run_note": "first light, new mount",
    }


def test_runs_shows_and_filters_by_the_context(folder: Path) -> None:
    done = subprocess.run(
        qmg("runs", str(folder), "--json", "--where", "operator=ada lovelace"), capture_output=True, text=True
    )
    assert done.returncode == 0, done.stderr
    rows = json.loads(done.stdout)["runs"]
    assert [Path(r["file"]).name for r in rows] == ["who.h5"]
    assert rows[0]["device_serial"] == "QMG-0042" and rows[0]["run_note"] == "first light, new mount"
    none = subprocess.run(
        qmg("runs", str(folder), "--json", "--where", "operator=nobody"), capture_output=True, text=True
    )
    assert json.loads(none.stdout)["runs"] == []
    older = subprocess.run(qmg("runs", str(folder), "--json", "--where", "operator="), capture_output=True, text=True)
    assert [Path(r["file"]).name for r in json.loads(older.stdout)["runs"]] == ["older.h5"]  # no operator: ""
    bad = subprocess.run(qmg("runs", str(folder), "--where", "colour=red"), capture_output=True, text=True)
    assert bad.returncode == 2 and "no key colour" in bad.stderr and "operator" in bad.stderr
    assert "Traceback" not in bad.stderr
    malformed = subprocess.run(qmg("runs", str(folder), "--where", "operator"), capture_output=True, text=True)
    assert malformed.returncode == 2 and "KEY=VALUE" in malformed.stderr


def test_piped_runs_are_whole_tab_separated_rows(folder: Path) -> None:
    """stdout is a pipe here: a header line and one line per file, every field in its column."""
    done = subprocess.run(qmg("runs", str(folder)), capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    lines = done.stdout.splitlines()
    header = lines[0].split("\t")
    assert len(lines) == 3 and header[:2] == ["file", "status"]
    rows = {Path(r.split("\t")[0]).name: dict(zip(header, r.split("\t"), strict=True)) for r in lines[1:]}
    assert rows["who.h5"]["status"] == "completed" and rows["who.h5"]["operator"] == "Ada Lovelace"
    assert rows["older.h5"]["operator"] == ""  # a file without the attributes
    grep = subprocess.run(["grep", "QMG-0042"], input=done.stdout, capture_output=True, text=True)
    assert grep.stdout.count("\n") == 1 and "who.h5" in grep.stdout and "completed" in grep.stdout


def test_analyze_and_the_watch_page_show_the_context(folder: Path) -> None:
    done = subprocess.run(qmg("analyze", str(folder / "who.h5"), "--json"), capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    assert json.loads(done.stdout)["run_context"]["operator"] == "Ada Lovelace"
    table = subprocess.run(qmg("analyze", str(folder / "who.h5")), capture_output=True, text=True)
    assert "QMG-0042" in table.stdout and "first light, new mount" in table.stdout
    with h5py.File(folder / "who.h5", "r") as h5:
        html_text = _run_context({k: v for k, v in h5.attrs.items()})
    assert "operator: Ada Lovelace" in html_text and "device serial: QMG-0042" in html_text


def test_bounds_of_the_context_keys() -> None:
    with pytest.raises(ConfigError, match="operator"):
        parse_config(f'[campaign]\noperator = "{"x" * 101}"\n')
    with pytest.raises(ConfigError, match="notes"):
        parse_config(f'[campaign]\nnotes = "{"x" * (NOTES_MAX_CHARS + 1)}"\n')
    assert parse_config('[campaign]\ndevice_serial = "SN 1"\n').campaign.device_serial == "SN 1"


def test_a_too_long_note_is_bad_input(tmp_path: Path) -> None:
    cfg = tmp_path / "short.toml"
    cfg.write_text(config_text())
    done = subprocess.run(
        qmg("run", str(cfg), "-o", str(tmp_path / "r.h5"), "--note", "x" * (NOTES_MAX_CHARS + 1)),
        capture_output=True,
        text=True,
    )
    assert done.returncode == 2 and "--note" in done.stderr and "Traceback" not in done.stderr
    assert not (tmp_path / "r.h5").exists()
