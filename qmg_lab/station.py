"""The composition root: builds the station from a configuration, each instrument real or twin on its own.

This is the only module of `qmg_lab` that imports `drivers` and `sims`. A twin replaces the instrument, not the
driver: the same driver classes talk to the hardware through zhinst's data server, a VISA resource and serial
ports, or to the twins through zhinst's Session(connection=twin), a VISA-like twin resource and serial-like ports
(in-process, a pty or a socket). All twins share one simulated World.

World clock: when the lock-in is simulated its polls advance the world (virtual time, a campaign simulates in
seconds). When only the table, chamber or generator are twins (bring-up one instrument at a time) the world
follows the wall clock.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import pyvisa
import serial
from zhinst.toolkit import Session

from drivers.aerosmith import Aerosmith1291BR
from drivers.chamber import SunEC1xChamber
from drivers.ds345 import DS345
from drivers.hf2li import HF2LI
from qmg_lab.config import Config
from qmg_lab.instruments import InstrumentError, Station, TruthBlock, TruthSource
from sims.chamber_twin import ChamberTwin
from sims.ds345_twin import DS345Twin
from sims.faults import FaultInjector, FaultPlan
from sims.gyro_params import GyroParams
from sims.hf2_loops import HF2Wiring
from sims.hf2_server import HF2DataServerTwin
from sims.serial_twin import InProcessSerial, serve_pty, serve_socket
from sims.table_twin import RateTableTwin
from sims.world import World, WorldParams

SIM_DEVICE_ID = "dev1234"


class _WorldTruth(TruthSource):
    """Drains the truth the HF2 twin records into the world."""

    def __init__(self, world: World) -> None:
        self.world = world

    def drain(self) -> TruthBlock | None:
        rec = self.world.drain_truth()
        if rec is None:
            return None
        return TruthBlock(time=rec.time, scale_factor=rec.scale_factor, temperature=rec.temperature, rate=rec.rate)


def make_world(cfg: Config) -> World:
    s = cfg.sim
    params = WorldParams(chamber_time_constant_s=s.chamber_time_constant_s, thermal_lag_s=s.thermal_lag_s,
                         initial_temperature_c=s.initial_temperature_c,
                         table_rate_scale_error_ppm=s.table_rate_scale_error_ppm,
                         ds345_timebase_offset_ppm=s.ds345_timebase_offset_ppm,
                         ds345_timebase_wander_ppm=s.ds345_timebase_wander_ppm,
                         ds345_timebase_wander_period_s=s.ds345_timebase_wander_period_s,
                         ds345_command_latency_s=s.ds345_command_latency_s)
    return World(params, clock="virtual" if cfg.lockin.sim else "wall")


def gyro_params(cfg: Config) -> GyroParams:
    """The twin's physics from [sim] (the device's true constants, which the [device] section only estimates)."""
    values = cfg.sim.model_dump(exclude={"seed", "faults"})
    values["drive_amplitude_vrms"] = cfg.device.drive_amplitude_vrms
    return GyroParams.from_mapping(values)


def fault_plan(cfg: Config) -> FaultPlan:
    """[sim.faults] as the plain values sims/faults.py takes (seeded by sim.seed)."""
    f = cfg.sim.faults
    values = f.model_dump()
    values["disconnect_at_s"] = tuple(f.disconnect_at_s)
    values["sample_loss_at_s"] = tuple(f.sample_loss_at_s)
    return FaultPlan(seed=cfg.sim.seed, **values)


def hf2_wiring(cfg: Config) -> HF2Wiring:
    lk = cfg.lockin
    return HF2Wiring(drive_sigin=lk.drive_sigin, sense_sigin=lk.sense_sigin, drive_sigout=lk.drive_sigout,
                     forcer_sigout=lk.forcer_sigout, forcer_carrier_amplitude=lk.forcer_carrier_amplitude,
                     rate_auxout=lk.rate_auxout, quadrature_auxout=lk.quadrature_auxout,
                     rate_auxin=lk.rate_auxin, dither_auxin=lk.dither_auxin)


def _serial_port(url: str, baudrate: int, timeout_s: float) -> Callable[[], Any]:
    def open_port() -> Any:
        try:
            return serial.serial_for_url(url, baudrate=baudrate, timeout=timeout_s)
        except (serial.SerialException, ValueError) as exc:
            raise InstrumentError(f"cannot open serial port {url!r}: {exc}") from exc
    return open_port


def _twin_port(twin: Any, transport: str, baudrate: int, timeout_s: float,
               closers: list[Callable[[], None]]) -> Callable[[], Any]:
    """A port factory reaching `twin` in-process, over a pty or over a loopback socket."""
    if transport == "inprocess":
        return lambda: InProcessSerial(twin, timeout=timeout_s)
    if transport == "pty":
        path, stop = serve_pty(twin)
    else:
        path, stop = serve_socket(twin)
    closers.append(stop)
    return _serial_port(path, baudrate, timeout_s)


def _visa_opener(resource: str, backend: str, timeout_ms: int) -> Callable[[], Any]:
    def open_resource() -> Any:
        try:
            rm = pyvisa.ResourceManager(backend) if backend else pyvisa.ResourceManager()
            res = rm.open_resource(resource)
            res.timeout = timeout_ms
            return res
        except (pyvisa.errors.Error, ValueError, OSError) as exc:
            raise InstrumentError(f"cannot open VISA resource {resource!r} (backend {backend or 'default'}): "
                                  f"{exc}") from exc
    return open_resource


def build_station(cfg: Config, world: World | None = None) -> Station:
    """Connect every instrument of the configuration (twins where `sim = true`). `world`: the twins' shared
    world (default: a new one from [sim]; tests pass their own to look at the physical state)."""
    if world is None and cfg.any_sim:
        world = make_world(cfg)
    closers: list[Callable[[], None]] = []
    plan = fault_plan(cfg)
    faults = FaultInjector(world, plan) if world is not None and plan.any else None

    # lock-in
    lk = cfg.lockin
    if lk.sim:
        assert world is not None
        twin = HF2DataServerTwin(world, gyro_params(cfg), cfg.sim.seed, hf2_wiring(cfg), device_id=SIM_DEVICE_ID,
                                 host=lk.host, port=lk.port, rate_set=cfg.sim.hf2_rate_set)
        if faults is not None:
            faults.attach_hf2(twin)
        session = Session(lk.host, lk.port, hf2=True, connection=twin)
        device_id = SIM_DEVICE_ID
    else:
        try:
            session = Session(lk.host, lk.port, hf2=True)
        except RuntimeError as exc:
            raise InstrumentError(f"cannot reach the HF2 data server at {lk.host}:{lk.port}: {exc}") from exc
        device_id = lk.device
    lockin = HF2LI(session, device_id, wiring=lk)

    # generator
    g = cfg.generator
    if g.sim:
        assert world is not None
        ds_twin = DS345Twin(world)
        open_gen: Callable[[], Any] = lambda: ds_twin.resource(g.resource)  # noqa: E731
        if faults is not None:
            faults.attach_ds345(ds_twin)
            open_gen = faults.visa_link("generator", open_gen)
    else:
        open_gen = _visa_opener(g.resource, g.visa_backend, g.timeout_ms)
    generator = DS345(open_gen(), max_amplitude_vpp=g.max_amplitude_vpp, reopen=open_gen)

    # table
    t = cfg.table
    if t.sim:
        assert world is not None
        open_table = _twin_port(_faulty(faults, "table", RateTableTwin(world)), t.sim_transport, t.baudrate,
                                t.timeout_s, closers)
    else:
        open_table = _serial_port(t.port, t.baudrate, t.timeout_s)
    table = Aerosmith1291BR(open_table(), max_rate_dps=t.max_rate_dps, max_accel_dps2=t.max_accel_dps2,
                            port_factory=open_table)

    # chamber
    c = cfg.chamber
    if c.sim:
        assert world is not None
        open_chamber = _twin_port(_faulty(faults, "chamber", ChamberTwin(world)), c.sim_transport, c.baudrate,
                                  c.timeout_s, closers)
    else:
        open_chamber = _serial_port(c.port, c.baudrate, c.timeout_s)
    chamber = SunEC1xChamber(open_chamber(), min_c=c.min_c, max_c=c.max_c, max_ramp_c_per_min=c.max_ramp_c_per_min,
                             safe_setpoint_c=c.safe_setpoint_c, port_factory=open_chamber)

    station = Station(lockin=lockin, generator=generator, table=table, chamber=chamber,
                      simulated={"lockin": lk.sim, "generator": g.sim, "table": t.sim, "chamber": c.sim},
                      truth=_WorldTruth(world) if (world is not None and lk.sim) else None,
                      restore=(lambda state: restore_world(world, state)) if world is not None else None)
    station.poll_interval_s = lk.sim_poll_interval_s if lk.sim else lk.poll_interval_s
    station.on_close.extend(closers)
    if faults is not None:
        station.injected_faults = lambda: [e.as_dict() for e in faults.events]
    return station


def _faulty(faults: FaultInjector | None, name: str, twin: Any) -> Any:
    """The twin as its port reaches it: through the fault injector's link gate when faults are configured."""
    if faults is None:
        return twin
    faults.attach_serial(name, twin)
    return faults.serial_link(name, twin)


def restore_world(world: World, state: dict[str, Any]) -> None:
    """A resumed simulated run: the physical world did not stop when the host process died. Put the twins'
    world back where the file says it was (time, chamber setpoint and air, gyro temperature)."""
    with world.lock:
        t = state.get("last_time")
        if t is not None and world.clock == "virtual":
            world.t = float(t)
        sp, air, gyro = (state.get(k) for k in ("chamber_setpoint_c", "chamber_temperature_c", "gyro_temperature_c"))
        if sp is not None:
            world.chamber.controller_setpoint_c = float(sp)
            world.chamber.target_c = float(sp)
        if air is not None:
            world.chamber.air_c = float(air)
        if gyro is not None:
            world.chamber.gyro_c = float(gyro)
