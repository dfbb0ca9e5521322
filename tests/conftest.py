"""What every test shares: the test kinds, told apart by folder, and the slow tests' switch.

- tests/unit/: one module or one instrument (its driver over a protocol double or its twin); seconds.
- tests/integration/: whole campaigns on the twins, in process or through the `qmg-lab` command; run files
  written, killed, resumed and analysed; tens of seconds each.
- @pytest.mark.slow: long simulated runs (minutes). Skipped unless `--run-slow` is given; CI gives it.
- @pytest.mark.hardware: needs a real instrument (skipped unless its address is given).

Each test gets the marker of its folder (`unit` or `integration`), so `pytest -m unit` runs the fast ones.
Shared helpers are plain modules in tests/support/, imported by the tests that use them.
"""

from __future__ import annotations

from pathlib import Path

import pytest

TESTS = Path(__file__).resolve().parent


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption("--run-slow", action="store_true", default=False, help="also run the tests marked slow")


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    run_slow = bool(config.getoption("--run-slow"))
    skip_slow = pytest.mark.skip(reason="slow: give --run-slow to run it")
    for item in items:
        kind = Path(str(item.path)).resolve().relative_to(TESTS).parts[0]
        if kind in ("unit", "integration"):
            item.add_marker(getattr(pytest.mark, kind))
        if "slow" in item.keywords and not run_slow:
            item.add_marker(skip_slow)
