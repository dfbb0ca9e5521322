"""Fault injection (sims/faults.py) and what the campaign does about each fault (qmg_lab/campaign/runner.py).

Twin level: the injected replies have the documented forms and follow the seed; link drops stop commands
reaching the instrument; timed events act on the World at the block that contains them.
Campaign level (the short plan of tests/test_faults_helpers.py, 2 s blocks): every fault ends recovered (the
step clock pauses for a number of blocks that follows from the block grid) or in the safe state with the reason
in the file.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from typer.testing import CliRunner

from qmg_lab.campaign.runner import CampaignAborted
from qmg_lab.cli.main import app
from qmg_lab.config.schema import parse_config
from qmg_lab.station import fault_plan
from sims.chamber_twin import ChamberTwin
from sims.ds345_twin import DS345Twin
from sims.faults import GARBLE_BYTE, SENSOR_FAULT_REPLY, FaultInjector
from sims.table_twin import RateTableTwin
from sims.world import World
from tests.support.campaigns import SHORT_DURATION_S, SHORT_STEPS, config_text, run_inprocess
from tests.support.twin_params import chamber_twin_settings, fault_plan_with, paper_world, table_twin_settings

DT_S = round(210e6 / 1800.0) / 210e6  # demod sample period at 1800 Sa/s, in whole 210 MHz ticks (the HF2 twin)
BLOCK_S = round(2.0 / DT_S) * DT_S  # one twin poll of sim_poll_interval_s = 2 s: a whole number of samples


def advance_to(world: World, t_s: float, dt: float = 0.01) -> None:
    """Advance the world in 1 s blocks up to t_s (the World's own clock, no sleeping)."""
    while world.t < t_s - 1e-9:
        world.advance(int(round(min(1.0, t_s - world.t) / dt)), dt)


# ====================================================================================== twin level
def test_faults_are_off_by_default():
    assert not fault_plan(parse_config("")).any


def _sta_replies(seed: int, n: int = 400) -> list[bytes]:
    world = paper_world()
    inj = FaultInjector(world, fault_plan_with(seed=seed, serial_timeout_prob=0.3, serial_garble_prob=0.3))
    twin = RateTableTwin(world, **table_twin_settings())
    inj.attach_serial("table", twin)
    return [twin.respond(b"STA\r") for _ in range(n)]


def test_serial_reply_faults_have_the_documented_forms_and_rates():
    replies = _sta_replies(seed=5)
    healthy = b"10\r>\r"  # STA at rest: servo on (8) + at rate (2), then the prompt (1291BR protocol)
    lost = [r for r in replies if r == b""]
    garbled = [r for r in replies if bytes([GARBLE_BYTE]) in r]
    truncated = [r for r in replies if r and GARBLE_BYTE not in r and not r.endswith(b"\r")]
    ok = [r for r in replies if r == healthy]
    assert len(lost) + len(garbled) + len(truncated) + len(ok) == len(replies)
    assert all(len(r) == len(healthy) for r in garbled)  # one byte replaced, nothing added
    assert all(healthy.startswith(r) and b"\r" not in r for r in truncated)  # cut before the first CR
    # binomial counts: p = 0.3 lost, 0.15 garbled, 0.15 truncated of 400 draws; 4.5 sigma bounds
    for count, p in ((len(lost), 0.3), (len(garbled), 0.15), (len(truncated), 0.15)):
        sigma = math.sqrt(400 * p * (1 - p))
        assert abs(count - 400 * p) < 4.5 * sigma


def test_serial_faults_follow_the_seed():
    assert _sta_replies(seed=5) == _sta_replies(seed=5)
    assert _sta_replies(seed=5) != _sta_replies(seed=6)


def test_visa_reply_faults_drop_or_damage_the_reply():
    world = paper_world()
    inj = FaultInjector(world, fault_plan_with(seed=1, visa_timeout_prob=0.5, visa_garble_prob=0.5))
    twin = DS345Twin(world)
    inj.attach_ds345(twin)
    res = twin.resource()
    res.write_termination = "\n"
    outcomes = set()
    for _ in range(60):
        twin.clear()
        res.write("*IDN?")
        message = twin.read_message()
        if message is None:
            outcomes.add("timeout")
        elif bytes([GARBLE_BYTE]) in message:
            outcomes.add("garbled")
        else:
            assert not message.endswith(b"\n")  # truncated: the LF is gone, a reader times out
            outcomes.add("truncated")
    assert outcomes == {"timeout", "garbled", "truncated"}
    assert {e.kind for e in inj.events} == {"visa_timeout", "visa_garbled", "visa_truncated"}


def test_a_dropped_serial_link_reaches_nobody_then_comes_back():
    world = paper_world()
    inj = FaultInjector(world, fault_plan_with(disconnect_at_s=(10.0,), disconnect_duration_s=5.0))
    link = inj.serial_link("table", RateTableTwin(world, **table_twin_settings()))
    assert link.respond(b"JOG1\r") == b">\r"
    assert world.table.rate_command_dps == 1.0
    advance_to(world, 10.0)
    assert link.respond(b"JOG2\r") == b""  # [10, 15): nothing reaches the controller
    assert world.table.rate_command_dps == 1.0
    advance_to(world, 15.0)
    assert link.respond(b"JOG3\r") == b">\r"
    assert world.table.rate_command_dps == 3.0
    assert [e.kind for e in inj.events] == ["disconnect", "link_restored"]


def test_a_dropped_visa_link_fails_io_and_reopening():
    import pyvisa.errors

    world = paper_world()
    twin = DS345Twin(world)
    inj = FaultInjector(
        world, fault_plan_with(disconnect_at_s=(1.0,), disconnect_duration_s=2.0, disconnect_instrument="generator")
    )
    opener = inj.visa_link("generator", twin.resource)
    res = opener()
    res.read_termination = "\n"
    assert res.query("*IDN?").startswith("StanfordResearchSystems,DS345")
    advance_to(world, 1.0)
    with pytest.raises(pyvisa.errors.VisaIOError):
        res.query("*IDN?")
    with pytest.raises(pyvisa.errors.VisaIOError):
        opener()
    advance_to(world, 3.0)
    assert opener().query("*IDN?").startswith("StanfordResearchSystems,DS345")


def test_chamber_overshoot_decays_exponentially_from_the_block_that_contains_it():
    world = paper_world()
    FaultInjector(
        world, fault_plan_with(chamber_overshoot_at_s=10.5, chamber_overshoot_c=5.0, chamber_overshoot_decay_s=30.0)
    )
    advance_to(world, 10.0)
    assert world.chamber.disturbance_c == 0.0
    advance_to(world, 11.0)  # the block [10, 11) contains 10.5: set at its start, d = 5 exp(-0) (t0 < at)
    assert world.chamber.disturbance_c == 5.0
    advance_to(world, 21.0)  # last block starts at t0 = 20: d = 5 exp(-(20 - 10.5)/30)
    assert world.chamber.disturbance_c == pytest.approx(5.0 * math.exp(-9.5 / 30.0), rel=1e-12)
    assert world.chamber_air_c() == pytest.approx(world.chamber.air_c + 5.0 * math.exp(-9.5 / 30.0))


def test_chamber_sensor_dropout_answers_sensor_fault_for_its_duration():
    world = paper_world()
    inj = FaultInjector(world, fault_plan_with(chamber_dropout_at_s=2.0, chamber_dropout_duration_s=3.0))
    twin = ChamberTwin(world, **chamber_twin_settings(status_layout="flags16"))
    inj.attach_serial("chamber", twin)
    assert twin.respond(b"C1?\r") == b"25.00\r\n"
    advance_to(world, 2.0)
    assert twin.respond(b"C1?\r") == SENSOR_FAULT_REPLY
    assert twin.respond(b"SET?\r") == b"25.00\r\n"  # only the sensor is gone
    advance_to(world, 5.0)
    assert twin.respond(b"C1?\r") == b"25.00\r\n"


def test_interlock_trip_brakes_the_table():
    world = paper_world()
    FaultInjector(world, fault_plan_with(interlock_trip_at_s=3.0))
    world.set_table_rate(5.0, 300.0)
    advance_to(world, 3.0)
    assert not world.table.interlock
    advance_to(world, 4.0)
    assert world.table.interlock and world.table.rate_command_dps == 0.0


# ====================================================================================== campaign level
@pytest.fixture(scope="module")
def baseline(tmp_path_factory):
    out = run_inprocess(tmp_path_factory.mktemp("baseline"), config_text())
    assert out.error is None
    return out


def _steps_once(out) -> None:
    steps = out.run().steps
    assert sorted(steps["index"].tolist()) == list(range(SHORT_STEPS))


def test_baseline_completes_in_the_planned_time(baseline):
    s = baseline.summary
    assert s.status == "completed" and s.steps_completed == SHORT_STEPS
    assert s.simulated_s == pytest.approx(SHORT_DURATION_S, abs=2 * DT_S)
    assert baseline.world_is_safe()


def test_pll_unlock_pauses_the_step_clock(tmp_path, baseline):
    out = run_inprocess(tmp_path, config_text("pll_unlock_at_s = 45.0\npll_unlock_duration_s = 3.0"))
    assert out.error is None and out.summary.status == "completed"
    # unlock from the start of the block [45, 47) for 3 s: blocks [45, 47) and [47, 49) report unlock -> +4 s
    assert out.summary.simulated_s - baseline.summary.simulated_s == pytest.approx(2 * BLOCK_S, abs=1e-6)
    assert out.summary.suspensions == 1
    _steps_once(out)


def test_sample_loss_is_counted_and_leaves_a_gap(tmp_path, baseline):
    out = run_inprocess(tmp_path, config_text("sample_loss_at_s = [40.0, 60.0]\nsample_loss_count = 100"))
    assert out.error is None and out.summary.status == "completed"
    assert out.summary.samples_lost == 200
    t = out.run().groups["lockin"]["time"]
    # a step's clock counts the samples received, so the run is 200 sample periods longer, same sample count
    assert len(t) == len(baseline.run().groups["lockin"]["time"])
    assert out.summary.simulated_s - baseline.summary.simulated_s == pytest.approx(200 * DT_S, rel=1e-3)
    gaps = np.diff(t)[np.diff(t) > 1.5 * DT_S]
    assert gaps == pytest.approx([101 * DT_S, 101 * DT_S], rel=1e-3)


@pytest.mark.parametrize(
    "faults, extra_s",
    [
        # link down [40, 45): the table read at 41 fails, blocks ending 43 and 45 are logged suspended; the retry at
        # 45 succeeds; the three blocks [39, 45) do not count -> +6 s
        ("disconnect_at_s = [40.0]\ndisconnect_duration_s = 5.0", 6.0),
        # the same grid for the chamber link and for the chamber's sensor (C1? refused in [40, 45))
        ("disconnect_at_s = [40.0]\ndisconnect_duration_s = 5.0\ndisconnect_instrument = 'chamber'", 6.0),
        ("chamber_dropout_at_s = 40.0\nchamber_dropout_duration_s = 5.0", 6.0),
        # generator down [1, 5): the dither step's FUNC at t = 2 fails; retries after the blocks ending 4 and 6;
        # the one at 6 succeeds -> the two blocks [2, 6) do not count -> +4 s
        ("disconnect_at_s = [1.0]\ndisconnect_duration_s = 4.0\ndisconnect_instrument = 'generator'", 4.0),
    ],
)
def test_a_link_that_comes_back_is_recovered(tmp_path, baseline, faults, extra_s):
    out = run_inprocess(tmp_path, config_text(faults))
    assert out.error is None, out.error
    s = out.summary
    assert s.status == "completed" and s.recoveries >= 1 and s.suspensions >= 1
    assert s.simulated_s - baseline.summary.simulated_s == pytest.approx(extra_s / 2.0 * BLOCK_S, abs=1e-6)
    assert s.faults_injected and s.faults_injected[0]["time_s"] >= 1.0
    _steps_once(out)
    assert out.world_is_safe()


def test_no_reading_is_invented_while_the_table_is_away(tmp_path):
    out = run_inprocess(tmp_path, config_text("disconnect_at_s = [40.0]\ndisconnect_duration_s = 5.0"))
    t = out.run().groups["table"]["time"]
    assert not np.any((t > 40.0) & (t <= 45.0))
    assert np.all(np.diff(t) > 0)


def test_chamber_overshoot_suspends_until_back_in_band(tmp_path, baseline):
    out = run_inprocess(
        tmp_path,
        config_text("chamber_overshoot_at_s = 40.0\nchamber_overshoot_c = 5.0\nchamber_overshoot_decay_s = 30.0"),
    )
    assert out.error is None and out.summary.status == "completed" and out.summary.suspensions == 1
    _steps_once(out)
    # the air physics is the same in both runs (every rate step targets 26 degC); the reading at the end of
    # the block [t0, t0 + 2) carries the disturbance 5 exp(-max(0, t0 - 40)/30) set at the block start
    f, b = out.run().groups["chamber"], baseline.run().groups["chamber"]
    common, i_f, i_b = np.intersect1d(np.round(f["time"], 6), np.round(b["time"], 6), return_indices=True)
    sel = (common > 27.5) & (common < 100.0)
    t0 = common[sel] - 2.0
    expected = np.where(t0 + 2.0 > 40.0, 5.0 * np.exp(-np.maximum(0.0, t0 - 40.0) / 30.0), 0.0)
    diff = f["temperature"][i_f[sel]] - b["temperature"][i_b[sel]]
    assert diff == pytest.approx(expected, abs=0.0101)  # each reading is rounded to 0.01 degC by C1?
    # suspended while the reading is out of the 2 degC band: it ends when 5 exp(-(t0-40)/30) + (air - sp) < 2
    assert out.summary.simulated_s > baseline.summary.simulated_s + 30.0 * math.log(5.0 / 3.0)


def test_random_transaction_faults_are_all_recovered(tmp_path):
    out = run_inprocess(
        tmp_path,
        config_text(
            "serial_timeout_prob = 0.02\nserial_garble_prob = 0.02\nvisa_timeout_prob = 0.05\nvisa_garble_prob = 0.05"
        ),
    )
    assert out.error is None and out.summary.status == "completed"
    kinds = {f["kind"] for f in out.summary.faults_injected}
    assert {"serial_timeout", "serial_garbled", "serial_truncated"} <= kinds
    assert len(out.summary.faults_injected) >= 10
    assert out.summary.recoveries >= 1
    _steps_once(out)
    assert out.world_is_safe()


def test_interlock_trip_aborts_to_the_safe_state(tmp_path):
    out = run_inprocess(tmp_path, config_text("interlock_trip_at_s = 50.0"))
    assert isinstance(out.error, CampaignAborted) and "interlock" in str(out.error)
    run = out.run()
    assert run.status == "aborted" and "interlock" in run.attrs["abort_reason"]
    # steps 0-4 end at 47 s; the trip lands in the block [49, 51) of step 5
    assert sorted(run.steps["index"].tolist()) == [0, 1, 2, 3, 4]
    assert out.world_is_safe()


def test_a_link_that_stays_down_aborts_after_the_recovery_timeout(tmp_path):
    out = run_inprocess(tmp_path, config_text("disconnect_at_s = [40.0]\ndisconnect_duration_s = 40.0"))
    assert isinstance(out.error, CampaignAborted)
    reason = out.run().attrs["abort_reason"]
    assert "table not recovered within recovery.timeout_s = 30 s" in reason
    assert out.summary.safe_state_confirmed  # the link came back at 80 s, inside safe_state_timeout_s
    assert out.world_is_safe()


def test_an_unreachable_instrument_is_reported_not_confirmed(tmp_path):
    text = config_text(
        "disconnect_at_s = [40.0]\ndisconnect_duration_s = 3600.0",
        extra="[recovery]\ntimeout_s = 4.0\nsafe_state_timeout_s = 4.0\n",
    )
    out = run_inprocess(tmp_path, text)
    assert isinstance(out.error, CampaignAborted)
    assert not out.summary.safe_state_confirmed
    reason = out.run().attrs["abort_reason"]
    assert "safe state not confirmed: table" in reason
    # everything that can still be reached is safe; the table keeps its last command (5 or -5 deg/s)
    assert out.world.dither.amplitude_vpp == 0.0 and out.world.chamber.target_c == 20.0
    assert abs(out.world.table.rate_command_dps) == 5.0


def test_cli_exit_code_3_names_the_fault(tmp_path):
    cfg = tmp_path / "c.toml"
    cfg.write_text(config_text("interlock_trip_at_s = 50.0"))
    result = CliRunner().invoke(app, ["run", str(cfg), "-o", str(tmp_path / "r.h5"), "-q"])
    assert result.exit_code == 3
    assert "interlock" in result.output and "Traceback" not in result.output
