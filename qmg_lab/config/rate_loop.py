"""The sense-axis rate loop a configuration designs: its PI as loop quantities, its closed loop, and how long a
step takes to settle under it. Pure functions of [device] and [loops]; the campaign turns them into the HF2's PID
gains (qmg_lab/campaign/loops.py), the analysis takes its settle floor from them (qmg_lab/analysis/reductions.py)
and the budget its transfer functions (qmg_lab/budget/), so the design is written once, where all three may
import it.

Plant (docs/physics.md section 4): with FTR holding c_y ~ 0, the sense demod X_s obeys
dX_s/dt = -X_s/tau - k R_d Omega + b G V, b = k R_d / SF, the plant b/(s + g), g = 1/tau. The PI
V = -P (X_s + z integral(X_s)), z = I/P, closes the loop with loop gain w_l = b P:
    open loop L(s) = w_l (s + z) / (s (s + g)),
    closed loop from the rate to the rate output T(s) = w_l (s + z) / (s^2 + (g + w_l) s + w_l z),
    error of a unit step 1 - y(t) with Laplace transform (1 - T(s))/s = (s + g) / (s^2 + (g + w_l) s + w_l z).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
from scipy.optimize import brentq

from qmg_lab.config.schema import Config, DeviceSection

RatePiDesign = Literal["critically_damped", "zero_on_pole"]
CRITICAL_BANDWIDTH_RATIO = math.sqrt(3.0 + math.sqrt(10.0))  # -3 dB of (2p s + p^2)/(s + p)^2 at w = 2.4824 p
#: a step has settled when what is left of it is within this fraction of its size for good: e^-5 (0.67 %)
SETTLED_FRACTION = math.exp(-5.0)


@dataclass(frozen=True)
class RateLoopDesign:
    """The FTR rate PI as loop quantities: loop gain w_l = b P and PI zero z = I / P, both rad/s; `design` the
    rule that chose them."""

    gain_rad_s: float
    zero_rad_s: float
    design: RatePiDesign = "critically_damped"


def rate_loop_design(
    device: DeviceSection, bandwidth_hz: float, design: RatePiDesign = "critically_damped", zero_offset_hz: float = 0.0
) -> RateLoopDesign:
    """Loop gain w_l = b P and zero z = I/P of the rate PI on the plant b/(s + g), g = 1/tau (nominal device).

    * zero_on_pole: z = g + 2 pi f_z, w_l = 2 pi f_bw. With f_z = 0, T = w_l/(s + w_l), first order. A plant whose
      g differs from the design's (Q moves with temperature) or whose sense mode is detuned by a split d keeps a
      closed-loop pole near -z, about 1/tau: after each table step a tail of relative size ~ (g - z)/w_l decaying
      with tau = 2Q/omega (174 s), longer than a table dwell.
    * critically_damped: s^2 + (g + w_l) s + w_l z = (s + p)^2, so w_l = 2p - g, z = p^2 / w_l, and
      T(s) = w_l (s + z)/(s + p)^2; for g << p, |T(j w)|^2 = (4 p^2 w^2 + p^4)/(w^2 + p^2)^2 = 1/2 at
      w = p sqrt(3 + sqrt 10): p = 2 pi f_bw / 2.4824 (1.61 Hz loop gain, 0.40 Hz zero for f_bw = 2 Hz). Step
      response 1 - e^{-pt} (1 - (p - g) t): 13.5 % overshoot at t = 2/p, within 2 % after p t = 5.39 (1.07 s at 2 Hz).
      Every closed-loop pole sits at -p: a drift of g or a split d << p moves them by O(dg, d^2/p), none becomes
      slow, so nothing of a table step remains after a few 1/p (e^{-25} after the campaign's 5 s settle).
    """
    g = 1.0 / device.tau_s
    if design == "zero_on_pole":
        return RateLoopDesign(2.0 * math.pi * bandwidth_hz, g + 2.0 * math.pi * zero_offset_hz, design)
    p = 2.0 * math.pi * bandwidth_hz / CRITICAL_BANDWIDTH_RATIO
    gain = 2.0 * p - g
    return RateLoopDesign(gain, p * p / gain, design)


def rate_loop_t(loop: RateLoopDesign, plant_pole_rad_s: float, s: complex | np.ndarray, gain_scale: float = 1.0) -> Any:
    """Closed loop T(s) = w (s + z)/(s (s + g) + w (s + z)), w = gain_scale w_l (the plant's actual gain over the
    nominal one scales the loop gain, not the zero I/P), g the plant's pole (rad/s); S = 1 - T keeps the share
    of a forcer-input disturbance the loop does not rebalance."""
    w = gain_scale * loop.gain_rad_s
    return w * (s + loop.zero_rad_s) / (s * (s + plant_pole_rad_s) + w * (s + loop.zero_rad_s))


def step_error(loop: RateLoopDesign, plant_pole_rad_s: float, t_s: float) -> float:
    """What is left of a unit rate step t_s seconds after it, 1 - y(t), on the nominal plant (pole g, rad/s): the
    inverse transform of (s + g)/(s^2 + (g + w_l) s + w_l z) (module docstring).

    * critically_damped, both poles at -p, p = (g + w_l)/2: 1 - y = e^(-pt) (1 - (p - g) t).
    * otherwise, poles r1 != r2 (real or a complex pair): 1 - y = Re[((r1 + g) e^(r1 t) - (r2 + g) e^(r2 t)) /
      (r1 - r2)]; for zero_on_pole with f_z = 0 (z = g) the poles are -w_l and -g and this is e^(-w_l t).
    """
    g, w = plant_pole_rad_s, loop.gain_rad_s
    if loop.design == "critically_damped":
        p = 0.5 * (g + w)
        return math.exp(-p * t_s) * (1.0 - (p - g) * t_s)
    r1, r2 = _poles(loop, g)
    return float((((r1 + g) * np.exp(r1 * t_s) - (r2 + g) * np.exp(r2 * t_s)) / (r1 - r2)).real)


def settle_time_s(loop: RateLoopDesign, plant_pole_rad_s: float, fraction: float = SETTLED_FRACTION) -> float:
    """The time after a step from which |1 - y(t)| (`step_error`) stays within `fraction` for good, s: its last
    crossing of that level. Found on a grid up to a horizon past which a bound on |1 - y| is below the level
    (critically damped: e^(-pt) (1 + |p - g| t); otherwise the sum over the poles of |r_k + g| e^(Re r_k t) /
    |r1 - r2|), then refined between the grid's last point above the level and the next (Brent).
    Critically damped with g << p: the overshoot e^(-pt) (pt - 1) = e^-5 at pt = 6.75 (1.33 s at 2 Hz);
    first order: 5 / w_l (0.40 s at 2 Hz)."""
    g = plant_pole_rad_s
    if loop.design == "critically_damped":
        p = 0.5 * (g + loop.gain_rad_s)

        def bound(t: float) -> float:
            return math.exp(-p * t) * (1.0 + abs(p - g) * t)
    else:
        r1, r2 = _poles(loop, g)
        terms = [(abs(r1 + g) / abs(r1 - r2), r1.real), (abs(r2 + g) / abs(r1 - r2), r2.real)]

        def bound(t: float) -> float:
            return sum(c * math.exp(sigma * t) for c, sigma in terms)

    horizon = 1.0 / loop.gain_rad_s
    while bound(horizon) >= fraction:
        horizon *= 2.0
    grid = np.linspace(0.0, horizon, 4097)
    above = np.flatnonzero([abs(step_error(loop, g, float(t))) >= fraction for t in grid])
    if above.size == 0:
        return 0.0
    a, b = float(grid[above[-1]]), float(grid[above[-1] + 1])
    return float(brentq(lambda t: abs(step_error(loop, g, t)) - fraction, a, b, xtol=1e-12, rtol=1e-12))


def _poles(loop: RateLoopDesign, g: float) -> tuple[complex, complex]:
    """The closed loop's poles, the roots of s^2 + (g + w_l) s + w_l z (rad/s)."""
    a1, a0 = g + loop.gain_rad_s, loop.gain_rad_s * loop.zero_rad_s
    root = np.sqrt(complex(a1 * a1 - 4.0 * a0))
    return complex(0.5 * (-a1 + root)), complex(0.5 * (-a1 - root))


def config_rate_loop(cfg: Config) -> RateLoopDesign:
    """rate_loop_design of a configuration's [device] and [loops]."""
    lp = cfg.loops
    return rate_loop_design(cfg.device, lp.rate_bandwidth_hz, lp.sense_pi_design, lp.rate_zero_offset_hz)


def config_quadrature_loop(cfg: Config) -> RateLoopDesign:
    """rate_loop_design of the quadrature loop of a configuration's [device] and [loops]."""
    return rate_loop_design(cfg.device, cfg.loops.quadrature_bandwidth_hz, cfg.loops.sense_pi_design)


def config_settle_floor_s(cfg: Config) -> float:
    """The configured rate loop's `settle_time_s` on the nominal plant (g = 1/tau of [device]), s: the shortest
    settle after which a table step is within e^-5 of its end."""
    return settle_time_s(config_rate_loop(cfg), 1.0 / cfg.device.tau_s)
