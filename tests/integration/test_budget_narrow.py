"""`qmg-lab budget` at 80 columns: every source name readable (wrapped, never cut to "…"), no line wider."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from qmg_lab.budget.noise import noise_budget
from qmg_lab.config.schema import parse_config


@pytest.mark.parametrize("columns", [80, 100, 132])
def test_budget_is_readable_at_the_terminal_width(tmp_path: Path, columns: int) -> None:
    config = tmp_path / "c.toml"
    config.write_text("[clsf]\nmode = 'correct'\n")
    env = {**os.environ, "COLUMNS": str(columns)}
    done = subprocess.run(
        [sys.executable, "-m", "qmg_lab", "budget", str(config)],
        capture_output=True,
        text=True,
        env=env,
        timeout=300,
        check=False,
    )
    assert done.returncode == 0, done.stderr
    lines = done.stdout.splitlines()
    assert "…" not in done.stdout
    assert max(len(line) for line in lines) <= columns
    table = "\n".join(lines[: next(i for i, line in enumerate(lines) if line.startswith("temperature sweep"))])
    words = table.split()
    for source in noise_budget(parse_config(config.read_text())).sources:
        assert all(word in words for word in source.name.split()), (source.name, table)  # wrapped, not cut
        assert f"  {source.name} = " in done.stdout  # its value, in the list under the table
    assert ("value" in words) == (columns >= 100)  # the values' column only where it fits
