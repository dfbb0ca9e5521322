"""Configuration that must reach the instruments (issue 12): lockin.output_safe_v and the chamber's own limits.

Each test sets a value different from the power-on default, so it fails if the station drops the setting.
Expected values are the configured ones, read back from the twins (the HF2 node tree; the EC1x controller's
LTL/UTL, documented in docs/instruments.md).
"""

from __future__ import annotations

from pathlib import Path

import pytest
from zhinst.toolkit import Session

from qmg_lab.config.schema import parse_config
from qmg_lab.station import SIM_DEVICE_ID, build_station, connect_instrument, gyro_params, hf2_wiring, lockin_driver
from sims.chamber_twin import ChamberTwin
from sims.hf2_server import HF2DataServerTwin
from sims.serial_twin import serve_socket
from sims.world import World
from tests.support.twin_params import chamber_twin_settings, paper_world_params

DEV = f"/{SIM_DEVICE_ID}"


def cfg_from(text: str):
    return parse_config(text)


def test_output_safe_v_reaches_the_lockin_safe_state() -> None:
    cfg = cfg_from("[lockin]\nsim = true\noutput_safe_v = 1.25\nrate_auxout = 2\nquadrature_auxout = 3\n")
    world = World(paper_world_params(), clock="virtual")
    twin = HF2DataServerTwin(
        world,
        gyro_params(cfg),
        1,
        hf2_wiring(cfg),
        rate_set=cfg.sim.hf2_rate_set,
        options=tuple(cfg.sim.hf2_options),
        device_id=SIM_DEVICE_ID,
    )
    li = lockin_driver(cfg, Session("localhost", 8005, hf2=True, connection=twin), SIM_DEVICE_ID)
    li.safe_state()
    for ch in (2, 3):
        assert twin.getInt(f"{DEV}/auxouts/{ch}/outputselect") == -1  # manual
        assert twin.getDouble(f"{DEV}/auxouts/{ch}/offset") == 1.25
    li.close()


def test_build_station_passes_output_safe_v() -> None:
    cfg = cfg_from(
        "[lockin]\nsim = true\noutput_safe_v = -0.75\n[generator]\nsim = true\n[table]\nsim = true\n"
        "[chamber]\nsim = true\n"
    )
    station = build_station(cfg)
    try:
        assert station.lockin.output_safe_v == -0.75
    finally:
        station.close()


@pytest.fixture
def chamber_controller():
    world = World(paper_world_params(), clock="wall")
    twin = ChamberTwin(world, **chamber_twin_settings(status_layout="flags16"))
    url, stop = serve_socket(twin, "127.0.0.1")
    yield twin, url
    stop()


def test_chamber_limits_are_written_to_the_controller(chamber_controller) -> None:
    twin, url = chamber_controller
    assert (twin.ltl_c, twin.utl_c) == (-70.0, 180.0)  # the controller's own range before qmg-lab connects
    cfg = cfg_from(f'[chamber]\nsim = false\nport = "{url}"\nmin_c = 10.0\nmax_c = 40.0\nsafe_setpoint_c = 20.0\n')
    conn = connect_instrument(cfg, "chamber")
    try:
        assert (twin.ltl_c, twin.utl_c) == (10.0, 40.0)
        # the controller itself now refuses a setpoint outside them (EC1x: ?LIMIT), whatever the host sends
        assert twin.respond(b"SET=45.00\r") == b"?LIMIT\r\n"
        assert twin.respond(b"SET=39.00\r") == b"OK\r\n"
    finally:
        conn.close()


def test_chamber_limits_are_written_again_on_reconnect(chamber_controller) -> None:
    twin, url = chamber_controller
    cfg = cfg_from(f'[chamber]\nsim = false\nport = "{url}"\nmin_c = 0.0\nmax_c = 50.0\n')
    conn = connect_instrument(cfg, "chamber")
    try:
        twin.respond(b"LTL=-60.00\r")  # a power-cycled controller forgot them
        conn.instrument.reconnect()
        assert (twin.ltl_c, twin.utl_c) == (0.0, 50.0)
    finally:
        conn.close()


def test_a_controller_that_refuses_the_limits_is_an_instrument_fault(tmp_path: Path) -> None:
    """min_c below the controller's hardware range: LTL= answers ?RANGE and the connection fails, naming it."""
    import subprocess
    import sys

    root = Path(__file__).resolve().parents[2]
    cfg = tmp_path / "c.toml"
    cfg.write_text("[chamber]\nsim = true\nmin_c = -90.0\n", encoding="utf-8")
    proc = subprocess.run(
        [sys.executable, "-m", "qmg_lab", "chamber", "setpoint", str(cfg), "25"],
        cwd=root,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 3
    assert "'LTL=-90.00' refused: '?RANGE'" in " ".join(proc.stderr.split())  # rich wraps at 80 columns
    assert "Traceback" not in proc.stderr


def test_a_reply_lost_while_writing_the_limits_is_retried_at_connect(chamber_controller) -> None:
    """The first LTL= reply is lost (a timeout); the connect reconnects once ([recovery] reconnect_attempts) and
    writes the limits, instead of failing the whole station on one lost reply."""
    twin, url = chamber_controller
    lost: list[bytes] = []

    def drop_first_ltl(line: bytes, reply: bytes) -> bytes:
        if line.startswith(b"LTL=") and not lost:
            lost.append(line)
            return b""
        return reply

    twin.fault_hook = drop_first_ltl
    cfg = cfg_from(
        f'[chamber]\nsim = false\nport = "{url}"\nmin_c = 5.0\nmax_c = 45.0\ntimeout_s = 0.3\n'
        "[recovery]\nreconnect_attempts = 1\n"
    )
    conn = connect_instrument(cfg, "chamber")
    try:
        assert len(lost) == 1 and lost[0].startswith(b"LTL=5.00")  # one reply was lost (the line as framed)
        assert (twin.ltl_c, twin.utl_c) == (5.0, 45.0)
    finally:
        conn.close()


def test_the_twins_cabling_is_the_configured_wiring_field_by_field() -> None:
    text = (
        "[lockin]\ndrive_sigin = 1\nsense_sigin = 0\nrate_auxout = 2\nquadrature_auxout = 3\n"
        "rate_auxin = 1\ndither_auxin = 0\nforcer_carrier_amplitude = 0.25\n"
    )
    w = hf2_wiring(parse_config(text))
    assert (w.drive_sigin, w.sense_sigin, w.rate_auxout, w.quadrature_auxout) == (1, 0, 2, 3)
    assert (w.rate_auxin, w.dither_auxin, w.forcer_carrier_amplitude) == (1, 0, 0.25)
    assert w.forcer_mixer_channel == 1  # derived as the driver does: MF ([sim] hf2_options default) -> channel 1
