"""`qmg-lab instruments CONFIG --sim --json` (issue 3): one JSON object, every instrument identified by its twin
through the real driver (the identities are the instruments' documented answers, not the station's labels)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def test_instruments_json_identifies_every_twin_through_its_driver():
    proc = subprocess.run(
        [sys.executable, "-m", "qmg_lab", "instruments", "configs/paper_campaign.toml", "--sim", "--json"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 0, proc.stderr
    report = json.loads(proc.stdout)
    assert set(report) == {"lockin", "generator", "table", "chamber"}
    for name, entry in report.items():
        assert entry["simulated"] is True and entry["ok"] is True, name
        assert entry["identity"], name
    assert "HF2LI" in report["lockin"]["identity"]
    # the DS345 answers *IDN? with the SRS comma-separated form
    assert report["generator"]["identity"].startswith("StanfordResearchSystems,DS345,")
    assert "1291BR" in report["table"]["identity"]
    # state read back over the wire: table at rest, chamber at its initial 25 degC
    assert report["table"]["state"]["rate_dps"] == 0.0
    assert report["chamber"]["state"]["temperature_c"] == 25.0


def test_instruments_on_hardware_addresses_that_do_not_answer_exit_3():
    """Without --sim the station tries the configured bench; on this machine nothing answers: exit 3, a message
    naming what could not be reached, no traceback."""
    proc = subprocess.run(
        [sys.executable, "-m", "qmg_lab", "instruments", "configs/paper_campaign.toml", "--json"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 3, (proc.stdout, proc.stderr)
    assert "Traceback" not in proc.stderr
    assert "could not connect" in proc.stderr
