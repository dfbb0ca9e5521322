"""The HF2LI driver running unchanged through zhinst.toolkit.Session(connection=twin): the real toolkit code
path (node tree from its bundled HF2 nodedoc, set_transaction, subscribe/poll) against the data-server twin.

Expected numbers: qmg_lab.campaign.loops gain design for a default Config (paper eq. 5 as implemented there), the HF2
clock (the HF2 rate 1800 Sa/s as whole 210 MHz ticks: 116667 ticks per sample) and the documented channel assignment
(drivers/hf2_nodes.py, docs/wiring.md).
"""

from __future__ import annotations

import itertools
import math
from dataclasses import replace
from typing import Any

import numpy as np
import pytest
from zhinst.toolkit import Session

from drivers.hf2li import HF2LI
from qmg_lab.campaign.loops import agc_pi, lockin_setup, pll_pi, quadrature_pi, rate_pi
from qmg_lab.config.schema import Config
from qmg_lab.instruments import LimitError
from qmg_lab.station import hf2_wiring
from sims.hf2_server import HF2DataServerTwin
from sims.world import World
from tests.support.twin_params import hf2_twin_settings, paper_gyro_params, paper_world

DEV = "/dev1234"
# rate PID of the default critically damped design (qmg_lab/config/rate_loop.py rate_loop_design): P = (2p - 1/tau) / b,
# p = 2 pi 2 Hz / sqrt(3 + sqrt 10), 1/tau = 2 pi 2200 / (2 * 1.2e6), b = k R_d / SF = 0.8 * 0.5 / (0.06 * 180/pi):
# 86.96 V/Vrms
RATE_P = (
    (2 * 2 * math.pi * 2.0 / math.sqrt(3 + math.sqrt(10)) - 2 * math.pi * 2200 / 2.4e6) * (0.06 * 180 / math.pi) / 0.4
)
RATE = 210e6 / round(210e6 / 1800.0)  # the configured 1800 Sa/s as the HF2 twin applies it: whole clock ticks


class CountingTwin(HF2DataServerTwin):
    """The twin, recording every set call the driver makes (to count transactions)."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.set_calls: list[Any] = []

    def set(self, path: Any, value: Any = None, **kwargs: Any) -> None:
        self.set_calls.append(path if value is None else [(path, value)])
        super().set(path, value, **kwargs)


def bench(cfg: Config | None = None) -> tuple[Config, World, CountingTwin, HF2LI]:
    cfg = cfg or Config()
    lk = cfg.lockin
    world = paper_world()
    wiring = hf2_wiring(cfg)  # the [lockin] wiring, as the station passes it to the twin
    twin = CountingTwin(world, paper_gyro_params(), seed=7, wiring=wiring, **hf2_twin_settings())
    session = Session("localhost", hf2=True, connection=twin)
    li = HF2LI(session, "dev1234", lk, output_safe_v=lk.output_safe_v)
    return cfg, world, twin, li


def pid_nodes(twin: HF2DataServerTwin, n: int) -> dict[str, float]:
    return {k: twin.getDouble(f"{DEV}/pids/{n}/{k}") for k in ("p", "i", "setpoint", "center", "range")}


def test_identify_names_device_options_and_server() -> None:
    _, _, _, li = bench()
    ident = li.identify()
    assert "HF2LI" in ident and "DEV1234" in ident and "HF2 data server 26.07" in ident
    assert "PLL" in ident and "PID" in ident


def test_configure_writes_the_loop_gains_in_one_transaction() -> None:
    cfg, _, twin, li = bench()
    li.configure(lockin_setup(cfg))
    assert len(twin.set_calls) == 1 and len(twin.set_calls[0]) > 50
    dev, lp = cfg.device, cfg.loops
    expected = {
        0: agc_pi(dev, lp.agc_bandwidth_hz, lp.agc_zero_offset_hz),
        1: rate_pi(dev, lp.rate_bandwidth_hz, lp.rate_zero_offset_hz, lp.sense_pi_design),
        2: quadrature_pi(dev, lp.quadrature_bandwidth_hz, lp.sense_pi_design),
    }
    for n, g in expected.items():
        got = pid_nodes(twin, n)
        assert got == pytest.approx(
            {"p": g.p, "i": g.i, "setpoint": g.setpoint, "center": g.center, "range": g.range}, rel=1e-12
        )
        assert twin.getInt(f"{DEV}/pids/{n}/enable") == 1
    assert twin.getDouble(f"{DEV}/pids/1/p") == pytest.approx(RATE_P, rel=1e-12)
    pll = pll_pi(dev.f0_hz, lp.pll_bandwidth_hz, lp.pll_damping)
    assert twin.getDouble(f"{DEV}/plls/0/p") == pytest.approx(pll.p, rel=1e-12)
    assert twin.getDouble(f"{DEV}/plls/0/i") == pytest.approx(pll.i, rel=1e-12)
    assert twin.getDouble(f"{DEV}/plls/0/setpoint") == pll.setpoint
    assert twin.getDouble(f"{DEV}/plls/0/freqcenter") == 2200.0
    assert twin.getDouble(f"{DEV}/plls/0/freqrange") == pytest.approx(pll.range)
    assert twin.getInt(f"{DEV}/plls/0/enable") == 1


def test_configure_wires_inputs_outputs_and_auxouts_as_documented() -> None:
    cfg, _, twin, li = bench()
    li.configure(lockin_setup(cfg))
    g = twin.getInt
    assert (
        g(f"{DEV}/pids/0/input"),
        g(f"{DEV}/pids/0/inputchannel"),
        g(f"{DEV}/pids/0/output"),
        g(f"{DEV}/pids/0/outputchannel"),
    ) == (2, 0, 0, 0)  # R of demod 0 -> SigOut1 amplitude, channel 0
    assert (
        g(f"{DEV}/pids/1/input"),
        g(f"{DEV}/pids/1/inputchannel"),
        g(f"{DEV}/pids/1/output"),
        g(f"{DEV}/pids/1/outputchannel"),
    ) == (0, 1, 3, 0)  # X of demod 1 -> AuxOut 1
    assert (
        g(f"{DEV}/pids/2/input"),
        g(f"{DEV}/pids/2/inputchannel"),
        g(f"{DEV}/pids/2/output"),
        g(f"{DEV}/pids/2/outputchannel"),
    ) == (1, 1, 3, 1)  # Y of demod 1 -> AuxOut 2
    assert g(f"{DEV}/demods/0/adcselect") == 0 and g(f"{DEV}/demods/1/adcselect") == 1
    osc = g(f"{DEV}/plls/0/oscselect")
    assert g(f"{DEV}/demods/0/oscselect") == osc and g(f"{DEV}/demods/1/oscselect") == osc
    assert twin.getDouble(f"{DEV}/demods/1/rate") == RATE
    assert g(f"{DEV}/auxouts/0/outputselect") == -1 and g(f"{DEV}/auxouts/1/outputselect") == -1
    assert twin.getDouble(f"{DEV}/sigouts/1/amplitudes/1") == 0.5  # nominal carrier, gain 1
    from sims.hf2_loops import identify_loops  # how the twin's physics reads these nodes

    plan = identify_loops(twin.nodes, twin.wiring)
    assert plan.open_reasons == {} and plan.pid_of == {"agc": 0, "rate": 1, "quadrature": 2}
    assert plan.settings.forcer_gain == 1.0


def test_commands_outside_limits_are_refused_before_anything_is_sent() -> None:
    cfg, _, twin, li = bench()
    good = lockin_setup(cfg)
    bad = [
        replace(good, forcer_gain=2.5),
        replace(good, demod_order=9),
        replace(good, rate=replace(good.rate, range=12.0)),
        replace(good, demod_rate_hz=0.0),
    ]
    for setup in bad:
        with pytest.raises(LimitError):
            li.configure(setup)
    with pytest.raises(LimitError, match=r"forcer_gain = 0.4 .*\[0.5, 2\]"):
        li.set_forcer_gain(0.4)
    with pytest.raises(LimitError, match="forcer_gain"):
        li.set_forcer_gain(float("nan"))
    assert twin.set_calls == []


def test_forcer_amplitude_above_full_range_is_refused() -> None:
    cfg = Config().model_copy(update={"lockin": Config().lockin.model_copy(update={"forcer_carrier_amplitude": 0.8})})
    _, _, twin, li = bench(cfg)
    with pytest.raises(LimitError, match=r"above the limit 1\.0"):
        li.set_forcer_gain(1.5)  # 0.8 * 1.5 = 1.2 of range
    assert twin.set_calls == []


def test_set_forcer_gain_scales_the_carrier() -> None:
    cfg, _, twin, li = bench()
    li.configure(lockin_setup(cfg))
    li.set_forcer_gain(1.1)
    assert twin.getDouble(f"{DEV}/sigouts/1/amplitudes/1") == pytest.approx(0.55)
    from sims.hf2_loops import identify_loops

    assert identify_loops(twin.nodes, twin.wiring).settings.forcer_gain == pytest.approx(1.1)


def test_poll_yields_samples_at_the_rate_with_monotonic_time() -> None:
    cfg, world, _twin, li = bench()
    li.configure(lockin_setup(cfg))
    li.start_stream()
    blocks = [li.poll(0.5) for _ in range(3)]
    t = np.concatenate([b.time for b in blocks])
    assert [len(b) for b in blocks] == [900, 900, 900]  # round(0.5 s * RATE)
    assert t[0] == 0.0
    assert np.allclose(np.diff(t), 1 / RATE, rtol=0, atol=1e-12)
    assert all(b.samples_lost == 0 for b in blocks)
    for b in blocks:
        assert all(len(getattr(b, f)) == len(b) for f in b.FIELDS)
    assert world.t == pytest.approx(3 * 900 / RATE, abs=1e-12)  # 3 polls of round(0.5 s * RATE) samples


def test_samples_lost_equals_the_injected_drop() -> None:
    cfg, _, twin, li = bench()
    li.configure(lockin_setup(cfg))
    li.start_stream()
    li.poll(0.5)
    twin.drop_samples(13)
    b = li.poll(0.5)
    assert b.samples_lost == 13 and len(b) == 900 - 13
    assert li.poll(0.5).samples_lost == 0


def _lost_by_definition(ticks: np.ndarray, last_ts: int | None, ticks_per_sample: float) -> int:
    """The module docstring's count, gap by gap in Python: sum of max(rint(gap / ticks_per_sample) - 1, 0) over
    the gaps between consecutive timestamps, the first one from the previous block's last sample."""
    edges = ([] if last_ts is None else [last_ts]) + [int(v) for v in ticks]
    return sum(max(int(np.rint((b - a) / ticks_per_sample)) - 1, 0) for a, b in itertools.pairwise(edges))


@pytest.mark.parametrize("last_ts", [None, 10_000_000])
def test_lost_samples_are_the_gap_count_of_the_definition_for_any_gaps(last_ts: int | None) -> None:
    """_count_lost against the definition for gap patterns on both sides of every rounding boundary: whole-sample
    gaps, gaps of 1.5 samples (rint to even: 2, one lost) and just below, a first gap (from the previous block)
    that alone loses samples, out-of-order and repeated timestamps, single samples and an empty block."""
    _, _, _, li = bench()
    m = 116667.0
    li._ticks_per_sample = m
    rng = np.random.default_rng(3)
    start = 10_000_000 + int(m)
    patterns: list[list[float]] = [
        [1.0] * 50,
        [1.0, 1.5, 1.0],
        [1.0, 1.4999, 1.0],
        [1.0, 2.5, 1.0, 3.0],
        [1.0, 0.0, 1.0],
        [1.0, -1.0, 2.0],
        [1.0],
        [],
        list(rng.choice([1.0, 1.0, 1.0, 2.0, 1.5, 7.0, 0.5], size=400)),
    ]
    for gaps in patterns:
        for first in (0, 1, 3):  # the block starts right after the previous one, or `first` samples later
            offsets = np.concatenate(([0.0], np.cumsum(gaps))) if gaps or first != 3 else np.zeros(0)
            ticks = (start + first * int(m) + np.round(offsets * m)).astype(np.int64)
            li._last_ts = last_ts
            expected = _lost_by_definition(ticks, last_ts, m)
            assert li._count_lost(ticks) == expected, (gaps, first)
    li._last_ts = last_ts
    assert li._count_lost(np.zeros(0, dtype=np.int64)) == 0


def test_timestamps_are_read_as_the_int64_values_astype_gives() -> None:
    from drivers.hf2li import _as_int64

    ts = np.array([0, 1, 116667, 2**62 + 5, 2**63 - 1, 2**63, 2**64 - 1], dtype=np.uint64)
    np.testing.assert_array_equal(_as_int64(ts), ts.astype(np.int64))
    np.testing.assert_array_equal(_as_int64(ts[::2]), ts[::2].astype(np.int64))  # a strided view too
    small = np.array([3, 4], dtype=np.uint32)
    assert _as_int64(small).dtype == np.int64 and list(_as_int64(small)) == [3, 4]


def test_poll_before_start_stream_is_an_error() -> None:
    from qmg_lab.instruments import InstrumentError

    _, _, _, li = bench()
    with pytest.raises(InstrumentError, match="start_stream"):
        li.poll(0.5)


def test_safe_state_is_idempotent_and_opens_every_loop() -> None:
    cfg, _, twin, li = bench()
    li.configure(lockin_setup(cfg))
    li.start_stream()
    li.safe_state()
    first = {p: v for p, v in twin.nodes.values.items()}
    li.safe_state()
    assert twin.nodes.values == first
    assert all(twin.getInt(f"{DEV}/pids/{n}/enable") == 0 for n in range(4))
    assert twin.getInt(f"{DEV}/sigouts/0/on") == 0 and twin.getInt(f"{DEV}/sigouts/1/on") == 0
    assert twin.getDouble(f"{DEV}/sigouts/1/amplitudes/1") == 0.0
    for ch in (0, 1):
        assert twin.getDouble(f"{DEV}/auxouts/{ch}/offset") == cfg.lockin.output_safe_v
    from sims.hf2_loops import identify_loops

    plan = identify_loops(twin.nodes, twin.wiring)
    assert plan.pid_of == {"agc": None, "rate": None, "quadrature": None}
    assert plan.settings.forcer_gain == 0.0 and plan.settings.agc.center == 0.0


def test_reconnect_restores_the_configuration() -> None:
    cfg, _, twin, li = bench()
    li.configure(lockin_setup(cfg))
    li.set_forcer_gain(1.2)
    twin.set(f"{DEV}/pids/1/p", 0.0)  # somebody changed the instrument while the link was down
    li.reconnect()
    assert twin.getDouble(f"{DEV}/pids/1/p") == pytest.approx(RATE_P, rel=1e-12)
    assert twin.getDouble(f"{DEV}/sigouts/1/amplitudes/1") == pytest.approx(0.6)


def test_state_is_json_serialisable() -> None:
    import json

    cfg, _, _, li = bench()
    li.configure(lockin_setup(cfg))
    st = json.loads(json.dumps(li.state()))
    assert st["pids"]["rate"]["p"] == pytest.approx(RATE_P) and st["pll"]["enable"] == 1
