"""[sim] defaults in one place (issue 25): the configuration schema (qmg_lab/config/schema.py SimSection,
SimFaultsSection, and [device] drive_amplitude_vrms) holds every default that [sim] exposes; the twins' parameter
classes take the values from the station (qmg_lab/station.py) and carry no second copy that could drift."""

from __future__ import annotations

import dataclasses
import importlib
import inspect
import pkgutil
from typing import Any

import sims
from qmg_lab.config.schema import Config, DeviceSection, SimFaultsSection, SimSection
from qmg_lab.station import fault_plan, gyro_params, world_params
from sims.chamber_twin import ChamberTwin
from sims.faults import FaultPlan
from sims.gyro_params import GyroParams
from sims.hf2_server import HF2DataServerTwin
from sims.table_twin import RateTableTwin
from sims.world import WorldParams

SIM_KEYS = set(SimSection.model_fields) - {"faults"}
FAULT_KEYS = set(SimFaultsSection.model_fields)
EXPOSED = SIM_KEYS | FAULT_KEYS | {"drive_amplitude_vrms"}  # the twin's drive amplitude is [device]'s


def _sims_dataclasses() -> list[type[Any]]:
    """Every dataclass defined in a module of the sims package."""
    found = []
    for info in pkgutil.walk_packages(sims.__path__, "sims."):
        module = importlib.import_module(info.name)
        found += [
            obj
            for obj in vars(module).values()
            if isinstance(obj, type) and dataclasses.is_dataclass(obj) and obj.__module__ == module.__name__
        ]
    return found


def test_no_twin_parameter_class_has_a_default_for_a_value_the_configuration_exposes() -> None:
    classes = _sims_dataclasses()
    assert {GyroParams, WorldParams, FaultPlan} <= set(classes)  # the scan reaches the classes the station fills
    with_default = [
        f"{cls.__module__}.{cls.__name__}.{f.name}"
        for cls in classes
        for f in dataclasses.fields(cls)
        if f.name in EXPOSED and (f.default is not dataclasses.MISSING or f.default_factory is not dataclasses.MISSING)
    ]
    assert with_default == [], f"defaults of [sim] values belong in qmg_lab/config/schema.py only: {with_default}"


def test_the_station_fills_every_field_of_the_twins_parameter_classes_from_the_configuration() -> None:
    """Every field of GyroParams, WorldParams and FaultPlan is a configuration key, and the station passes the
    configured value (values away from every default, so a field left to anything else would show)."""
    sim = SimSection(
        q_factor=1.1e6,
        sf_true_v_per_dps=0.05,
        hf2_demod_ripple=False,
        thermal_lag_s=300.0,
        ds345_command_latency_s=1e-3,
        seed=7,
        faults=SimFaultsSection(chamber_overshoot_c=2.0, sample_loss_at_s=[4.0], disconnect_instrument="chamber"),
    )
    cfg = Config(sim=sim, device=DeviceSection(drive_amplitude_vrms=0.4))
    built: list[tuple[Any, Any]] = [(gyro_params(cfg), sim), (world_params(cfg), sim), (fault_plan(cfg), sim.faults)]
    for params, section in built:
        for f in dataclasses.fields(params):
            assert f.name in EXPOSED, f"{type(params).__name__}.{f.name} is no configuration key"
            source = cfg.device if f.name == "drive_amplitude_vrms" else (sim if f.name == "seed" else section)
            expected = getattr(source, f.name)
            value = getattr(params, f.name)
            assert (list(value) if isinstance(value, tuple) else value) == expected, f"{f.name}: {value!r}"


TWIN_KEYWORDS = (  # the twins' constructor keywords the station fills from [sim], with the key of each
    (HF2DataServerTwin, "options", "hf2_options"),
    (HF2DataServerTwin, "rate_set", "hf2_rate_set"),
    (RateTableTwin, "servo_on", "table_servo_on_at_start"),
    (ChamberTwin, "status_layout", "chamber_status_layout"),
    (ChamberTwin, "self_test", "chamber_self_test"),
    (ChamberTwin, "acknowledges_settings", "chamber_acknowledges_settings"),
)


def test_the_twins_take_their_sim_settings_without_a_default_of_their_own() -> None:
    """[sim] values that reach a twin as a constructor keyword have no default there either."""
    for twin, keyword, key in TWIN_KEYWORDS:
        assert key in SIM_KEYS
        default = inspect.signature(twin).parameters[keyword].default
        assert default is inspect.Parameter.empty, f"{twin.__name__}({keyword}=...) has a default ({key})"
