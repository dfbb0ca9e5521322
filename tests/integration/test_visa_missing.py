"""With no VISA library on the machine, a VISA instrument's connection failure says what to install (pyvisa-py,
or NI-VISA / Keysight) and names the instrument and its address, instead of pyvisa's bare "Could not locate a
VISA implementation".

These run against the machine as it is (no VISA library, no pyvisa-py: the state of a fresh lab PC); where one
is installed they are skipped, since the condition cannot be made without mocking the OS.
"""

from __future__ import annotations

import importlib.util
import subprocess
import sys
from pathlib import Path

import pytest
import pyvisa

from qmg_lab.config.schema import parse_config
from qmg_lab.instruments import InstrumentError
from qmg_lab.station import connect_instrument

ROOT = Path(__file__).resolve().parents[2]


def _visa_library_found() -> bool:
    try:
        pyvisa.ResourceManager()
    except (ValueError, OSError):
        return False
    return True


needs_no_visa = pytest.mark.skipif(_visa_library_found(), reason="a VISA library is installed on this machine")


@needs_no_visa
def test_the_generator_command_says_what_to_install(tmp_path: Path) -> None:
    cfg = tmp_path / "ds345.toml"
    cfg.write_text('[generator]\nsim = false\nresource = "GPIB0::19::INSTR"\n', encoding="utf-8")
    proc = subprocess.run(
        [sys.executable, "-m", "qmg_lab", "generator", "mute", str(cfg)],
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=300,
    )
    assert proc.returncode == 3
    err = " ".join(proc.stderr.split())  # the console wraps long lines
    for words in ("generator (DS345)", "'GPIB0::19::INSTR'", "pip install pyvisa-py", "NI-VISA", "Keysight"):
        assert words in err, (words, err)


@needs_no_visa
def test_a_chamber_on_gpib_names_itself_and_what_to_install() -> None:
    cfg = parse_config('[chamber]\nsim = false\nport = "GPIB0::6::INSTR"\n[recovery]\nreconnect_attempts = 0\n')
    with pytest.raises(InstrumentError, match=r"chamber \(EC1x\) at VISA resource 'GPIB0::6::INSTR'.*pyvisa-py"):
        connect_instrument(cfg, "chamber")


@pytest.mark.skipif(importlib.util.find_spec("pyvisa_py") is not None, reason="pyvisa-py is installed here")
def test_backend_py_without_pyvisa_py_says_to_install_it() -> None:
    cfg = parse_config(
        '[chamber]\nsim = false\nport = "ASRL3::INSTR"\nvisa_backend = "@py"\n[recovery]\nreconnect_attempts = 0\n'
    )
    with pytest.raises(InstrumentError, match=r"visa_backend '@py'\).*pip install pyvisa-py.*No package named"):
        connect_instrument(cfg, "chamber")
