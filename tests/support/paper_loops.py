"""The lock-in loops of the default configuration as the physics twin takes them (shared by the twin's tests)."""

from __future__ import annotations

from qmg_lab.campaign.loops import lockin_setup
from qmg_lab.config.schema import Config
from sims.gyro_params import LoopSettings, PidSettings, PllSettings


def paper_loops(forcer_gain: float = 1.0) -> LoopSettings:
    """PLL, AGC, rate and quadrature PIs of `lockin_setup(Config())`, all closed, at forcer-path gain forcer_gain."""
    su = lockin_setup(Config())
    return LoopSettings(
        pll=PllSettings.from_gains(su.pll),
        agc=PidSettings.from_gains(su.agc),
        rate=PidSettings.from_gains(su.rate),
        quadrature=PidSettings.from_gains(su.quadrature),
        forcer_gain=forcer_gain,
    )
