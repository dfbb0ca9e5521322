"""The command line without POSIX-only modules, as on a Windows lab PC (issue 24 item 5).

CI runs on Linux, so Windows is stood in for: a fresh interpreter in which the project's own code (qmg_lab, drivers,
sims) cannot import `termios`, `tty`, `pty`, `fcntl` or `resource`, and `os.fork` / `os.register_at_fork` do not
exist. Third-party packages still import what they import on Linux (pyserial imports termios there and its win32
module on Windows), so only the project's own imports are refused:

* `builtins.__import__` is wrapped: an `import` statement whose importing module is the project's, naming a blocked
  module, raises ModuleNotFoundError (as on Windows), also when the module is already loaded;
* a meta-path finder refuses the blocked modules when they are not loaded yet and the first frame outside the
  import machinery is the project's (importlib.import_module, __import__ with other globals).

In that interpreter the CLI runs in-process (`qmg_lab.cli.main.main`, as the console script calls it), command after
command: `check`, `instruments --sim --json`, `instruments` on the bench's hardware addresses (nothing answers here:
exit 3, the hardware code path imported), a bring-up command and a raw console on the twins, a short campaign
`run --sim`, `analyze --json` of its file and `budget --json`. Each command's exit code is recorded; the run file is
checked here, with h5py, in the test's own process. Its standard streams are cp1252, as a Windows console's output
redirected to a file or a pipe is. `study` starts Dask worker processes, which a blocker installed in this
interpreter does not reach: it is not run here (its POSIX-only lock is replaced by `filelock`,
tests/unit/test_study_point_lock.py).

The run file's lock is filelock's (qmg_lab/storage/lock.py), which picks its Windows class (LockFileEx) by
`sys.platform`: the stand-in cannot reach that branch, filelock's own Windows CI covers it. Windows' `os.kill` is
stood in for: signal 0 is CTRL_C_EVENT, so `os.kill(pid, 0)` delivers a Ctrl-C to this process instead of probing
`pid`; a run killed on "Windows" must then still be analysed and resumed (the writer's liveness is its lock's
state, never a signal). What this stand-in cannot show: Windows' own refusal to rename an open file (the writer
no longer does: RunWriter.create builds a new file under a unique temporary name and renames it only once it is
closed) and Windows' console events (Ctrl-Break is handled as a stop signal; closing the window is not visible to
Python's signal module: docs/reliability.md).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import h5py
import pytest

from tests.support.campaigns import SHORT_DURATION_S, SHORT_STEPS, config_text

ROOT = Path(__file__).resolve().parents[2]
PAPER = "configs/paper_campaign.toml"

BLOCKED = ("termios", "tty", "pty", "fcntl", "resource")

#: installs the blocker, removes os.fork / os.register_at_fork, then runs each argv list of sys.argv[2] (a JSON
#: file) through qmg_lab.cli.main.main() and writes the exit codes to sys.argv[3]
CHILD = r"""
import builtins, importlib.abc, json, os, sys

BLOCKED = frozenset(json.loads(sys.argv[1]))

OWN = ("qmg_lab", "drivers", "sims")
ROOT = os.path.abspath(".")
OWN_DIRS = tuple(os.path.join(ROOT, d) + os.sep for d in OWN)
MACHINERY = ("<frozen importlib", "<string>", os.path.dirname(importlib.abc.__file__) + os.sep)


def own_module(name):
    return isinstance(name, str) and name.split(".")[0] in OWN


def refuse(name):
    raise ModuleNotFoundError(f"No module named {name!r} (POSIX-only: blocked for qmg-lab's own code)", name=name)


real_import = builtins.__import__


def guarded_import(name, globals=None, locals=None, fromlist=(), level=0):
    if level == 0 and name.split(".")[0] in BLOCKED and own_module((globals or {}).get("__name__")):
        refuse(name)
    return real_import(name, globals, locals, fromlist, level)


class Blocker(importlib.abc.MetaPathFinder):
    def find_spec(self, fullname, path=None, target=None):
        if fullname.split(".")[0] not in BLOCKED:
            return None
        frame = sys._getframe(1)
        while frame is not None and frame.f_code.co_filename.startswith(MACHINERY):
            frame = frame.f_back  # the import machinery (importlib.import_module too) and this script
        if frame is not None and frame.f_code.co_filename.startswith(OWN_DIRS):
            refuse(fullname)
        return None


builtins.__import__ = guarded_import
sys.meta_path.insert(0, Blocker())
for attr in ("fork", "register_at_fork"):
    if hasattr(os, attr):
        delattr(os, attr)

# the blocker works: the project's code cannot import them, other code can
for name in BLOCKED:
    try:
        exec(f"import {name}", {"__name__": "sims.windows_probe"})
    except ModuleNotFoundError:
        pass
    else:
        raise SystemExit(f"the blocker let the project import {name}")
for name in [m for m in BLOCKED if m not in sys.modules]:  # the meta-path layer: importlib from a project file
    probe = compile(f"import importlib; importlib.import_module({name!r})", os.path.join(ROOT, "sims", "p.py"), "exec")
    try:
        exec(probe, {"__name__": "windows_probe"})
    except ModuleNotFoundError:
        pass
    else:
        raise SystemExit(f"the meta-path blocker let a project file import {name}")
exec("import termios", {"__name__": "third_party_probe"})

from qmg_lab.cli.main import main
# Windows' os.kill: signal 0 is CTRL_C_EVENT, so os.kill(pid, 0) is GenerateConsoleCtrlEvent(CTRL_C_EVENT, pid):
# a Ctrl-C to the console this process shares, not a liveness probe (Python's os.kill documentation; Microsoft's
# GenerateConsoleCtrlEvent page). The stand-in delivers that Ctrl-C to this process; other signals end the pid
# as TerminateProcess does
import signal as _signal
_posix_kill = os.kill
def _windows_kill(pid, sig):
    if sig == 0:  # CTRL_C_EVENT
        _signal.raise_signal(_signal.SIGINT)
        return
    _posix_kill(pid, _signal.SIGKILL)
os.kill = _windows_kill

commands, codes_file, codes = json.load(open(sys.argv[2], encoding="utf-8")), sys.argv[3], []
for argv in commands:
    sys.argv = ["qmg-lab", *argv]
    print(f"=== qmg-lab {' '.join(argv)}", flush=True)
    try:
        main()
        code = 0
    except SystemExit as exc:
        code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
    print(f"=== exit {code}", flush=True)
    codes.append(code)
lock = sys.modules.get("qmg_lab.storage.lock")
lock_class = None if lock is None else f"{lock.FileLock.__module__}.{lock.FileLock.__name__}"
result = {"codes": codes, "has_fork": hasattr(os, "fork"), "lock_class": lock_class}
json.dump(result, open(codes_file, "w", encoding="utf-8"))
"""


def _sections(stdout: str) -> list[str]:
    """Each command's output, in order (between its '=== qmg-lab' and '=== exit' lines)."""
    parts = stdout.split("=== qmg-lab ")[1:]
    return [p.split("\n", 1)[1].rsplit("=== exit", 1)[0] for p in parts]


@pytest.mark.timeout(900)
def test_the_cli_runs_without_posix_only_modules(tmp_path: Path) -> None:
    cfg = tmp_path / "short.toml"
    cfg.write_text(config_text(seed=5), encoding="utf-8")
    run_file = tmp_path / "short.h5"
    commands = [
        ["check", str(cfg)],
        ["instruments", PAPER, "--sim", "--json"],
        ["instruments", PAPER, "--json"],  # the bench's addresses: nothing answers on a CI machine
        ["table", "rate", PAPER, "2.5", "--sim"],
        ["table", "raw", PAPER, "STA", "--sim"],
        ["run", str(cfg), "--sim", "-o", str(run_file), "-q"],
        ["analyze", str(run_file), "--json"],
        ["budget", PAPER, "--json"],
    ]
    argv_file, codes_file = tmp_path / "argv.json", tmp_path / "codes.json"
    argv_file.write_text(json.dumps(commands), encoding="utf-8")
    proc = subprocess.run(
        [sys.executable, "-c", CHILD, json.dumps(BLOCKED), str(argv_file), str(codes_file)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        encoding="cp1252",
        env={**os.environ, "PYTHONIOENCODING": "cp1252"},
        timeout=880,
    )
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-5000:]
    assert "Traceback" not in proc.stderr, proc.stderr[-5000:]
    result = json.loads(codes_file.read_text(encoding="utf-8"))
    assert result["has_fork"] is False
    assert result["lock_class"].startswith("filelock.")  # the run file's lock is filelock's (no fcntl of ours)
    expected = [0, 0, 3, 0, 0, 0, 0, 0]
    assert result["codes"] == expected, (proc.stdout[-3000:], proc.stderr[-3000:])
    out = _sections(proc.stdout)
    assert len(out) == len(commands)

    identities = json.loads(out[1])
    assert {name: entry["ok"] for name, entry in identities.items()} == dict.fromkeys(
        ("lockin", "generator", "table", "chamber"), True
    )
    assert "could not connect" in proc.stderr  # the hardware attempt: a message, not a traceback
    assert "table commanded to 2.5 deg/s" in out[3]
    assert "sent" in out[4] and "received" in out[4]

    with h5py.File(run_file, "r") as f:
        assert f.attrs["format"] == "qmg-lab/2"
        assert f.attrs["status"] == "completed"
        assert f.attrs["mode"] == "sim"
        assert [s.decode() for s in f["steps/status"][:]] == ["completed"] * SHORT_STEPS
        t = f["lockin/time"]
        # the last demodulator sample ends the plan: within one 2 s twin block of its duration
        assert SHORT_DURATION_S - 2.0 <= float(t[t.shape[0] - 1]) <= SHORT_DURATION_S + 2.0
        assert f["clsf/time"].shape[0] > 0 and "truth" in f

    analysis = json.loads(out[6])
    assert analysis["status"] == "completed"
    budget = json.loads(out[7])
    assert budget["sources"], "the budget lists its noise sources"


def test_the_pty_transport_is_refused_without_posix_with_a_message_naming_the_way_out(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """On Windows (os.name "nt") `sim_transport = "pty"` is bad input at load (exit 2 from the CLI), and
    serve_pty raises OSError naming the transports that work there, before it opens anything."""
    import types

    from qmg_lab.config import schema
    from sims import serial_twin
    from sims.table_twin import RateTableTwin
    from tests.support.twin_params import paper_world, table_twin_settings

    windows = types.SimpleNamespace(name="nt")
    monkeypatch.setattr(schema, "os", windows)
    monkeypatch.setattr(serial_twin, "os", windows)
    for section in ("table", "chamber"):
        with pytest.raises(schema.ConfigError, match=r'"pty" needs a POSIX system.*"inprocess" or "socket"'):
            schema.parse_config(f'[{section}]\nsim = true\nsim_transport = "pty"\n', "windows.toml")
        assert getattr(schema.parse_config(f'[{section}]\nsim_transport = "socket"\n'), section).sim_transport == (
            "socket"
        )
    assert not serial_twin.pty_supported()
    with pytest.raises(OSError, match=r'needs a POSIX system.*sim_transport = "inprocess"'):
        serial_twin.serve_pty(RateTableTwin(paper_world(), **table_twin_settings()))


@pytest.mark.timeout(900)
def test_a_killed_run_resumes_under_windows_os_kill_semantics(tmp_path: Path) -> None:
    """A run killed by SIGKILL leaves a file whose writer is gone; under Windows' os.kill (signal 0 is a Ctrl-C to
    the console) `analyze` and `run --resume` of it must not probe the dead writer's pid with os.kill: both exit 0,
    and the resumed file is completed (the writer's liveness is read from the run file's lock)."""
    from tests.integration.test_resume import wait_for_steps
    from tests.support.campaigns import qmg

    cfg = tmp_path / "short.toml"
    cfg.write_text(config_text(seed=5), encoding="utf-8")
    run_file = tmp_path / "killed.h5"
    proc = subprocess.Popen(
        qmg("run", str(cfg), "-o", str(run_file), "-q"), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True
    )
    wait_for_steps(proc, run_file, 4)
    proc.kill()
    proc.wait()
    with h5py.File(run_file, "r", swmr=True, libver="latest") as f:
        assert f.attrs["status"] == "running"  # killed: the writer's pid is recorded, its process gone

    commands = [["analyze", str(run_file), "--json"], ["run", str(cfg), "--resume", str(run_file), "-q"]]
    argv_file, codes_file = tmp_path / "argv.json", tmp_path / "codes.json"
    argv_file.write_text(json.dumps(commands), encoding="utf-8")
    child = subprocess.run(
        [sys.executable, "-c", CHILD, json.dumps(BLOCKED), str(argv_file), str(codes_file)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        encoding="cp1252",
        env={**os.environ, "PYTHONIOENCODING": "cp1252"},
        timeout=880,
    )
    assert child.returncode == 0, child.stdout[-3000:] + child.stderr[-5000:]
    result = json.loads(codes_file.read_text(encoding="utf-8"))
    assert result["codes"] == [0, 0], child.stderr[-3000:]
    assert "Traceback" not in child.stderr
    with h5py.File(run_file, "r") as f:
        assert f.attrs["status"] == "completed"
        assert [s.decode() for s in f["steps/status"][:]] == ["completed"] * SHORT_STEPS
