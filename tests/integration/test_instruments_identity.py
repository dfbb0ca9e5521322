"""`qmg-lab instruments` never prints a literal None in the identity column: a chamber that does not identify
(here an EC1x twin reached over a socket as hardware, silent past the driver's first-contact attempts) shows
"(not identified)" and its error, and the command exits 3."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from sims.chamber_twin import ChamberTwin
from sims.serial_twin import serve_socket
from sims.world import World
from tests.support.campaigns import SHORT_TOML
from tests.support.twin_params import chamber_twin_settings, paper_world_params

ROOT = Path(__file__).resolve().parents[2]


def test_a_chamber_that_does_not_identify_shows_no_none(tmp_path: Path) -> None:
    twin = ChamberTwin(World(paper_world_params(), clock="wall"), **chamber_twin_settings(silent_commands=100))
    url, stop = serve_socket(twin)
    try:
        text = SHORT_TOML.replace("[chamber]\nsim = true", f'[chamber]\nsim = false\nport = "{url}"\ntimeout_s = 0.2')
        cfg = tmp_path / "silent-chamber.toml"
        cfg.write_text(text + "\n[recovery]\nreconnect_attempts = 0\n", encoding="utf-8")
        proc = subprocess.run(
            [sys.executable, "-m", "qmg_lab", "instruments", str(cfg)],
            capture_output=True,
            text=True,
            cwd=ROOT,
            timeout=300,
            env={**os.environ, "COLUMNS": "250"},
        )
    finally:
        stop()
    assert proc.returncode == 3, proc.stderr
    # the table's rows: instrument | simulated | identity | state (a row may wrap onto continuation lines)
    cells = [[c.strip() for c in line.split("│")[1:-1]] for line in proc.stdout.splitlines() if line.count("│") == 5]
    identities = {row[0]: row[2] for row in cells if row[0]}
    assert set(identities) == {"lockin", "generator", "table", "chamber"}, proc.stdout
    assert identities["chamber"] == "(not identified)"
    assert all(cell[2] != "None" for cell in cells)
    assert twin.commands_seen >= 4  # the driver's first-contact STATUS? attempts reached the twin
