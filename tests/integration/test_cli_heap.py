"""The console entry point's handling of Python's cyclic collector (qmg_lab.cli.heap).

The contract: no automatic collection while a command starts; automatic collection back on, over a frozen start-up
heap, for the command's work (a multi-hour campaign must be able to free its cycles); frozen and off at exit; and
code that uses qmg-lab as a library (the CLI invoked in-process) keeps Python's default collector.
"""

from __future__ import annotations

import gc
import json
import subprocess
import sys
from pathlib import Path

from typer.testing import CliRunner

from qmg_lab.cli import heap
from qmg_lab.cli.main import app
from tests.support.campaigns import config_text

ROOT = Path(__file__).resolve().parents[2]

# runs the real console entry in a fresh interpreter, with heap.settle wrapped to report the collector's state
# right after it, and the state once main() is done
_PROBE = """
import gc, json, sys
from qmg_lab.cli import heap, main as cli
seen = []
settle = heap.settle
def probe():
    before = gc.isenabled()
    settle()
    seen.append({"enabled_before": before, "enabled_after": gc.isenabled(), "frozen": gc.get_freeze_count()})
heap.settle = probe
sys.argv = ["qmg-lab", *sys.argv[1:]]
code = 0
try:
    cli.main()
except SystemExit as exc:
    code = exc.code or 0
print(json.dumps({"code": code, "settles": seen, "enabled_at_exit": gc.isenabled(),
                  "frozen_at_exit": gc.get_freeze_count()}), file=sys.stderr)
"""


def _probe(*args: str) -> dict:
    done = subprocess.run([sys.executable, "-c", _PROBE, *args], cwd=ROOT, capture_output=True, text=True, timeout=300)
    return json.loads(done.stderr.strip().splitlines()[-1])


def test_a_campaign_starts_without_collection_and_runs_with_it(tmp_path):
    cfg = tmp_path / "short.toml"
    cfg.write_text(config_text(), encoding="utf-8")
    state = _probe("run", str(cfg), "--sim", "-o", str(tmp_path / "r.h5"), "-q")
    assert state["code"] == 0
    # `run` settles once, after its station is up: collection was off until then, on afterwards, over a frozen heap
    assert len(state["settles"]) == 1
    (settled,) = state["settles"]
    assert settled["enabled_before"] is False
    assert settled["enabled_after"] is True
    assert settled["frozen"] > 10_000  # numpy, zhinst-toolkit, h5py, pydantic and the station: a large heap
    assert state["enabled_at_exit"] is False
    assert state["frozen_at_exit"] >= settled["frozen"]


def test_other_commands_settle_before_their_work(tmp_path):
    state = _probe("check", str(ROOT / "configs" / "paper_campaign.toml"))
    assert state["code"] == 0
    assert state["settles"][0]["enabled_before"] is False
    assert state["settles"][0]["enabled_after"] is True
    assert state["enabled_at_exit"] is False


def test_a_failing_command_still_exits_quietly(tmp_path):
    state = _probe("run", str(tmp_path / "missing.toml"), "--sim")
    assert state["code"] == 2
    assert state["enabled_at_exit"] is False


def test_in_process_use_keeps_the_default_collector(tmp_path):
    frozen = gc.get_freeze_count()
    result = CliRunner().invoke(app, ["check", str(ROOT / "configs" / "paper_campaign.toml")])
    assert result.exit_code == 0, result.output
    assert gc.isenabled()
    assert gc.get_freeze_count() == frozen  # settle() is a no-op when start-up did not switch collection off


def test_settle_is_idempotent_and_quiet_exit_freezes():
    try:
        heap.quiet_start()
        assert not gc.isenabled()
        heap.settle()
        assert gc.isenabled()
        frozen = gc.get_freeze_count()
        assert frozen > 0
        heap.settle()  # already settled: nothing more is frozen
        assert gc.get_freeze_count() == frozen
        heap.quiet_exit()
        assert not gc.isenabled()
    finally:
        gc.unfreeze()
        gc.enable()
