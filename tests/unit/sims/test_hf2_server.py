"""The HF2 data-server twin at its connection boundary (the ziDAQServer API level 1 that toolkit uses).

Expected values come from the HF2 node documentation (zhinst-toolkit's nodedoc_hf2.json), the HF2 manual's
instance counts, and the twin's documented protocol (sims/hf2_server.py module docstring).
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from qmg_lab.config.schema import ConfigError, parse_config
from sims.gyro import GyroParams
from sims.hf2_server import AUXIN_ADC_RATE_HZ, HF2DataServerTwin
from sims.world import DITHER_SQUARE, World
from tests.support.twin_params import hf2_twin_settings, paper_gyro_params, paper_wiring, paper_world

DEV = "/dev1234"


def make_twin(
    rate_set: str = "ticks", params: GyroParams | None = None, **wiring: int
) -> tuple[World, HF2DataServerTwin]:
    """The protocol tests stream at 1400 Sa/s (whole clock ticks): rate_set "ticks" offers any clockbase/integer
    rate; the HF2's own rate ladder is tested on its own."""
    world = paper_world()
    twin = HF2DataServerTwin(
        world,
        params or paper_gyro_params(),
        seed=3,
        wiring=paper_wiring(**wiring),
        **hf2_twin_settings(rate_set=rate_set),
    )
    twin.connectDevice("dev1234", "USB")
    return world, twin


def stream_demods(twin: HF2DataServerTwin, rate_hz: float = 1400.0) -> None:
    twin.set(
        [
            (f"{DEV}/demods/0/rate", rate_hz),
            (f"{DEV}/demods/1/rate", rate_hz),
            (f"{DEV}/demods/1/adcselect", 1),
            (f"{DEV}/demods/0/enable", 1),
            (f"{DEV}/demods/1/enable", 1),
        ]
    )
    twin.subscribe([f"{DEV}/demods/0/sample", f"{DEV}/demods/1/sample"])


# ------------------------------------------------------------------ identity and node tree


def test_identifies_as_hf2_data_server_and_hf2li() -> None:
    _, twin = make_twin()
    assert twin.getString("/zi/about/dataserver") == "HF2DataServer"
    assert twin.getString(f"{DEV}/features/devtype") == "HF2LI"
    assert set(twin.getString(f"{DEV}/features/options").split("\n")) == {"MF", "PLL", "PID"}
    assert twin.getInt(f"{DEV}/clockbase") == 210_000_000
    assert twin.api_level == 1 and twin.port == 8005


def test_list_nodes_has_the_hf2li_instances() -> None:
    _, twin = make_twin()
    nodes = twin.listNodes(f"{DEV}/*", recursive=True, leavesonly=True)
    assert all(n == n.upper() for n in nodes)
    samples = sorted(n for n in nodes if n.endswith("/SAMPLE") and "/DEMODS/" in n)
    assert samples == [f"/DEV1234/DEMODS/{d}/SAMPLE" for d in range(6)]
    assert sorted({n.split("/")[3] for n in nodes if "/PIDS/" in n}) == ["0", "1", "2", "3"]
    assert sorted({n.split("/")[3] for n in nodes if "/PLLS/" in n}) == ["0", "1"]
    assert sum(1 for n in nodes if "/SIGOUTS/0/AMPLITUDES/" in n) == 8
    assert f"{DEV.upper()}/AUXINS/0/VALUES/1" in nodes


def test_list_nodes_json_is_not_available_like_hf2() -> None:
    _, twin = make_twin()
    with pytest.raises(RuntimeError, match="listNodesJSON"):
        twin.listNodesJSON(f"{DEV}/*")


def test_unknown_device_and_node_are_refused() -> None:
    _, twin = make_twin()
    with pytest.raises(RuntimeError, match="not found"):
        twin.connectDevice("dev9", "USB")
    with pytest.raises(RuntimeError, match="ZIAPINotFoundException"):
        twin.getDouble(f"{DEV}/demods/9/rate")
    with pytest.raises(RuntimeError, match="ZIAPINotFoundException"):
        twin.set(f"{DEV}/nosuch/node", 1)


def test_read_only_and_enumerated_nodes_are_enforced() -> None:
    _, twin = make_twin()
    with pytest.raises(RuntimeError, match="read-only"):
        twin.set(f"{DEV}/plls/0/locked", 1)
    with pytest.raises(RuntimeError, match=r"0\.01, 0\.1, 1, 10"):
        twin.set(f"{DEV}/sigouts/0/range", 5)
    twin.set(f"{DEV}/sigouts/0/range", 10)
    assert twin.getDouble(f"{DEV}/sigouts/0/range") == 10.0


def test_a_node_read_again_gives_its_current_value_and_the_same_refusals() -> None:
    """The second read of a path takes the twin's shortcut: it sees every change of the value, in any spelling
    of the path, and a disconnected device or a stream/branch node is refused as on the first read."""
    _, twin = make_twin()
    for path in (f"{DEV}/pids/0/p", f"{DEV.upper()}/PIDS/0/P", "pids/0/p"):
        twin.set(f"{DEV}/pids/0/p", 1.5)
        assert twin.getDouble(path) == 1.5
        twin.set(f"{DEV}/pids/0/p", -2.0)
        assert twin.getDouble(path) == -2.0
        assert twin.getInt(path) == -2
    with pytest.raises(RuntimeError, match="cannot be read as a value"):
        twin.getDouble(f"{DEV}/demods/0/sample")
    with pytest.raises(RuntimeError, match="cannot be read as a value"):
        twin.getDouble(f"{DEV}/demods/0/sample")
    twin.disconnectDevice("dev1234")
    with pytest.raises(RuntimeError, match="not connected"):
        twin.getDouble(f"{DEV}/pids/0/p")
    twin.connectDevice("dev1234", "USB")
    assert twin.getDouble(f"{DEV}/pids/0/p") == -2.0


def test_list_set_is_validated_before_any_node_changes() -> None:
    _, twin = make_twin()
    with pytest.raises(RuntimeError):
        twin.set([(f"{DEV}/pids/0/p", 3.0), (f"{DEV}/pids/0/input", 99)])
    assert twin.getDouble(f"{DEV}/pids/0/p") == 0.0


@pytest.mark.parametrize("asked, ticks", [(1400.0, 150_000), (1000.0, 210_000), (1234.5, 170_109)])
def test_demod_rate_is_rounded_to_whole_clock_ticks(asked: float, ticks: int) -> None:
    # rate = clockbase / round(clockbase / asked): 210e6/1234.5 = 170109.35 -> 170109 ticks
    _, twin = make_twin()
    twin.set(f"{DEV}/demods/1/rate", asked)
    assert twin.getDouble(f"{DEV}/demods/1/rate") == pytest.approx(210e6 / ticks, rel=1e-15)


@pytest.mark.parametrize(
    "asked, rung",
    [(1800.0, 1800.0), (1400.0, 1800.0), (1000.0, 900.0), (3000.0, 3600.0), (28800.0, 28800.0), (2e6, 460800.0)],
)
def test_hf2_rate_ladder(asked: float, rung: float) -> None:
    # the HF2 twin offers 921.6 kSa/s / 2^k (k >= 1), the nearest in ratio, each a whole number of 210 MHz ticks
    _, twin = make_twin(rate_set="hf2")
    twin.set(f"{DEV}/demods/1/rate", asked)
    assert twin.getDouble(f"{DEV}/demods/1/rate") == pytest.approx(210e6 / round(210e6 / rung), rel=1e-15)


def test_get_flat_wildcard_and_nested_forms() -> None:
    _, twin = make_twin()
    twin.set(f"{DEV}/pids/2/p", -4.5)
    flat = twin.get(f"{DEV}/pids/*/p", flat=True, settingsonly=False)
    assert sorted(flat) == [f"{DEV}/pids/{n}/p" for n in range(4)]
    assert flat[f"{DEV}/pids/2/p"][0] == -4.5
    nested = twin.get(f"{DEV}/pids/2/p")
    assert nested["dev1234"]["pids"]["2"]["p"][0] == -4.5
    # settings-only (the default) drops read-only nodes of a branch, never an explicit leaf
    assert f"{DEV}/plls/0/locked" not in twin.get(f"{DEV}/plls/0", flat=True)
    assert f"{DEV}/plls/0/locked" in twin.get(f"{DEV}/plls/0/locked", flat=True)
    assert not any(p.endswith("/sample") for p in twin.get(f"{DEV}/demods/*", flat=True, settingsonly=False))


# ------------------------------------------------------------------ streaming protocol


def test_nothing_subscribed_no_data_and_world_stands_still() -> None:
    world, twin = make_twin()
    assert twin.poll(0.5, 500, 0, True) == {}
    assert world.t == 0.0


def test_an_oscillator_no_demod_uses_keeps_turning_and_a_demod_taking_it_sees_its_phase() -> None:
    """Oscillator 1 (fixed at 1234.5 Hz) runs on while no subscribed demod uses it (its phase advanced block by
    block, 2 pi f n dt each, floor-modulo 2 pi); demod 2, switched to it after three blocks, reports its phase
    continuing from there: phi_k = (phi + 2 pi (f_0 + ... + f_k) dt) mod 2 pi, computed here in numpy."""
    _, twin = make_twin()
    stream_demods(twin)
    f1, n, dt = 1234.5, 700, 150_000 / 210e6
    twin.set(f"{DEV}/oscs/1/freq", f1)
    phase = np.float64(0.0)
    for _ in range(3):
        twin.poll(0.5, 500, 0, True)
        phase = (phase + 2 * np.pi * f1 * n * dt) % (2 * np.pi)
    twin.set([(f"{DEV}/demods/2/oscselect", 1), (f"{DEV}/demods/2/enable", 1), (f"{DEV}/demods/2/rate", 1400.0)])
    twin.subscribe(f"{DEV}/demods/2/sample")
    s = twin.poll(0.5, 500, 0, True)[f"{DEV}/demods/2/sample"]
    expected = np.mod(phase + 2 * np.pi * np.cumsum(np.full(n, f1)) * dt, 2 * np.pi)
    np.testing.assert_array_equal(s["phase"], expected)
    np.testing.assert_array_equal(s["frequency"], np.full(n, f1))


def test_a_polls_arrays_stay_as_they_were_while_later_polls_run() -> None:
    """The samples a poll hands out (the gyro block's own rows for x and y, no copies) are not touched by the
    polls after it: every field of two demods kept from the first poll equals its copy after three more."""
    _, twin = make_twin()
    stream_demods(twin)
    first = twin.poll(0.5, 500, 0, True)
    kept = {path: {k: v.copy() for k, v in sample.items()} for path, sample in first.items()}
    for _ in range(3):
        twin.poll(0.5, 500, 0, True)
    for path, sample in first.items():
        for field, values in sample.items():
            np.testing.assert_array_equal(values, kept[path][field], err_msg=f"{path} {field}")


def test_poll_returns_samples_at_the_rate_with_exact_timestamps() -> None:
    world, twin = make_twin()
    stream_demods(twin)
    data = twin.poll(0.5, 500, 0, True)
    assert sorted(data) == [f"{DEV}/demods/0/sample", f"{DEV}/demods/1/sample"]
    s = data[f"{DEV}/demods/1/sample"]
    assert set(s) == {"timestamp", "x", "y", "frequency", "phase", "dio", "trigger", "auxin0", "auxin1"}
    assert s["timestamp"].dtype == np.uint64
    assert len(s["x"]) == 700  # round(0.5 s * 1400 Sa/s)
    assert np.all(np.diff(s["timestamp"].astype(np.int64)) == 150_000)  # 210 MHz / 1400 Sa/s
    assert int(s["timestamp"][-1]) == 105_000_000  # end of the last step = 0.5 s * 210 MHz
    assert world.t == pytest.approx(0.5, abs=1e-12)
    s2 = twin.poll(0.5, 500, 0, True)[f"{DEV}/demods/1/sample"]
    assert int(s2["timestamp"][0]) - int(s["timestamp"][-1]) == 150_000
    nested = twin.poll(0.1, 500)
    assert len(nested["dev1234"]["demods"]["0"]["sample"]["x"]) == 140


def test_disabled_demod_delivers_nothing() -> None:
    _, twin = make_twin()
    stream_demods(twin)
    twin.set(f"{DEV}/demods/0/enable", 0)
    assert list(twin.poll(0.1, 500, 0, True)) == [f"{DEV}/demods/1/sample"]


def test_auxins_carry_the_dither_and_truth_is_recorded() -> None:
    world, twin = make_twin(params=paper_gyro_params(auxin_bits=0, auxin_noise_v_rms=0.0), rate_auxin=0, dither_auxin=1)
    world.set_dither(function=DITHER_SQUARE, frequency_hz=7.0, amplitude_vpp=0.6)
    stream_demods(twin)
    s = twin.poll(1.0, 500, 0, True)[f"{DEV}/demods/1/sample"]
    # each AuxIn reading is the mean over 2^averaging ADC samples ending at the timestamp; averaging 0 reads one
    # sample, so the dither reads +-0.3 V: high where the DS345's phase (its own timebase, started 0.37 ms after
    # the command) is in the first half cycle
    t = s["timestamp"].astype(float) / 210e6 - 0.5 / AUXIN_ADC_RATE_HZ
    p = world.params
    u = 7.0 * ((t - p.ds345_command_latency_s) * (1 + p.ds345_timebase_offset_ppm * 1e-6))
    expected = np.where((u - np.floor(u)) < 0.5, 0.3, -0.3)
    assert np.mean(np.abs(s["auxin1"] - expected) < 1e-6) > 0.99
    assert set(np.round(s["auxin1"], 9)) <= {0.3, -0.3} | set(np.round(s["auxin1"][np.abs(s["auxin1"]) < 0.3], 9))
    truth = world.drain_truth()
    assert truth is not None and len(truth.time) == 1400
    assert truth.time[-1] == pytest.approx(1.0)
    assert np.all(truth.scale_factor > 0)


def test_drop_samples_leaves_a_gap_and_sets_the_flag() -> None:
    _, twin = make_twin()
    stream_demods(twin)
    twin.drop_samples(25)
    s = twin.poll(0.5, 500, 0, True)[f"{DEV}/demods/0/sample"]
    assert len(s["x"]) == 700 - 25
    gaps = np.diff(s["timestamp"].astype(np.int64)) // 150_000
    assert sorted(set(gaps)) == [1, 26] and int(np.sum(gaps - 1)) == 25
    assert twin.getInt(f"{DEV}/status/flags/demodsampleloss") == 1
    twin.poll(0.5, 500, 0, True)
    assert twin.getInt(f"{DEV}/status/flags/demodsampleloss") == 0


def test_fault_hooks_reject_bad_arguments() -> None:
    _, twin = make_twin()
    with pytest.raises(ValueError, match="drop_samples"):
        twin.drop_samples(-1)
    with pytest.raises(ValueError, match="force_pll_unlock"):
        twin.force_pll_unlock(-2.0)


def test_wiring_is_validated_by_the_schema() -> None:
    """The wiring is declared and checked once, in [lockin]; the twin takes what the station passes."""
    with pytest.raises(ConfigError, match=r"rate_auxin and lockin\.dither_auxin"):
        parse_config("[lockin]\nrate_auxin = 1\ndither_auxin = 1\n")
    with pytest.raises(ConfigError, match="forcer_carrier_amplitude"):
        parse_config("[lockin]\nforcer_carrier_amplitude = 1.5\n")


def test_auxin_readings_are_quantised_noisy_and_clipped() -> None:
    """Each AuxIn reading: + white noise sigma, rounded to 2 R / 2^bits, clipped to +-R. The dither's plateaus
    (+-0.3 V) then read as multiples of the step whose spread about the true level is sqrt(sigma^2 + lsb^2/12)
    (sigma >= lsb/2 dithers the rounding), and a range below the level clips it."""
    params = paper_gyro_params(auxin_bits=8, auxin_range_v=1.0, auxin_noise_v_rms=0.01)
    lsb = 2.0 / 2**8
    world, twin = make_twin(params=params, rate_auxin=0, dither_auxin=1)
    world.set_dither(function=DITHER_SQUARE, frequency_hz=7.0, amplitude_vpp=0.6)
    stream_demods(twin)
    d = np.concatenate([twin.poll(1.0, 500, 0, True)[f"{DEV}/demods/1/sample"]["auxin1"] for _ in range(5)])
    assert np.allclose(d / lsb, np.round(d / lsb), atol=1e-9)
    plateau = d[np.abs(np.abs(d) - 0.3) < 0.1]
    err = plateau - np.sign(plateau) * 0.3
    assert abs(float(np.mean(err))) < 0.002
    assert float(np.std(err)) == pytest.approx(math.sqrt(0.01**2 + lsb**2 / 12), rel=0.05)
    world, twin = make_twin(params=paper_gyro_params(auxin_range_v=0.2), rate_auxin=0, dither_auxin=1)
    world.set_dither(function=DITHER_SQUARE, frequency_hz=7.0, amplitude_vpp=0.6)
    stream_demods(twin)
    d = twin.poll(1.0, 500, 0, True)[f"{DEV}/demods/1/sample"]["auxin1"]
    assert float(np.max(np.abs(d))) == pytest.approx(0.2)


def test_an_hf2li_without_mf_refuses_the_mf_mixer_channels_and_streams_on_two_oscillators() -> None:
    """Without MF (zhinst-utils default_output_mixer_channel; a recorded non-MF HF2): only mixer channels 6 and
    7, two oscillators; a write to channel 0 is refused like any node the instrument does not list."""
    world = paper_world()
    twin = HF2DataServerTwin(
        world,
        paper_gyro_params(),
        seed=3,
        wiring=paper_wiring(forcer_mixer_channel=7),
        **hf2_twin_settings(options=("PLL", "PID")),
    )
    twin.connectDevice("dev1234", "USB")
    assert twin.getString(f"{DEV}/features/options") == "PLL\nPID"
    with pytest.raises(RuntimeError, match="ZIAPINotFoundException"):
        twin.set(f"{DEV}/sigouts/0/enables/0", 0)
    with pytest.raises(RuntimeError, match="ZIAPINotFoundException"):
        twin.getDouble(f"{DEV}/oscs/2/freq")
    twin.set(f"{DEV}/sigouts/0/enables/6", 1)
    assert twin.getInt(f"{DEV}/sigouts/0/enables/6") == 1
    stream_demods(twin)
    data = twin.poll(0.1, 500, 0, True)
    rate = twin.getDouble(f"{DEV}/demods/1/rate")  # n = round(rec_s * rate) samples (module doc, item 1)
    assert len(data[f"{DEV}/demods/1/sample"]["timestamp"]) == round(0.1 * rate) > 0
