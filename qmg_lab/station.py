"""The composition root: builds the station from a configuration, each instrument real or twin on its own.

This is the only module of `qmg_lab` that imports `drivers` and `sims`. A twin replaces the instrument, not the
driver: the same driver classes talk to the hardware through zhinst's data server, a VISA resource and serial
ports, or to the twins through zhinst's Session(connection=twin), a VISA-like twin resource and serial-like ports
(in-process, a pty or a socket). All twins share one simulated World.

World clock: when the lock-in is simulated its polls advance the world (virtual time, a campaign simulates in
seconds). When only the table, chamber or generator are twins (bring-up one instrument at a time) the world
follows the wall clock. A mixed bench with the lock-in twin and at least one real instrument runs in real
time: the twin's polls are paced to the wall clock (`RealTimePacedConnection`), so that a 60 s dwell lasts
60 s on the real table too. An all-twin bench runs in real time too when asked (`build_station(cfg,
pacing=RealTimePacing())`, `qmg-lab run --sim --realtime`): a rehearsal in which the driver path (the
zhinst-toolkit poll of hardware-length blocks, `[lockin] poll_interval_s`, the estimator, the writer, the
progress and the watch page) runs at the pace it will have on the bench.

Why one module of this length: it is the only module that imports drivers and sims (an import-linter
contract); building each instrument, real or twin, over each transport has to happen here and nowhere else.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import pyvisa
import serial
from zhinst.toolkit import Session

from drivers.aerosmith import Aerosmith1291BR
from drivers.chamber import SunEC1xChamber
from drivers.ds345 import DS345
from drivers.hf2_nodes import mixer_layout
from drivers.hf2li import HF2LI, open_hf2_session
from drivers.line_transport import LineTransport, SerialLineTransport, VisaLineTransport
from drivers.serial_link import Framing
from qmg_lab.config.schema import Config, ConfigError
from qmg_lab.instruments import (
    INSTRUMENT_NAMES,
    FunctionGenerator,
    Instrument,
    InstrumentError,
    LockIn,
    RateTable,
    Station,
    ThermalChamber,
    TruthBlock,
    TruthSource,
)
from sims.chamber_twin import ChamberTwin
from sims.ds345_twin import DS345Twin
from sims.faults import FaultInjector, FaultPlan
from sims.gyro_params import GyroParams
from sims.hf2_loops import HF2Wiring
from sims.hf2_server import HF2DataServerTwin
from sims.serial_twin import InProcessSerial, serve_pty, serve_socket, terminator
from sims.table_twin import RateTableTwin, TableEncoder
from sims.visa_line_twin import LineTwinVisaResource
from sims.world import World, WorldParams

SIM_DEVICE_ID = "dev1234"

log = logging.getLogger(__name__)


class _WorldTruth(TruthSource):
    """Drains the truth the HF2 twin records into the world."""

    def __init__(self, world: World) -> None:
        self.world = world

    def drain(self) -> TruthBlock | None:
        rec = self.world.drain_truth()
        if rec is None:
            return None
        return TruthBlock(time=rec.time, scale_factor=rec.scale_factor, temperature=rec.temperature, rate=rec.rate)


def world_params(cfg: Config) -> WorldParams:
    """The stand's physics outside the gyro from [sim]: every WorldParams field, taken by name (the schema is the
    one place of their defaults)."""
    return WorldParams(**cfg.sim.model_dump(include={f.name for f in dataclasses.fields(WorldParams)}))


def make_world(cfg: Config, clock: str | None = None) -> World:
    """The twins' shared world from [sim]. clock: "virtual" (the lock-in twin's polls advance it) or "wall";
    default virtual when the lock-in is a twin."""
    return World(world_params(cfg), clock=clock or ("virtual" if cfg.lockin.sim else "wall"))


def gyro_params(cfg: Config) -> GyroParams:
    """The twin's physics from [sim] (the device's true constants, which the [device] section only estimates) and
    [device] drive_amplitude_vrms (the amplitude at which sim.sf_true_v_per_dps applies): every GyroParams field
    (the schema is the one place of their defaults)."""
    values = cfg.sim.model_dump(include=set(GyroParams.field_names()))  # [sim] also holds the world's and faults'
    values["drive_amplitude_vrms"] = cfg.device.drive_amplitude_vrms
    params = GyroParams.from_mapping(values)
    # the schema bounds every key; only the physics computes the forcer's electrostatic spring from them
    if params.electrostatic_spring_ratio >= 0.5:
        raise ConfigError(
            "[sim]: the forcer's electrostatic spring must stay below half the sense stiffness (k_e/k = "
            f"{params.electrostatic_spring_ratio:.3g} from forcer_bias_v, forcer_gap_um, drive_amplitude_um, "
            "forcer_electrode_v_per_v): near pull-in"
        )
    return params


def fault_plan(cfg: Config) -> FaultPlan:
    """[sim.faults] as the plain values sims/faults.py takes (seeded by sim.seed)."""
    f = cfg.sim.faults
    values = f.model_dump()
    values["disconnect_at_s"] = tuple(f.disconnect_at_s)
    values["sample_loss_at_s"] = tuple(f.sample_loss_at_s)
    return FaultPlan(seed=cfg.sim.seed, **values)


def hf2_wiring(cfg: Config) -> HF2Wiring:
    """How the twin's bench is cabled: the [lockin] wiring fields, taken by name, and the mixer channel that
    carries the forcer carrier as the driver derives it for the twin's options ([sim] hf2_options, the
    [lockin] forcer_mixer_channel override: drivers/hf2_nodes.py mixer_layout)."""
    lk = cfg.lockin
    names = {f.name for f in dataclasses.fields(HF2Wiring)} & set(type(lk).model_fields)
    names.discard("forcer_mixer_channel")
    layout = mixer_layout(tuple(cfg.sim.hf2_options), lk)
    return HF2Wiring(**{name: getattr(lk, name) for name in sorted(names)}, forcer_mixer_channel=layout.forcer)


def _serial_port(url: str, baudrate: int, timeout_s: float) -> Callable[[], Any]:
    def open_port() -> Any:
        try:
            return serial.serial_for_url(url, baudrate=baudrate, timeout=timeout_s)
        except (serial.SerialException, ValueError) as exc:
            raise InstrumentError(f"cannot open serial port {url!r}: {exc}") from exc

    return open_port


def _twin_port(
    twin: Any, transport: str, baudrate: int, timeout_s: float, closers: list[Callable[[], None]]
) -> Callable[[], Any]:
    """A port factory reaching `twin` in-process, over a pty or over a loopback socket."""
    if transport == "inprocess":
        return lambda: InProcessSerial(twin, timeout=timeout_s)
    if transport == "pty":
        path, stop = serve_pty(twin)
    else:
        path, stop = serve_socket(twin)
    closers.append(stop)
    return _serial_port(path, baudrate, timeout_s)


#: what to install when pyvisa finds no VISA library: pyvisa's own "Could not locate a VISA implementation"
#: (no IVI library and no pyvisa-py), "Could not open VISA library" (the IVI library named or found cannot be
#: loaded) and "Wrapper not found: No package named pyvisa_py" ("@py" without pyvisa-py) name neither the
#: instrument nor a vendor (pyvisa.highlevel)
NO_VISA_LIBRARY = (
    "no VISA library: install pyvisa-py (`pip install pyvisa-py`: pyvisa takes it when it finds no vendor VISA, "
    'or set visa_backend = "@py"; RS-232 (ASRL) and TCPIP, GPIB only with gpib-ctypes or linux-gpib) or a '
    "vendor VISA (NI-VISA or Keysight IO Libraries Suite; a GPIB adapter needs its vendor's)"
)
_NO_VISA_SIGNS = ("Could not locate a VISA implementation", "Could not open VISA library", "No package named pyvisa")


def visa_failure(instrument: str, resource: str, backend: str, exc: BaseException) -> str:
    """The message for a VISA resource that could not be opened: the instrument, its address and backend, and,
    when no VISA library was found, what to install (NO_VISA_LIBRARY) before pyvisa's own words."""
    where = f"{instrument} at VISA resource {resource!r} (visa_backend {backend or 'default'!r})"
    if any(sign in str(exc) for sign in _NO_VISA_SIGNS):
        return f"{where}: {NO_VISA_LIBRARY} (pyvisa: {exc})"
    return f"cannot open the {where}: {exc}"


def _visa_opener(instrument: str, resource: str, backend: str, timeout_ms: int) -> Callable[[], Any]:
    def open_resource() -> Any:
        try:
            rm = pyvisa.ResourceManager(backend) if backend else pyvisa.ResourceManager()
            res = rm.open_resource(resource)
            res.timeout = timeout_ms
            return res
        except (pyvisa.errors.Error, ValueError, OSError) as exc:
            raise InstrumentError(visa_failure(instrument, resource, backend, exc)) from exc

    return open_resource


def table_framing(cfg: Config) -> Framing:
    """[table] command_terminator, reply_terminator, prompt -> the 1291BR driver's Framing."""
    t = cfg.table
    return Framing(command_terminator=t.command_terminator, reply_terminator=t.reply_terminator, prompt=t.prompt)


def chamber_framing(cfg: Config) -> Framing:
    """[chamber] command_terminator, reply_terminator -> the EC1x driver's Framing (no prompt)."""
    c = cfg.chamber
    return Framing(command_terminator=c.command_terminator, reply_terminator=c.reply_terminator, prompt="")


def table_twin(cfg: Config, world: World) -> RateTableTwin:
    """The 1291BR twin, framed as [table] says (command terminator, sim_reply_terminator, sim_prompt_terminator),
    its servo at power-up as [sim] table_servo_on_at_start says."""
    t = cfg.table
    return RateTableTwin(
        world,
        command_end=terminator(t.command_terminator),
        reply_end=terminator(t.sim_reply_terminator),
        prompt_end=b"" if t.sim_prompt_terminator == "none" else terminator(t.sim_prompt_terminator),
        servo_on=cfg.sim.table_servo_on_at_start,
    )


def table_encoder(cfg: Config, world: World) -> TableEncoder | None:
    """The 1291BR twin's encoder A/B on the HF2 twin's DIO, on the bits [table] says it is cabled to, with the
    [sim] table_encoder_lines_per_rev of the twin's own table; None if [table] encoder_on_dio is off."""
    t = cfg.table
    if not t.encoder_on_dio:
        return None
    return TableEncoder(
        world,
        lines_per_rev=cfg.sim.table_encoder_lines_per_rev,
        a_bit=t.encoder_a_dio_bit,
        b_bit=t.encoder_b_dio_bit,
    )


def chamber_twin(cfg: Config, world: World) -> ChamberTwin:
    """The EC1x twin, framed as [chamber] says (command terminator, sim_reply_terminator), answering as [sim]
    says (chamber_status_layout, chamber_self_test, chamber_acknowledges_settings, chamber_powered_at_start,
    chamber_set_query_while_off, chamber_silent_commands)."""
    c, s = cfg.chamber, cfg.sim
    return ChamberTwin(
        world,
        command_end=terminator(c.command_terminator),
        reply_end=terminator(c.sim_reply_terminator),
        status_layout=s.chamber_status_layout,
        self_test=s.chamber_self_test,
        acknowledges_settings=s.chamber_acknowledges_settings,
        powered_at_start=s.chamber_powered_at_start,
        set_query_while_off=s.chamber_set_query_while_off,
        silent_commands=s.chamber_silent_commands,
    )


def is_visa_address(address: str) -> bool:
    """A VISA resource string (GPIB0::6::INSTR, ASRL3::INSTR, TCPIP0::host::INSTR) rather than a pyserial URL:
    every VISA resource name has '::', no pyserial URL or device path does."""
    return "::" in address


def lockin_driver(cfg: Config, session: Session, device_id: str) -> HF2LI:
    """The HF2LI driver on a session (to the data server or to the twin), with the [lockin] wiring and the
    AuxOut value of its safe state (lockin.output_safe_v)."""
    lk = cfg.lockin
    return HF2LI(
        session,
        device_id,
        wiring=lk,
        output_safe_v=lk.output_safe_v,
        port=lk.port,
        allow_version_mismatch=lk.allow_version_mismatch,
    )


def table_driver(cfg: Config, open_port: Callable[[], Any]) -> Aerosmith1291BR:
    """The 1291BR driver on a newly opened port, with the [table] limits, framing and servo command."""
    t = cfg.table
    return Aerosmith1291BR(
        open_port(),
        max_rate_dps=t.max_rate_dps,
        max_accel_dps2=t.max_accel_dps2,
        port_factory=open_port,
        framing=table_framing(cfg),
        servo_enable_command=t.servo_enable_command or None,
    )


def chamber_link(cfg: Config, open_link: Callable[[], Any]) -> LineTransport:
    """The chamber's line transport: a VISA resource if [chamber] port is a VISA address, else a serial port;
    `open_link` opens one (it is also the reopen factory of reconnect())."""
    name, framing = SunEC1xChamber.NAME, chamber_framing(cfg)
    if is_visa_address(cfg.chamber.port):
        return VisaLineTransport(open_link(), name=name, framing=framing, reopen=open_link)
    return SerialLineTransport(open_link(), name=name, framing=framing, port_factory=open_link)


def chamber_driver(cfg: Config, open_link: Callable[[], Any]) -> SunEC1xChamber:
    """The EC1x driver on a newly opened port or VISA resource: identified, then the [chamber] min_c/max_c
    written to the controller as its own limits (LTL=, UTL=), so that the controller refuses a setpoint outside
    them even if the host goes wrong."""
    c = cfg.chamber
    chamber = SunEC1xChamber(
        chamber_link(cfg, open_link),
        min_c=c.min_c,
        max_c=c.max_c,
        max_ramp_c_per_min=c.max_ramp_c_per_min,
        safe_setpoint_c=c.safe_setpoint_c,
        framing=chamber_framing(cfg),
        ack=c.setting_ack,
    )
    # a transient fault at connect (a reply lost on a noisy line) gets the same bounded reconnects as a fault
    # during a campaign ([recovery] reconnect_attempts); what still fails after them is reported

    def identify_and_limit() -> None:
        chamber.identify()
        chamber.write_limits()

    steps: list[Callable[[], None]] = [identify_and_limit]
    steps += [chamber.reconnect] * cfg.recovery.reconnect_attempts  # reopen, identify, write the limits again
    for n, step in enumerate(steps, start=1):
        try:
            step()
            return chamber
        except InstrumentError:
            if n == len(steps):
                chamber.close()
                raise
    return chamber


def generator_driver(cfg: Config, open_resource: Callable[[], Any]) -> DS345:
    """The DS345 driver on a newly opened VISA resource, with the [generator] amplitude limit."""
    return DS345(open_resource(), max_amplitude_vpp=cfg.generator.max_amplitude_vpp, reopen=open_resource)


# ---------------------------------------------------------------------------------------- one bench
class _Bench:
    """What the instruments of one configuration share: the twins' world, the fault injector and the closers
    of the twins' pty/socket servers. Each instrument is connected on its own (`connect(name)`)."""

    def __init__(
        self, cfg: Config, world: World | None, clock: str | None = None, pacing: RealTimePacing | None = None
    ) -> None:
        self.cfg = cfg
        self.pacing = pacing
        if world is None and cfg.any_sim:
            world = make_world(cfg, clock)
        self.world = world
        self.closers: list[Callable[[], None]] = []
        plan = fault_plan(cfg)
        self.faults = FaultInjector(world, plan) if world is not None and plan.any else None

    def connect(self, name: str) -> Instrument:
        """Connect the instrument `name` (real or twin as the configuration says); InstrumentError if it cannot."""
        log.info("connecting %s (%s)", name, "twin" if getattr(self.cfg, name).sim else "hardware")
        try:
            return getattr(self, f"_{name}")()
        except (OSError, ValueError) as exc:
            raise InstrumentError(f"{name}: {exc}") from exc

    def _lockin(self) -> HF2LI:
        lk, world, faults = self.cfg.lockin, self.world, self.faults
        if lk.sim:
            assert world is not None
            twin = HF2DataServerTwin(
                world,
                gyro_params(self.cfg),
                self.cfg.sim.seed,
                hf2_wiring(self.cfg),
                device_id=SIM_DEVICE_ID,
                host=lk.host,
                port=lk.port,
                rate_set=self.cfg.sim.hf2_rate_set,
                options=tuple(self.cfg.sim.hf2_options),
                timestamp_offset_ticks=self.cfg.sim.hf2_timestamp_offset_ticks,
            )
            twin.table_encoder = table_encoder(self.cfg, world)
            if faults is not None:
                faults.attach_hf2(twin)
            paced = self.pacing is not None or not self.cfg.all_sim
            connection: Any = RealTimePacedConnection(twin, world, self.pacing) if paced else twin
            return lockin_driver(self.cfg, Session(lk.host, lk.port, hf2=True, connection=connection), SIM_DEVICE_ID)
        return lockin_driver(self.cfg, hf2_session(self.cfg), lk.device)

    def _generator(self) -> DS345:
        g, world, faults = self.cfg.generator, self.world, self.faults
        if g.sim:
            assert world is not None
            ds_twin = DS345Twin(world)

            # on an RS-232 address the twin ends its replies CR, as public serial DS345 code reads a real unit
            reply_end = b"\r" if g.resource.upper().startswith("ASRL") else b"\n"

            def open_gen_twin() -> Any:
                return ds_twin.resource(g.resource, reply_end=reply_end)

            open_gen: Callable[[], Any] = open_gen_twin
            if faults is not None:
                faults.attach_ds345(ds_twin)
                open_gen = faults.visa_link("generator", open_gen)
        else:
            open_gen = _visa_opener("generator (DS345)", g.resource, g.visa_backend, g.timeout_ms)
        return generator_driver(self.cfg, open_gen)

    def _table(self) -> Aerosmith1291BR:
        return table_driver(self.cfg, self.table_port())

    def _chamber(self) -> SunEC1xChamber:
        return chamber_driver(self.cfg, self.chamber_port())

    def table_port(self) -> Callable[[], Any]:
        t = self.cfg.table
        if t.sim:
            assert self.world is not None
            return _twin_port(
                _faulty(self.faults, "table", table_twin(self.cfg, self.world)),
                t.sim_transport,
                t.baudrate,
                t.timeout_s,
                self.closers,
            )
        return _serial_port(t.port, t.baudrate, t.timeout_s)

    def chamber_port(self) -> Callable[[], Any]:
        """The chamber's opener: a VISA resource (its twin behind a VISA-like resource) for a VISA address,
        else a serial port (its twin in-process, over a pty or a socket)."""
        c = self.cfg.chamber
        visa = is_visa_address(c.port)
        if c.sim:
            assert self.world is not None
            twin = _faulty(self.faults, "chamber", chamber_twin(self.cfg, self.world))
            if visa:
                return lambda: LineTwinVisaResource(twin, c.port)
            return _twin_port(twin, c.sim_transport, c.baudrate, c.timeout_s, self.closers)
        if visa:
            return _visa_opener("chamber (EC1x)", c.port, c.visa_backend, round(c.timeout_s * 1000))
        return _serial_port(c.port, c.baudrate, c.timeout_s)

    def close(self) -> None:
        for stop in self.closers:
            with contextlib.suppress(Exception):
                stop()
        self.closers.clear()


@dataclass
class RealTimePacing:
    """An all-twin bench paced to the wall clock (a rehearsal), and what the pacing measured: the HF2 twin's own
    CPU time (`twin_cpu_s`: thread CPU time, time.thread_time, spent inside its polls, which run on the calling
    thread), the polls, the wall time waited for the clock (`waited_s`), and the largest lag of the twin's clock
    behind the wall clock when a poll returned (`max_late_s`: the host could not keep up when it grows)."""

    twin_cpu_s: float = 0.0
    polls: int = 0
    waited_s: float = 0.0
    max_late_s: float = 0.0


class RealTimePacedConnection:
    """The HF2 twin's data-server connection, paced to the wall clock (a mixed bench: real instruments beside
    the lock-in twin must see real time; an all-twin rehearsal, `RealTimePacing`). `poll(recording_time_s, ...)`
    advances the twin's world as usual, then returns only once that much wall time has passed since the first
    poll, as a data server answers; every other call goes to the twin unchanged."""

    def __init__(self, twin: HF2DataServerTwin, world: World, pacing: RealTimePacing | None = None) -> None:
        self._twin = twin
        self._world = world
        self._wall0: float | None = None
        self.pacing = pacing if pacing is not None else RealTimePacing()

    def poll(
        self, recording_time_s: float, timeout_ms: int = 500, flags: int = 0, flat: bool = False, group_id: int = 1
    ) -> dict[str, Any]:
        if self._wall0 is None:
            self._wall0 = time.monotonic() - self._world.t
        cpu0 = time.thread_time()
        data = self._twin.poll(recording_time_s, timeout_ms, flags, flat, group_id)
        pacing = self.pacing
        pacing.twin_cpu_s += time.thread_time() - cpu0
        pacing.polls += 1
        lag = self._world.t - (time.monotonic() - self._wall0)
        if lag > 0:
            time.sleep(lag)  # real time, as a data server answers
            pacing.waited_s += lag
        else:
            pacing.max_late_s = max(pacing.max_late_s, -lag)
        return data

    def __getattr__(self, name: str) -> Any:
        return getattr(self._twin, name)


def hf2_session(cfg: Config) -> Session:
    """A zhinst-toolkit session to the real HF2 data server at [lockin] host:port ([lockin]
    allow_version_mismatch; a refusal names both LabOne versions and the ways out: drivers/hf2li.py)."""
    lk = cfg.lockin
    return open_hf2_session(lk.host, lk.port, lk.allow_version_mismatch)


@dataclass
class Connected:
    """One instrument connected on its own (bring-up): close() releases it and whatever twin serves it."""

    name: str
    instrument: Instrument
    simulated: bool
    _bench: _Bench

    def close(self) -> None:
        try:
            self.instrument.close()
        finally:
            self._bench.close()


def connect_instrument(cfg: Config, name: str, world: World | None = None) -> Connected:
    """Connect only the instrument `name` ("lockin", "generator", "table" or "chamber"); nothing else is
    touched, so a bench where only that instrument is cabled can bring it up. A twin that is not the lock-in
    runs on the wall clock (nothing else advances its world)."""
    if name not in INSTRUMENT_NAMES:
        raise ValueError(f"unknown instrument {name!r}; one of {', '.join(INSTRUMENT_NAMES)}")
    bench = _Bench(cfg, world, clock=None if name == "lockin" else "wall")
    try:
        inst = bench.connect(name)
    except BaseException:
        bench.close()
        raise
    return Connected(name=name, instrument=inst, simulated=bool(getattr(cfg, name).sim), _bench=bench)


def build_station(cfg: Config, world: World | None = None, pacing: RealTimePacing | None = None) -> Station:
    """Connect every instrument of the configuration (twins where `sim = true`). `world`: the twins' shared
    world (default: a new one from [sim]; tests pass their own to look at the physical state). `pacing`: pace
    the lock-in twin to the wall clock and poll hardware-length blocks ([lockin] poll_interval_s) even when every
    instrument is a twin (a rehearsal at real time; the object collects what the pacing measured); a bench with
    real instruments is paced anyway. If one instrument cannot be connected, those already connected are
    closed and the InstrumentError names it."""
    if pacing is not None and not cfg.lockin.sim:
        raise ValueError("real-time pacing applies to the lock-in twin: [lockin] sim is false (hardware is real time)")
    if cfg.lockin.sim:
        gyro_params(cfg)  # a [sim] the twin cannot simulate is bad input, found before anything is connected
    bench = _Bench(cfg, world, pacing=pacing)
    world = bench.world
    connected: dict[str, Instrument] = {}
    try:
        for name in INSTRUMENT_NAMES:
            try:
                connected[name] = bench.connect(name)
            except InstrumentError as exc:
                raise InstrumentError(f"{name}: {exc}") from exc
    except BaseException:
        for inst in connected.values():
            with contextlib.suppress(Exception):
                inst.close()
        bench.close()
        raise
    lk = cfg.lockin
    lockin, generator, table, chamber = (connected[n] for n in INSTRUMENT_NAMES)
    if not (
        isinstance(lockin, LockIn)
        and isinstance(generator, FunctionGenerator)
        and isinstance(table, RateTable)
        and isinstance(chamber, ThermalChamber)
    ):
        raise TypeError(f"the bench's instruments do not implement their interfaces: {connected}")
    station = Station(
        lockin=lockin,
        generator=generator,
        table=table,
        chamber=chamber,
        simulated={n: bool(getattr(cfg, n).sim) for n in INSTRUMENT_NAMES},
        truth=_WorldTruth(world) if (world is not None and lk.sim) else None,
        restore=(lambda state: restore_world(world, state)) if world is not None else None,
    )
    # a paced twin (mixed bench) polls like the hardware: short blocks in real time
    twin_blocks = lk.sim and cfg.all_sim and pacing is None
    station.poll_interval_s = lk.sim_poll_interval_s if twin_blocks else lk.poll_interval_s
    station.on_close.append(bench.close)
    faults = bench.faults
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
    world back where the file says it was (time, chamber setpoint and air, gyro temperature, table angle)."""
    world.restore(
        time_s=state.get("last_time"),
        chamber_setpoint_c=state.get("chamber_setpoint_c"),
        chamber_air_c=state.get("chamber_temperature_c"),
        gyro_c=state.get("gyro_temperature_c"),
        table_angle_deg=state.get("table_angle_deg"),
    )


# ---------------------------------------------------------------------------------------- raw transports
def open_raw_serial(cfg: Config, name: str) -> tuple[Any, Framing, Callable[[], None], bool]:
    """The open serial port of the table or the chamber (or of its twin), its configured framing, a closer,
    and whether the port answers at once (an in-process twin): for the raw console, nothing else is connected
    and no driver speaks on it."""
    if name not in ("table", "chamber"):
        raise ValueError(f"no serial raw console for {name!r}: table or chamber")
    if name == "chamber" and is_visa_address(cfg.chamber.port):
        raise InstrumentError(
            f"the chamber is at the VISA address {cfg.chamber.port!r}, not on a serial port: the serial raw "
            "console cannot reach it (use `qmg-lab instruments` or a VISA tool such as pyvisa-shell)"
        )
    bench = _Bench(cfg, None, clock="wall")
    try:
        port = (bench.table_port() if name == "table" else bench.chamber_port())()
    except BaseException:
        bench.close()
        raise
    framing = table_framing(cfg) if name == "table" else chamber_framing(cfg)
    section = getattr(cfg, name)

    def close() -> None:
        try:
            port.close()
        finally:
            bench.close()

    return port, framing, close, bool(section.sim and section.sim_transport == "inprocess")


def open_raw_visa(cfg: Config) -> tuple[Any, Callable[[], None]]:
    """The DS345's VISA resource (or its twin's), with the driver's terminations and serial framing set."""
    conn = connect_instrument(cfg, "generator")
    if not isinstance(conn.instrument, DS345):
        raise TypeError(f"the generator is a {type(conn.instrument).__name__}, not the DS345 driver")
    return conn.instrument.resource, conn.close


def open_raw_hf2(cfg: Config) -> tuple[Any, str, Callable[[], None]]:
    """The HF2 data-server connection (zhinst ziDAQServer, or the twin itself) and the device id."""
    lk = cfg.lockin
    if lk.sim:
        world = make_world(cfg)
        twin = HF2DataServerTwin(
            world,
            gyro_params(cfg),
            cfg.sim.seed,
            hf2_wiring(cfg),
            device_id=SIM_DEVICE_ID,
            host=lk.host,
            port=lk.port,
            rate_set=cfg.sim.hf2_rate_set,
            options=tuple(cfg.sim.hf2_options),
            timestamp_offset_ticks=cfg.sim.hf2_timestamp_offset_ticks,
        )
        twin.connectDevice(SIM_DEVICE_ID, "USB")
        return twin, SIM_DEVICE_ID, lambda: None
    session = hf2_session(cfg)
    try:
        session.connect_device(lk.device)
    except Exception as exc:
        raise InstrumentError(f"the HF2 data server does not know device {lk.device}: {exc}") from exc
    return session.daq_server, lk.device, lambda: None
