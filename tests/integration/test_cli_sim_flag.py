"""`--sim` reads as a flag on every command that takes it: no value in --help (typer shows a bool option's type
as `<bool>` unless it has a metavar), `--sim` alone switches every instrument to its twin, and a value after it
is not taken for one."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import typer
from typer.testing import CliRunner

from qmg_lab.cli.main import app

ROOT = Path(__file__).resolve().parents[2]
runner = CliRunner()


def commands(group: Any, path: tuple[str, ...] = ()) -> Iterator[tuple[tuple[str, ...], Any]]:
    """Every leaf command of a (typer's own click) group, with its path of names."""
    for name, cmd in group.commands.items():
        if hasattr(cmd, "commands"):
            yield from commands(cmd, (*path, name))
        else:
            yield (*path, name), cmd


def test_every_sim_option_is_a_flag_shown_without_a_value() -> None:
    root = typer.main.get_command(app)
    with_sim = []
    for path, cmd in commands(root):
        sim = [p for p in cmd.params if "--sim" in getattr(p, "opts", ())]
        if not sim:
            continue
        with_sim.append(" ".join(path))
        assert sim[0].is_flag, path
        result = runner.invoke(app, [*path, "--help"], env={"COLUMNS": "200"})
        assert result.exit_code == 0, (path, result.output)
        line = next(ln for ln in result.output.splitlines() if "--sim " in ln)
        assert "<bool>" not in line and "BOOLEAN" not in line, (path, line)
    # the commands docs/cli.md lists with --sim: the campaign, instruments, budget, the characterizations, tune
    # and the bring-up commands
    for expected in ("run", "instruments", "budget", "tune", "characterize bandwidth", "chamber setpoint"):
        assert expected in with_sim, expected


def test_sim_alone_switches_to_the_twins_and_a_value_is_not_taken() -> None:
    cfg = str(ROOT / "configs" / "paper_campaign.toml")  # every instrument hardware: without --sim, no DS345
    result = runner.invoke(app, ["generator", "mute", cfg])
    assert result.exit_code == 3, result.output  # the configured GPIB address cannot be reached here
    result = runner.invoke(app, ["generator", "mute", cfg, "--sim"])
    assert result.exit_code == 0, result.output
    assert "DS345 muted" in result.output
    result = runner.invoke(app, ["generator", "mute", cfg, "--sim", "true"])
    assert result.exit_code == 2  # "true" is an extra argument, not the flag's value
