"""The raw consoles of bring-up (issue 12): exactly the bytes sent and received, with timing.

Expected bytes come from the documented protocols (docs/instruments.md): the 1291BR answers STA at rest with
8 (servo on) | 2 (at rate) = 10, its value line then the prompt ">"; the EC1x answers C1? with the air
temperature, 25.00 at start; the DS345 answers *IDN? with its comma-separated identity; HF2 nodes read back
what was set.
"""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

from sims.chamber_twin import ChamberTwin
from sims.serial_twin import serve_socket
from sims.table_twin import RateTableTwin
from sims.world import World
from tests.support.twin_params import chamber_twin_settings, paper_world_params, table_twin_settings

ROOT = Path(__file__).resolve().parents[2]


def qmg(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "qmg_lab", *args], capture_output=True, text=True, cwd=ROOT, timeout=120
    )


def write(tmp: Path, text: str) -> Path:
    p = tmp / "bench.toml"
    p.write_text(text, encoding="utf-8")
    return p


@pytest.mark.parametrize(
    ("reply_end", "prompt_end", "received"),
    [
        (b"\r", b"\r", b"10\r>\r"),
        (b"\r\n", b"\r\n", b"10\r\n>\r\n"),
        (b"\n", b"", b"10\n>"),
    ],
)
def test_table_raw_prints_the_bytes_of_a_real_serial_exchange(
    tmp_path: Path, reply_end: bytes, prompt_end: bytes, received: bytes
) -> None:
    twin = RateTableTwin(
        World(paper_world_params(), clock="wall"), reply_end=reply_end, prompt_end=prompt_end, **table_twin_settings()
    )
    url, stop = serve_socket(twin, "127.0.0.1")
    try:
        cfg = write(tmp_path, f'[table]\nport = "{url}"\n')
        proc = qmg("table", "raw", str(cfg), "STA", "--idle", "0.2")
    finally:
        stop()
    assert proc.returncode == 0, proc.stderr
    assert f"sent 5 bytes {b'STA' + bytes([13, 10])!r}; received {len(received)} bytes {received!r}" in proc.stdout
    # every chunk: time in ms since the write, direction, bytes
    chunks = re.findall(r"^\s+(\d+\.\d) ms  << (b'.*')$", proc.stdout, flags=re.M)
    assert chunks and b"".join(eval(c) for _, c in chunks) == received
    assert twin.commands_seen == 1


def test_chamber_raw_without_terminator_and_with_escapes(tmp_path: Path) -> None:
    twin = ChamberTwin(World(paper_world_params(), clock="wall"), **chamber_twin_settings(status_layout="flags16"))
    url, stop = serve_socket(twin, "127.0.0.1")
    try:
        cfg = write(tmp_path, f'[chamber]\nport = "{url}"\n')
        proc = qmg("chamber", "raw", str(cfg), r"C1?\r\n", "--no-terminator", "--idle", "0.2")
    finally:
        stop()
    assert proc.returncode == 0, proc.stderr
    assert "sent 5 bytes b'C1?\\r\\n'; received 7 bytes b'25.00\\r\\n'" in proc.stdout


def test_table_raw_reports_silence(tmp_path: Path) -> None:
    """A port where nobody answers: the console says so, exit 0 (nothing was wrong with the input)."""
    twin = RateTableTwin(World(paper_world_params(), clock="wall"), **table_twin_settings())
    twin.fault_hook = lambda line, reply: b""  # the instrument stays silent
    url, stop = serve_socket(twin, "127.0.0.1")
    try:
        cfg = write(tmp_path, f'[table]\nport = "{url}"\n')
        proc = qmg("table", "raw", str(cfg), "STA", "--wait", "0.3")
    finally:
        stop()
    assert proc.returncode == 0, proc.stderr
    assert "<< nothing within 0.3 s" in proc.stdout and "received 0 bytes b''" in proc.stdout


def test_generator_raw_on_the_twin() -> None:
    proc = qmg("generator", "raw", "configs/paper_campaign.toml", "*IDN?", "--sim")
    assert proc.returncode == 0, proc.stderr
    assert "sent 6 bytes b'*IDN?\\n'" in proc.stdout
    assert "b'StanfordResearchSystems,DS345," in proc.stdout


def test_lockin_set_then_get_on_the_twin() -> None:
    proc = qmg("lockin", "set", "configs/paper_campaign.toml", "oscs/0/freq", "2201.5", "--sim")
    assert proc.returncode == 0, proc.stderr
    assert ">> set('/dev1234/oscs/0/freq', 2201.5)" in proc.stdout
    assert "<< getDouble('/dev1234/oscs/0/freq') -> 2201.5" in proc.stdout


@pytest.mark.parametrize(
    ("args", "code", "message"),
    [
        (("table", "raw", "configs/paper_campaign.toml", "", "--sim"), 2, "the command is empty"),
        (("table", "raw", "configs/paper_campaign.toml", "STA", "--sim", "--idle", "0"), 2, "--idle 0 s"),
        (("lockin", "get", "configs/paper_campaign.toml", "oscs/0/nosuchnode", "--sim"), 2, "oscs/0/nosuchnode"),
        (("table", "raw", "configs/paper_campaign.toml", "STA"), 3, "could not open the table's port"),
    ],
)
def test_raw_console_bad_input_and_absent_instrument(args: tuple[str, ...], code: int, message: str) -> None:
    proc = qmg(*args)
    assert proc.returncode == code, (proc.stdout, proc.stderr)
    assert message in " ".join(proc.stderr.split())
    assert "Traceback" not in proc.stderr
