"""qmg_lab.campaign.loops.forcer_path_problem: the CLSF reference rho_0 (the forcer path's gain beta) against the
plant gain the loops were designed on, b = k R_d / SF_rad = 0.8 * 0.5 / (0.06 * 180/pi) = 0.11636 per the default
[device], times the forcer gain in force; plausible within a factor 2 either way."""

from __future__ import annotations

import math

import pytest

from qmg_lab.campaign.loops import forcer_path_problem
from qmg_lab.config.schema import DeviceSection

B = 0.8 * 0.5 / (0.06 * 180 / math.pi)


@pytest.mark.parametrize("ratio", [1.0, 1.0058, 0.51, 1.99])
def test_a_forcer_path_near_the_design_passes(ratio: float) -> None:
    assert forcer_path_problem(ratio * B, DeviceSection()) is None


@pytest.mark.parametrize("ratio", [1.6e-5, 0.49, 2.01, -1.0])
def test_a_forcer_path_off_by_more_than_a_factor_two_is_named(ratio: float) -> None:
    words = forcer_path_problem(ratio * B, DeviceSection())
    assert words is not None
    assert f"{ratio:.3g} times the plant gain" in words and "the forcer does not act as configured" in words


def test_the_forcer_gain_in_force_scales_the_expectation() -> None:
    assert forcer_path_problem(1.5 * B, DeviceSection(), forcer_gain=1.5) is None
    assert forcer_path_problem(B, DeviceSection(), forcer_gain=2.5) is not None
