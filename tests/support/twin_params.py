"""The twins' parameters of the default configuration (the paper's device and stand, no fault injected), for the
tests and benchmarks that build a twin without a station.

The schema (qmg_lab/config/schema.py SimSection, SimFaultsSection) is the one place of these values; the twins'
parameter classes and constructor keywords carry no copy of them. These helpers take them from the default
configuration, the parameter classes through the station's own mapping (qmg_lab/station.py `gyro_params`,
`world_params`, `fault_plan`), so a test sees exactly the device a default campaign simulates.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Any

from qmg_lab.config.schema import Config
from qmg_lab.station import fault_plan, gyro_params, hf2_wiring, world_params
from sims.faults import FaultPlan
from sims.gyro_params import GyroParams
from sims.hf2_loops import HF2Wiring
from sims.world import World, WorldParams


@functools.cache
def _paper() -> tuple[GyroParams, WorldParams, FaultPlan]:
    cfg = Config()
    return gyro_params(cfg), world_params(cfg), fault_plan(cfg)


def paper_wiring(**overrides: Any) -> HF2Wiring:
    """The default configuration's HF2 wiring ([lockin], through the station's `hf2_wiring`), `overrides` changed."""
    return dataclasses.replace(hf2_wiring(Config()), **overrides)


def paper_gyro_params(**overrides: Any) -> GyroParams:
    """The default configuration's gyro (the paper's QMG), with `overrides` (GyroParams field names) changed."""
    return dataclasses.replace(_paper()[0], **overrides)


def paper_world_params(**overrides: Any) -> WorldParams:
    """The default configuration's stand (chamber, table, DS345 timebase), with `overrides` changed."""
    return dataclasses.replace(_paper()[1], **overrides)


def paper_world(clock: str = "virtual", **overrides: Any) -> World:
    """A new World of the default configuration's stand (with `overrides` changed) on the `clock` given."""
    return World(paper_world_params(**overrides), clock=clock)


def hf2_twin_settings(**overrides: Any) -> dict[str, Any]:
    """The HF2 twin's `options` and `rate_set` keywords of the default configuration ([sim] hf2_options,
    hf2_rate_set), with `overrides` changed."""
    sim = Config().sim
    return {"options": tuple(sim.hf2_options), "rate_set": sim.hf2_rate_set, **overrides}


def table_twin_settings(**overrides: Any) -> dict[str, Any]:
    """The 1291BR twin's `servo_on` keyword of the default configuration ([sim] table_servo_on_at_start), with
    `overrides` changed."""
    return {"servo_on": Config().sim.table_servo_on_at_start, **overrides}


def chamber_twin_settings(**overrides: Any) -> dict[str, Any]:
    """The EC1x twin's keywords of the default configuration ([sim] chamber_status_layout, chamber_self_test,
    chamber_acknowledges_settings, chamber_powered_at_start, chamber_set_query_while_off,
    chamber_silent_commands), with `overrides` changed."""
    sim = Config().sim
    return {
        "status_layout": sim.chamber_status_layout,
        "self_test": sim.chamber_self_test,
        "acknowledges_settings": sim.chamber_acknowledges_settings,
        "powered_at_start": sim.chamber_powered_at_start,
        "set_query_while_off": sim.chamber_set_query_while_off,
        "silent_commands": sim.chamber_silent_commands,
        **overrides,
    }


def fault_plan_with(**injected: Any) -> FaultPlan:
    """The default configuration's fault plan (nothing injected, seeded by its sim.seed) with `injected` changed
    (FaultPlan field names)."""
    return dataclasses.replace(_paper()[2], **injected)
