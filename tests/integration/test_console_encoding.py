"""Output never fails on the console's encoding: a Windows console or redirected stream in cp1252 has no ≤
(and µ, −), and Python raises UnicodeEncodeError when one is written to it (strict errors). The command line
writes such characters as their backslash escape instead (qmg_lab.cli.common.tolerant_streams).

PYTHONIOENCODING=cp1252 gives a subprocess on any OS the streams of a redirected Windows process (Python's
documentation of PYTHONIOENCODING: the encoding of stdin/stdout/stderr, errors strict unless given).
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
NAME = "cold ≤ 5 °C"


def qmg_cp1252(*args: str) -> subprocess.CompletedProcess[bytes]:
    env = {**os.environ, "PYTHONIOENCODING": "cp1252"}
    return subprocess.run([sys.executable, "-m", "qmg_lab", *args], capture_output=True, cwd=ROOT, env=env, timeout=300)


def test_a_character_cp1252_lacks_reaches_stdout_as_its_escape(tmp_path: Path) -> None:
    cfg = tmp_path / "cold.toml"
    cfg.write_text(f'[campaign]\nname = "{NAME}"\n', encoding="utf-8")
    proc = qmg_cp1252("check", str(cfg))
    assert b"UnicodeEncodeError" not in proc.stderr
    assert proc.returncode == 0, proc.stderr.decode("cp1252", "replace")
    text = proc.stdout.decode("cp1252")  # the stream stays cp1252: ° is its byte 0xB0
    assert "cold \\u2264 5 °C" in text


def test_an_error_message_with_such_a_character_reaches_stderr(tmp_path: Path) -> None:
    missing = tmp_path / "≤ none.toml"
    proc = qmg_cp1252("check", str(missing))
    assert b"UnicodeEncodeError" not in proc.stderr
    assert proc.returncode == 2
    err = proc.stderr.decode("cp1252")
    assert "\\u2264" in err and "configuration file not found" in err
