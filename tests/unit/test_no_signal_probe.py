"""`os.kill(pid, 0)` is not a liveness check on Windows (signal 0 is CTRL_C_EVENT: the call sends Ctrl-C to a
console, Python's os.kill documentation): no code of qmg_lab, drivers or sims calls it. The ruff rule TID251
(pyproject.toml, banned-api "os.kill") refuses any os.kill there; this test holds the narrower rule even if the lint
configuration changes, and shows that its scan finds the call it forbids."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
PACKAGES = ("qmg_lab", "drivers", "sims")


def signal_probes(source: str, filename: str = "<src>") -> list[int]:
    """Line numbers of `os.kill(x, 0)` / `kill(x, 0)` / `os.kill(x, signal.SIG...=0)`-style calls: any call of a
    name or attribute `kill` whose second argument is the constant 0."""
    lines = []
    for node in ast.walk(ast.parse(source, filename)):
        if not isinstance(node, ast.Call) or len(node.args) < 2:
            continue
        func = node.func
        name = func.attr if isinstance(func, ast.Attribute) else func.id if isinstance(func, ast.Name) else ""
        second = node.args[1]
        if name == "kill" and isinstance(second, ast.Constant) and second.value == 0:
            lines.append(node.lineno)
    return lines


def test_the_scan_finds_a_signal_zero_probe() -> None:
    assert signal_probes("import os\ntry:\n    os.kill(pid, 0)\nexcept OSError:\n    pass\n") == [3]
    assert signal_probes("from os import kill\nkill(1234, 0)\n") == [2]
    assert signal_probes("import os, signal\nos.kill(1234, signal.SIGTERM)\n") == []


def test_no_code_probes_a_process_with_signal_zero() -> None:
    found = {
        str(path.relative_to(ROOT)): lines
        for package in PACKAGES
        for path in sorted((ROOT / package).rglob("*.py"))
        if (lines := signal_probes(path.read_text(encoding="utf-8"), str(path)))
    }
    assert found == {}, f"os.kill(pid, 0) is Ctrl-C on Windows; use qmg_lab.storage.lock.writer_state: {found}"


def test_the_lint_rule_bans_os_kill_in_the_packages() -> None:
    import tomllib

    ruff = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))["tool"]["ruff"]["lint"]
    assert "TID251" in ruff["select"]
    assert "os.kill" in ruff["flake8-tidy-imports"]["banned-api"]
    assert all(
        "TID251" not in ignored
        for pattern, ignored in ruff["per-file-ignores"].items()
        if "tests" not in pattern and "benchmarks" not in pattern
    )
