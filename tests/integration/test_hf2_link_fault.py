"""The HF2 link in the twins' fault injection ([sim.faults] hf2_disconnect_at_s; sims/faults.py) and what the
campaign does about it (qmg_lab/campaign/recovery.py: the lock-in's stream is the clock, so its calls are
reconnected and retried at once, `recovery.reconnect_attempts` times, and otherwise the campaign aborts to the
safe state).

The twin drops the link at its connection boundary, so the real zhinst-toolkit session and the real HF2LI driver
see what a client of a broken data-server link sees: zhinst-core's ConnectionError (a RuntimeError) from every
call. The instrument runs on meanwhile: each failed call lets world time pass by what the host waited for it (a
poll its recording time, any other call hf2_call_timeout_s = 1 s), so the arithmetic below follows from the
block grid of tests/support/campaigns.py (2 s blocks, edges at odd seconds from 7 s on).
"""

from __future__ import annotations

import contextlib
from pathlib import Path

import h5py
import numpy as np
import pytest
from typer.testing import CliRunner
from zhinst.core.errors import ConnectionError as ZIConnectionError

from qmg_lab.campaign.loops import lockin_setup
from qmg_lab.cli.main import app
from qmg_lab.config.schema import parse_config
from qmg_lab.instruments import InstrumentError
from qmg_lab.station import connect_instrument, make_world
from qmg_lab.storage.records import read_events
from qmg_lab.storage.writer import read_run
from tests.support.campaigns import SHORT_DURATION_S, SHORT_STEPS, config_text, run_inprocess

CALL_TIMEOUT_S = 1.0  # [sim.faults] hf2_call_timeout_s, the default
DT_S = round(210e6 / 1800.0) / 210e6  # demod sample period at 1800 Sa/s, in whole 210 MHz ticks (the HF2 twin)


# ====================================================================================== twin and driver
@pytest.fixture
def lockin_with_drop():
    """The HF2LI driver on the twin, configured and streaming, with the link down for world time [3, 6) s."""
    cfg = parse_config(
        "[lockin]\nsim = true\n[sim.faults]\nhf2_disconnect_at_s = [3.0]\nhf2_disconnect_duration_s = 3.0\n"
    )
    world = make_world(cfg)
    conn = connect_instrument(cfg, "lockin", world)
    lockin = conn.instrument
    lockin.configure(lockin_setup(cfg))
    lockin.start_stream()
    yield lockin, world
    with contextlib.suppress(InstrumentError):  # a test that ends inside the drop cannot unsubscribe
        conn.close()


def test_the_dropped_link_raises_what_zhinst_core_raises(lockin_with_drop):
    lockin, world = lockin_with_drop
    server = lockin._session.daq_server  # the data-server connection the toolkit session talks to
    locked = f"/{lockin.device_id}/plls/0/locked"
    lockin.poll(1.0)
    lockin.poll(1.0)
    server.getInt(locked)  # t = 2: up
    with pytest.raises(InstrumentError, match="poll failed: Connection to the data server at localhost:8005 lost"):
        lockin.poll(1.0)  # the poll [2, 3) runs; its status read at t = 3 is refused (+1 s)
    assert world.now() == pytest.approx(4.0, abs=1e-3)
    with pytest.raises(ZIConnectionError, match="Connection to the data server at localhost:8005 lost") as err:
        server.getInt(locked)  # refused at 4 (+1 s)
    assert isinstance(err.value, RuntimeError)  # what the toolkit and the driver catch
    with pytest.raises(InstrumentError):
        lockin.poll(1.0)  # the poll itself refused at 5: the host waited its recording time, 1 s
    assert world.now() == pytest.approx(6.0, abs=1e-3)  # the instrument ran on all along
    assert server.getInt(locked) in (0, 1)  # t = 6: the link is back


def test_a_reconnect_while_down_fails_and_the_next_one_restarts_the_stream(lockin_with_drop):
    lockin, world = lockin_with_drop
    lockin.poll(2.0)
    with pytest.raises(InstrumentError):
        lockin.poll(1.0)  # [2, 3) polled, its status read refused at 3 -> 4
    with pytest.raises(InstrumentError, match="HF2 data server at localhost:8005"):
        lockin.reconnect()  # the new session's first call refused at 4 -> 5
    with pytest.raises(InstrumentError):
        lockin.reconnect()  # refused at 5 -> 6
    lockin.reconnect()  # at 6 the link is back: a new session, configured, and the stream the campaign had
    block = lockin.poll(1.0)
    assert abs(len(block) - 1800) <= 1  # 1 s at 1800 Sa/s: the stream runs again
    assert world.now() == pytest.approx(7.0, abs=1e-3)


def test_each_refused_call_lets_the_configured_time_pass(lockin_with_drop):
    lockin, world = lockin_with_drop
    server = lockin._session.daq_server
    lockin.poll(2.0)
    with pytest.raises(InstrumentError):
        lockin.poll(1.0)  # down from 3; at 4 after the refused status read
    refused = 0
    while True:
        try:
            server.getInt(f"/{lockin.device_id}/plls/0/locked")
            break
        except RuntimeError:
            refused += 1
    assert refused == round((6.0 - 4.0) / CALL_TIMEOUT_S)  # refused at 4 and 5, answered at 6
    assert world.now() == pytest.approx(6.0, abs=1e-3)


# ====================================================================================== the campaign
def _events(path: Path) -> list[tuple[str, str]]:
    """(instrument, kind) of every /events row of the run file."""
    with h5py.File(path, "r") as h5:
        return [(e["instrument"], e["kind"]) for e in read_events(h5)]


def test_a_short_hf2_link_drop_is_reconnected_and_the_campaign_completes(tmp_path):
    """Link down [40, 43): the block [39, 41) is polled before the drop, its status reads at t = 41 are refused
    (+1 s -> 42); the first reconnect is refused (42 -> 43); the second finds the link back and the block is polled
    again: 2 reconnects, 1 recovery, every step completed."""
    out = run_inprocess(tmp_path, config_text("hf2_disconnect_at_s = [40.0]\nhf2_disconnect_duration_s = 3.0"))
    assert out.error is None, out.error
    summary = out.summary
    assert summary.status == "completed" and summary.steps_completed == SHORT_STEPS
    assert (summary.reconnects, summary.recoveries) == (2, 1)
    lockin_events = [k for i, k in _events(out.path) if i == "lockin"]
    assert lockin_events == ["fault", "reconnect", "fault", "reconnect", "recovered"]
    injected = [(f["kind"], f["instrument"], round(f["time_s"], 3)) for f in summary.faults_injected]
    assert injected == [("disconnect", "lockin", 41.0), ("link_restored", "lockin", 43.0)]
    assert out.world_is_safe()
    # the host missed [39, 43): the block whose status reads failed and the two refused calls. The device's clock
    # ran on, so the restarted stream continues its timestamps: one gap of 4 s + one sample period in /lockin/time,
    # its samples counted as lost (CLSF restarts its periods after it), and the run 4 s longer than without the drop
    t = out.run().groups["lockin"]["time"]
    steps = np.diff(t)
    gaps = steps[steps > 1.5 * DT_S]
    assert gaps == pytest.approx([4.0 + DT_S], abs=DT_S / 2)
    assert summary.samples_lost == round(4.0 / DT_S)
    assert t[:-1][steps > 1.5 * DT_S] == pytest.approx([39.0], abs=DT_S)
    assert summary.simulated_s == pytest.approx(SHORT_DURATION_S + 4.0, abs=2 * DT_S)


def test_a_long_hf2_link_drop_aborts_with_exit_3_and_names_the_lockin_not_confirmed(tmp_path):
    """Link down [40, 70): the reconnects are refused at 42, 43, 44; the campaign aborts. The table, the DS345 and
    the chamber reach their safe state (their links are up); the lock-in cannot be told, and the file says so:
    the lock-in is the only instrument whose safe state is not confirmed."""
    config = tmp_path / "drop.toml"
    config.write_text(config_text("hf2_disconnect_at_s = [40.0]\nhf2_disconnect_duration_s = 30.0"))
    path = tmp_path / "r.h5"
    result = CliRunner().invoke(app, ["run", str(config), "--sim", "-o", str(path), "-q"])
    assert result.exit_code == 3, result.output
    said = " ".join(result.output.split())
    assert "instrument fault: lockin: HF2 data server at localhost:8005" in said and "Traceback" not in said
    run = read_run(path)
    reason = run.attrs["abort_reason"]
    assert run.status == "aborted" and "gave up after 3 reconnections" in reason
    assert "Connection to the data server at localhost:8005 lost" in reason
    not_confirmed = reason.split("safe state not confirmed: ")[1]
    assert not_confirmed.startswith("lockin:")
    assert not any(f"{name}:" in not_confirmed for name in ("table", "chamber", "generator"))
    assert [k for i, k in _events(path) if i == "lockin"] == ["fault"] + ["reconnect", "fault"] * 3
    assert sorted(run.steps["index"].tolist()) == [0, 1, 2, 3]  # the steps done before 39 s, kept


def test_hf2_link_settings_are_validated():
    for text, key in (
        ("hf2_disconnect_at_s = [-1.0]", "sim.faults.hf2_disconnect_at_s"),
        ("hf2_disconnect_duration_s = inf", "sim.faults.hf2_disconnect_duration_s"),
        ("hf2_call_timeout_s = 0", "sim.faults.hf2_call_timeout_s"),
    ):
        with pytest.raises(ValueError, match=key):
            parse_config(f"[sim.faults]\n{text}\n")
