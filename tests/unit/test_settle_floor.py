"""The analysis's settle floor is the configured rate loop's own time to within e^-5 of the end of a table step
(qmg_lab/config/rate_loop.py settle_time_s, qmg_lab/analysis/reductions.py analysis_settle_s).

Expected values come from the closed loop written out here, T(s) = w_l (s + z)/(s^2 + (g + w_l) s + w_l z), g = 1/tau:
* critically damped (both poles at -p, p = 2 pi f_bw / sqrt(3 + sqrt 10)): 1 - y(t) = e^(-pt) (1 - (p - g) t);
* zero on the pole, f_z = 0: first order, 1 - y(t) = e^(-w_c t), w_c = 2 pi f_bw, so the floor is 5 / w_c;
* zero on the pole with an offset f_z: the step response of T(s)'s state-space form (scipy.signal.tf2ss) by the
  matrix exponential, independent of the code's pole formula.
The floor is where |1 - y| comes down to e^-5 for good: equal to it there, never above it later, above it at 0.99 of
the floor.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import signal
from scipy.linalg import expm

from qmg_lab.analysis.reductions import analysis_settle_s
from qmg_lab.config.rate_loop import config_settle_floor_s
from qmg_lab.config.schema import Config, DeviceSection, LoopsSection, PlanSection

LEVEL = math.exp(-5.0)


def _cfg(design: str, bandwidth_hz: float, settle_s: float, zero_offset_hz: float = 0.0) -> Config:
    return Config(
        loops=LoopsSection(sense_pi_design=design, rate_bandwidth_hz=bandwidth_hz, rate_zero_offset_hz=zero_offset_hz),
        plan=PlanSection(settle_s=settle_s),
    )


def _assert_settles_at(error, floor: float) -> None:  # type: ignore[no-untyped-def]
    assert abs(error(floor)) == pytest.approx(LEVEL, rel=1e-6)
    later = np.linspace(floor, 20.0 * floor, 4001)
    assert float(np.max(np.abs(error(later)))) <= LEVEL * (1 + 1e-6)
    assert abs(error(0.99 * floor)) > LEVEL


@pytest.mark.parametrize("bandwidth_hz", [0.5, 2.0, 5.0])
def test_critically_damped_floor_is_where_the_overshoot_falls_to_e5(bandwidth_hz: float) -> None:
    cfg = _cfg("critically_damped", bandwidth_hz, settle_s=0.0)
    p = 2 * math.pi * bandwidth_hz / math.sqrt(3 + math.sqrt(10))
    g = 1.0 / cfg.device.tau_s

    def error(t):  # type: ignore[no-untyped-def]
        return np.exp(-p * t) * (1 - (p - g) * t)

    floor = analysis_settle_s(cfg)
    _assert_settles_at(error, floor)
    assert floor > 2.0 / p  # past the overshoot's peak, not the response's first pass through 1 - e^-5


@pytest.mark.parametrize("bandwidth_hz", [0.5, 2.0, 5.0])
def test_first_order_floor_is_five_time_constants(bandwidth_hz: float) -> None:
    cfg = _cfg("zero_on_pole", bandwidth_hz, settle_s=0.0)
    w_c = 2 * math.pi * bandwidth_hz
    _assert_settles_at(lambda t: np.exp(-w_c * t), analysis_settle_s(cfg))
    assert analysis_settle_s(cfg) == pytest.approx(5.0 / w_c, rel=1e-9)


def test_zero_offset_floor_follows_the_loops_step_response() -> None:
    """A zero 0.2 Hz above 1/tau leaves a slow closed-loop pole near -2 pi 0.2: its tail sets the floor."""
    cfg = _cfg("zero_on_pole", 2.0, settle_s=0.0, zero_offset_hz=0.2)
    w, g = 2 * math.pi * 2.0, 1.0 / cfg.device.tau_s
    z = g + 2 * math.pi * 0.2
    a, b, c, d = signal.tf2ss([w, w * z], [1.0, g + w, w * z])
    gain = c @ np.linalg.solve(a, np.eye(2))

    def step(t: float) -> float:  # y(t) = C A^-1 (e^(At) - I) B + D of the state-space form of T(s)
        return float((gain @ (expm(a * t) - np.eye(2)) @ b + d)[0, 0])

    def error(t):  # type: ignore[no-untyped-def]
        if np.ndim(t):
            return np.array([1.0 - step(float(x)) for x in t])
        return 1.0 - step(float(t))

    floor = analysis_settle_s(cfg)
    _assert_settles_at(error, floor)
    assert floor > 5.0 / w  # the slow tail, not the fast pole


def test_the_plans_longer_settle_wins_and_the_floor_raises_a_shorter_one() -> None:
    floor = config_settle_floor_s(Config())
    assert analysis_settle_s(_cfg("critically_damped", 2.0, settle_s=5.0)) == 5.0
    assert analysis_settle_s(_cfg("critically_damped", 2.0, settle_s=0.5)) == floor
    slow_q = Config(device=DeviceSection(q_factor=1.2e5), plan=PlanSection(settle_s=0.0))
    assert config_settle_floor_s(slow_q) != floor  # g = 1/tau of [device] enters the response
