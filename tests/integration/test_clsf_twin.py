"""The CLSF estimator's sensitivity on the simulated bench, for every demodulator filter a configuration accepts.

The real HF2 driver configures the HF2 twin through zhinst-toolkit; the DS345 twin runs on its own timebase
(offset in ppm plus wander), the HF2 twin streams at the rate it offers, filters the demodulator output with the
configured cascade and reports the AuxIns as the instrument does. Noise is switched off, so the only thing
that moves the estimate is a true step of the forcer-path gain, applied through the lock-in (the same node
correct mode uses): beta -> 1.01 beta. The model says rho is proportional to beta, so the estimate must read
sf_change = 1/1.01 - 1, i.e. a sensitivity d ln(rho)/d ln(beta) of 1; the requirement is 1 +- 1e-3.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from qmg_lab.budget.sweep import DETERMINISTIC_OFF, sim_lines
from qmg_lab.campaign.loops import lockin_setup
from qmg_lab.clsf.demod_filter import DemodFilter
from qmg_lab.clsf.estimator import ClsfEstimator
from qmg_lab.config.schema import dither_amplitude_vpp, parse_config
from qmg_lab.station import build_station

ROOT = Path(__file__).resolve().parents[2]
GAIN_STEP = 1.01


def _config(order: int, tc_s: float, rate_hz: float, dither_hz: float, offset_ppm: float):
    text = (ROOT / "configs" / "paper_campaign.toml").read_text()
    text = text.replace("demod_rate_hz = 1800.0", f"demod_rate_hz = {rate_hz}")
    text = text.replace("frequency_hz = 7.0", f"frequency_hz = {dither_hz}")
    text = text.replace(
        "[lockin]                       # HF2LI via the HF2 data server (port 8005)",
        f"[lockin]\ndemod_order = {order}\ndemod_timeconstant_s = {tc_s}",
    )
    text += (
        f"arw_deg_per_rt_h = 0.0\nbias_instability_deg_per_h = 0.0\npickoff_noise_vrms_per_rt_hz = 0.0\n"
        "forcer_noise_v_per_rt_hz = 0.0\nauxin_noise_v_rms = 0.0\nauxin_bits = 0\nauxout_bits = 0\n"
        f"ds345_timebase_offset_ppm = {offset_ppm}\n"
    )
    # the estimator's own exactness, on a plant without the deterministic non-idealities: a forcer-to-pickoff
    # feedthrough, for one, scales with the forcer-path gain and moves the sensitivity itself (docs/accuracy-budget.md)
    text += sim_lines(DETERMINISTIC_OFF)
    return parse_config(text).with_all_sim()


def measured_sensitivity(
    order: int, tc_s: float, rate_hz: float = 1800.0, dither_hz: float = 7.0, offset_ppm: float = 3.0
) -> float:
    cfg = _config(order, tc_s, rate_hz, dither_hz, offset_ppm)
    station = build_station(cfg)
    try:
        lockin = station.lockin
        lockin.configure(lockin_setup(cfg))
        timing = lockin.stream_timing()
        assert (timing.filter_order, timing.filter_tc_s) == (order, pytest.approx(tc_s))
        est = ClsfEstimator(tau_s=cfg.device.tau_s, reference_periods=40)
        est.set_stream_timing(DemodFilter(timing.filter_order, timing.filter_tc_s), timing.auxin_window_s)
        station.generator.set_square(dither_hz, dither_amplitude_vpp(cfg))
        lockin.start_stream()

        def run(seconds: float) -> np.ndarray:
            etas = []
            for _ in range(int(seconds / 2)):
                b = lockin.poll(2.0)
                etas.append(est.process(b.time, b.x_sense, b.rate_output, b.dither).eta)
            return np.concatenate(etas)

        run(4.0)  # the dither's start transient through the loops
        before = run(16.0)
        lockin.set_forcer_gain(GAIN_STEP)
        run(4.0)  # the loop settles on the new gain
        after = run(16.0)
        lockin.stop_stream()
    finally:
        station.close()
    return math.log((1 + after.mean()) / (1 + before.mean())) / math.log(GAIN_STEP)


@pytest.mark.parametrize("order", [1, 2, 3, 4, 5, 6, 7, 8])
@pytest.mark.parametrize("tc_s", [1e-5, 1e-4, 1e-3])
def test_sensitivity_is_one_for_every_filter_setting(order, tc_s):
    assert measured_sensitivity(order, tc_s) == pytest.approx(1.0, abs=1e-3)


@pytest.mark.parametrize(
    ("rate_hz", "dither_hz", "offset_ppm"),
    [
        (3600.0, 7.3, 50.0),
        (900.0, 5.3, -50.0),
        (1800.0, 9.7, -20.0),
    ],
)
def test_sensitivity_is_one_at_other_rates_and_incommensurate_dithers(rate_hz, dither_hz, offset_ppm):
    assert measured_sensitivity(4, 3e-4, rate_hz, dither_hz, offset_ppm) == pytest.approx(1.0, abs=1e-3)
