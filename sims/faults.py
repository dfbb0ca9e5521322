"""Fault injection in the twins, deterministic from a seed and driven by the world clock.

`FaultInjector(world, FaultPlan(...))` takes plain values (sims import nothing of qmg_lab; the station turns the
configuration's [sim.faults] into a FaultPlan) and plugs into the twins' existing hooks:

* per-transaction faults, one uniform draw u per reply from numpy's PCG64 seeded with (seed, channel):
  - serial (1291BR table, EC1x chamber): `FaultableTwin.fault_hook(line, reply)`: u < p_timeout -> the reply is
    lost (b"", the driver's read times out); p_timeout <= u < p_timeout + p_garble -> garbled (one byte replaced
    by 0xFF, which no printable-ASCII reply contains) or truncated (cut before its first terminator), half and
    half from a second draw. The command itself was executed: only its reply is damaged, as on a noisy line.
  - VISA (DS345): `DS345Twin.reply_hook(framed_reply)`: the same split with p_visa_timeout / p_visa_garble
    (timeout: None, the reply is never queued).
* link drops: `serial_link(name, twin)` / `visa_link(name, open_resource)` put a gate between a driver's port
  and the twin. While world time t lies in [at, at + duration) for one of `disconnect_at_s`, nothing reaches the
  instrument and nothing comes back (serial: b""; VISA: VisaIOError connection lost, and reopening fails with
  resource not found). After the interval the same port works again: a disconnect followed by a reconnect.
* the HF2 link: `attach_hf2(server)` gates the data-server twin's connection API (poll, get*, set*, subscribe,
  sync, connectDevice, ...: HF2_LINK_CALLS) when `hf2_disconnect_at_s` is set. While world time lies in
  [at, at + hf2_disconnect_duration_s), every call raises zhinst-core's ConnectionError (a RuntimeError and an
  OSError, zhinst.core.errors; RuntimeError itself before zhinst-core had that module), as a client of a data
  server whose link broke gets it; the toolkit session and the driver see exactly that. The instrument runs on
  meanwhile (`server.run_unobserved`): each failed call lets world time pass by what the host waited for it, a
  poll's recording time or `hf2_call_timeout_s` for any other call (*assumed*: how long a zhinst-core call to
  a dead link takes to fail is not documented; a configuration key). So a drop ends after a bounded number of
  calls, and the first block after it shows the samples the host missed as a timestamp gap.
* timed events, fired from `World.on_advance(t0, t1)` at the start of the block [t0, t1) that contains the
  event time (block resolution: the same block for the same seed and poll length). Blocks tile world time, so
  each event fires once; an event before the world's time when the injector starts (a resumed run's restored
  world) never fires:
  - interlock trip: `world.trip_interlock()` (the table brakes to 0 and refuses JOG/SGO).
  - chamber overshoot: `world.chamber.disturbance_c = A exp(-(t0 - at) / decay)` for t0 >= at (set each block;
    the measured air and the gyro see it), cleared once below 1 mK.
  - chamber sensor dropout: for [at, at + duration) the EC1x answers "C1?" with "?SENSOR" (assumed form of a
    sensor fault, like its other "?" refusals).
  - HF2 sample loss: `hf2.drop_samples(count)` for the block (a timestamp gap and the sample-loss flag).
  - PLL unlock: `hf2.force_pll_unlock(duration)` from the block start.

Every fault injected is logged (`events`: time, kind, instrument, detail) so tests and benchmarks can check
that each one ended recovered or in the safe state.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pyvisa.constants
import pyvisa.errors

from sims.world import World

try:  # what zhinst-core raises when the data server cannot be reached
    from zhinst.core.errors import ConnectionError as HF2LinkError
except ImportError:  # pragma: no cover - zhinst-core before its errors module raised RuntimeError
    HF2LinkError = RuntimeError  # type: ignore[assignment,misc]

GARBLE_BYTE = 0xFF
SENSOR_FAULT_REPLY = b"?SENSOR\r\n"
OVERSHOOT_FLOOR_C = 1e-3
_CHANNELS = {"table": 1, "chamber": 2, "generator": 3}
# the HF2 data-server connection's calls (zhinst.core.ziDAQServer, API level 1) that fail while its link is down
HF2_LINK_CALLS = (
    "poll",
    "get",
    "getInt",
    "getDouble",
    "getString",
    "getSample",
    "set",
    "setInt",
    "setDouble",
    "setString",
    "syncSetInt",
    "syncSetDouble",
    "syncSetString",
    "sync",
    "subscribe",
    "unsubscribe",
    "connectDevice",
    "disconnectDevice",
    "listNodes",
    "listNodesJSON",
    "echoDevice",
    "update",
)


@dataclass(frozen=True)
class FaultPlan:
    """What to inject. Probabilities per reply; times in world seconds; durations in seconds.

    Every field is required: the configuration's [sim.faults] section (and [sim] seed) exposes each one, and the
    schema (qmg_lab/config/schema.py SimFaultsSection) is the one place of their defaults (nothing injected),
    bounds and descriptions; qmg_lab/station.py `fault_plan` maps a configuration to this class.
    """

    seed: int
    serial_timeout_prob: float
    serial_garble_prob: float
    visa_timeout_prob: float
    visa_garble_prob: float
    disconnect_at_s: tuple[float, ...]
    disconnect_duration_s: float
    disconnect_instrument: str
    interlock_trip_at_s: float | None
    chamber_overshoot_at_s: float | None
    chamber_overshoot_c: float
    chamber_overshoot_decay_s: float
    chamber_dropout_at_s: float | None
    chamber_dropout_duration_s: float
    sample_loss_at_s: tuple[float, ...]
    sample_loss_count: int
    pll_unlock_at_s: float | None
    pll_unlock_duration_s: float
    hf2_disconnect_at_s: tuple[float, ...]
    hf2_disconnect_duration_s: float
    hf2_call_timeout_s: float

    def __post_init__(self) -> None:
        object.__setattr__(self, "hf2_disconnect_at_s", tuple(float(t) for t in self.hf2_disconnect_at_s))
        if self.hf2_call_timeout_s <= 0:
            raise ValueError("FaultPlan.hf2_call_timeout_s must be > 0 (each failed call lets world time pass)")
        for name in ("serial_timeout_prob", "serial_garble_prob", "visa_timeout_prob", "visa_garble_prob"):
            p = getattr(self, name)
            if not 0.0 <= p <= 1.0:
                raise ValueError(f"FaultPlan.{name} = {p!r} must lie in [0, 1]")
        for a, b in (("serial_timeout_prob", "serial_garble_prob"), ("visa_timeout_prob", "visa_garble_prob")):
            if getattr(self, a) + getattr(self, b) > 1.0:
                raise ValueError(f"FaultPlan.{a} + {b} must not exceed 1")
        if self.disconnect_instrument not in _CHANNELS:
            raise ValueError(
                f"FaultPlan.disconnect_instrument = {self.disconnect_instrument!r} must be one of {sorted(_CHANNELS)}"
            )
        if self.sample_loss_count < 1:
            raise ValueError(f"FaultPlan.sample_loss_count = {self.sample_loss_count!r} must be >= 1")
        if self.chamber_overshoot_decay_s <= 0:
            raise ValueError("FaultPlan.chamber_overshoot_decay_s must be > 0")

    @property
    def any(self) -> bool:
        """True if this plan injects anything at all."""
        return bool(
            self.serial_timeout_prob
            or self.serial_garble_prob
            or self.visa_timeout_prob
            or self.visa_garble_prob
            or self.disconnect_at_s
            or self.interlock_trip_at_s is not None
            or self.chamber_overshoot_at_s is not None
            or self.chamber_dropout_at_s is not None
            or self.sample_loss_at_s
            or self.pll_unlock_at_s is not None
            or self.hf2_disconnect_at_s
        )


@dataclass(frozen=True)
class FaultEvent:
    """One injected fault: world time (s), kind, instrument, detail."""

    time_s: float
    kind: str
    instrument: str
    detail: str = ""

    def as_dict(self) -> dict[str, Any]:
        return {"time_s": self.time_s, "kind": self.kind, "instrument": self.instrument, "detail": self.detail}


@dataclass
class _Timed:
    at_s: float
    kind: str
    fire: Callable[[float], None]
    done: bool = False


@dataclass
class FaultInjector:
    """Injects a FaultPlan into the twins sharing `world`. Attach the twins with the attach_* methods."""

    world: World
    plan: FaultPlan
    events: list[FaultEvent] = field(default_factory=list)

    def __post_init__(self) -> None:
        self._rngs = {
            name: np.random.default_rng([int(self.plan.seed), 0x6661756C, ch]) for name, ch in _CHANNELS.items()
        }
        self._hf2: Any = None
        self._timed: list[_Timed] = []
        self._overshoot_active = False
        self._down: set[str] = set()  # links currently down (for logging the edges once)
        p = self.plan
        if p.interlock_trip_at_s is not None:
            self._timed.append(_Timed(p.interlock_trip_at_s, "interlock_trip", self._trip))
        if p.chamber_overshoot_at_s is not None:
            self._timed.append(_Timed(p.chamber_overshoot_at_s, "chamber_overshoot", self._overshoot_start))
        for at in p.sample_loss_at_s:
            self._timed.append(_Timed(float(at), "sample_loss", self._sample_loss))
        if p.pll_unlock_at_s is not None:
            self._timed.append(_Timed(p.pll_unlock_at_s, "pll_unlock", self._pll_unlock))
        self._timed.sort(key=lambda e: e.at_s)
        self.world.on_advance.append(self._on_advance)

    # ================================================================== attaching the twins
    def attach_serial(self, name: str, twin: Any) -> None:
        """Per-reply faults on a FaultableTwin (table or chamber) through its fault_hook."""
        twin.fault_hook = lambda line, reply: self._serial_reply(name, line, reply)

    def attach_ds345(self, twin: Any) -> None:
        """Per-reply faults on the DS345 twin through its reply_hook."""
        twin.reply_hook = self._visa_reply

    def attach_hf2(self, server: Any) -> None:
        """The HF2 data-server twin receiving sample loss and PLL unlock, and whose link drops (its connection
        calls gated on this instance, when the plan drops the HF2 link)."""
        self._hf2 = server
        if self.plan.hf2_disconnect_at_s:
            for name in HF2_LINK_CALLS:
                if hasattr(server, name):
                    setattr(server, name, self._hf2_gated(name, getattr(server, name)))

    def _hf2_gated(self, name: str, call: Callable[..., Any]) -> Callable[..., Any]:
        """`call` as it behaves across the HF2 link: ConnectionError while the link is down, the instrument
        running on for as long as the host waited (module docstring)."""

        def gated(*args: Any, **kwargs: Any) -> Any:
            if not self.link_down("lockin"):
                return call(*args, **kwargs)
            waited = self.plan.hf2_call_timeout_s
            if name == "poll":
                waited = float(kwargs.get("recording_time_s", args[0] if args else waited))
            self._hf2.run_unobserved(waited)
            host, port = getattr(self._hf2, "host", "localhost"), getattr(self._hf2, "port", 8005)
            raise HF2LinkError(f"Connection to the data server at {host}:{port} lost ({name}; HF2 link down)")

        return gated

    def serial_link(self, name: str, twin: Any) -> _SerialGate:
        """A LineTwin to hand to the port in place of `twin`: it drops the link during disconnects."""
        return _SerialGate(self, name, twin)

    def visa_link(self, name: str, open_resource: Callable[[], Any]) -> Callable[[], Any]:
        """A resource opener that fails while the link is down and yields resources that fail while it is."""

        def opener() -> Any:
            if self.link_down(name):
                raise pyvisa.errors.VisaIOError(pyvisa.constants.StatusCode.error_resource_not_found)
            return _VisaGate(self, name, open_resource())

        return opener

    # ================================================================== state queries
    def link_down(self, name: str) -> bool:
        """True while `name`'s link is in one of its disconnect intervals (world time); "lockin": the HF2's."""
        p = self.plan
        if name == "lockin":
            starts, duration = p.hf2_disconnect_at_s, p.hf2_disconnect_duration_s
        elif name == p.disconnect_instrument:
            starts, duration = p.disconnect_at_s, p.disconnect_duration_s
        else:
            return False
        if not starts:
            return False
        with self.world.lock:
            t = self.world.now()
        down = any(at <= t < at + duration for at in starts)
        if down and name not in self._down:
            self._down.add(name)
            self._log(t, "disconnect", name, f"link down for {duration:g} s")
        elif not down and name in self._down:
            self._down.discard(name)
            self._log(t, "link_restored", name)
        return down

    def sensor_dropout(self, t: float) -> bool:
        p = self.plan
        return p.chamber_dropout_at_s is not None and (
            p.chamber_dropout_at_s <= t < p.chamber_dropout_at_s + p.chamber_dropout_duration_s
        )

    def count(self, kind: str | None = None) -> int:
        """Number of faults injected (of one kind); link_restored edges are not faults."""
        return sum(1 for e in self.events if e.kind != "link_restored" and (kind is None or e.kind == kind))

    # ================================================================== per-reply faults
    def _draw(self, name: str, p_timeout: float, p_garble: float) -> str:
        if p_timeout == 0.0 and p_garble == 0.0:
            return ""
        rng = self._rngs[name]
        u = float(rng.random())
        if u < p_timeout:
            return "timeout"
        if u < p_timeout + p_garble:
            return "garbled" if rng.random() < 0.5 else "truncated"
        return ""

    def _damage(self, name: str, reply: bytes, kind: str, terminator: bytes) -> bytes:
        if kind == "garbled":
            i = int(self._rngs[name].integers(0, max(1, len(reply) - len(terminator))))
            return reply[:i] + bytes([GARBLE_BYTE]) + reply[i + 1 :]
        cut = reply.find(terminator)
        cut = len(reply) if cut < 0 else cut
        return reply[: int(self._rngs[name].integers(0, cut + 1))]

    def _serial_reply(self, name: str, line: bytes, reply: bytes) -> bytes:
        with self.world.lock:
            t = self.world.now()
        if name == "chamber" and line.rstrip(b"\r") == b"C1?" and self.sensor_dropout(t):
            if not any(e.kind == "sensor_dropout" for e in self.events):
                self._log(
                    t, "sensor_dropout", name, f"C1? answers ?SENSOR for {self.plan.chamber_dropout_duration_s:g} s"
                )
            return SENSOR_FAULT_REPLY
        if not reply:
            return reply
        kind = self._draw(name, self.plan.serial_timeout_prob, self.plan.serial_garble_prob)
        if not kind:
            return reply
        self._log(t, f"serial_{kind}", name, f"reply to {line!r}")
        if kind == "timeout":
            return b""
        return self._damage(name, reply, kind, b"\r")

    def _visa_reply(self, framed: bytes) -> bytes | None:
        kind = self._draw("generator", self.plan.visa_timeout_prob, self.plan.visa_garble_prob)
        if not kind:
            return framed
        with self.world.lock:
            t = self.world.now()
        self._log(t, f"visa_{kind}", "generator", f"reply {framed!r}")
        if kind == "timeout":
            return None
        return self._damage("generator", framed, kind, b"\n")

    # ================================================================== timed events
    def _on_advance(self, t0: float, t1: float) -> None:
        for ev in self._timed:
            if not ev.done and t0 <= ev.at_s < t1:
                ev.done = True
                ev.fire(t0)
        p = self.plan
        if self._overshoot_active and p.chamber_overshoot_at_s is not None:
            d = p.chamber_overshoot_c * math.exp(-max(0.0, t0 - p.chamber_overshoot_at_s) / p.chamber_overshoot_decay_s)
            if d < OVERSHOOT_FLOOR_C:
                d, self._overshoot_active = 0.0, False
            self.world.chamber.disturbance_c = d

    def _trip(self, t: float) -> None:
        self.world.trip_interlock()
        self._log(t, "interlock_trip", "table")

    def _overshoot_start(self, t: float) -> None:
        self._overshoot_active = True
        self._log(
            t,
            "chamber_overshoot",
            "chamber",
            f"+{self.plan.chamber_overshoot_c:g} degC, decay {self.plan.chamber_overshoot_decay_s:g} s",
        )

    def _sample_loss(self, t: float) -> None:
        if self._hf2 is None:
            return
        self._hf2.drop_samples(self.plan.sample_loss_count)
        self._log(t, "sample_loss", "lockin", f"{self.plan.sample_loss_count} samples")

    def _pll_unlock(self, t: float) -> None:
        if self._hf2 is None:
            return
        self._hf2.force_pll_unlock(self.plan.pll_unlock_duration_s)
        self._log(t, "pll_unlock", "lockin", f"{self.plan.pll_unlock_duration_s:g} s")

    def _log(self, t: float, kind: str, instrument: str, detail: str = "") -> None:
        self.events.append(FaultEvent(float(t), kind, instrument, detail))


class _SerialGate:
    """A LineTwin between a port and a twin: while the link is down a line reaches nobody and gets no reply."""

    def __init__(self, injector: FaultInjector, name: str, twin: Any) -> None:
        self.injector, self.name, self.twin = injector, name, twin
        self.line_end = getattr(twin, "line_end", b"\n")  # the port splits command lines as the twin does

    def respond(self, line: bytes) -> bytes:
        if self.injector.link_down(self.name):
            return b""
        return self.twin.respond(line)


class _VisaGate:
    """A VISA-like resource whose I/O fails with 'connection lost' while the link is down."""

    def __init__(self, injector: FaultInjector, name: str, resource: Any) -> None:
        object.__setattr__(self, "_gate", (injector, name, resource))

    def _check(self) -> None:
        injector, name, _ = self._gate
        if injector.link_down(name):
            raise pyvisa.errors.VisaIOError(pyvisa.constants.StatusCode.error_connection_lost)

    def write(self, message: str) -> int:
        self._check()
        return self._gate[2].write(message)

    def read(self) -> str:
        self._check()
        return self._gate[2].read()

    def query(self, message: str) -> str:
        self._check()
        return self._gate[2].query(message)

    def read_bytes(self, count: int) -> bytes:  # the DS345 driver's byte-wise reading on an ASRL resource
        self._check()
        return bytes(self._gate[2].read_bytes(count))

    def clear(self) -> None:
        self._check()
        self._gate[2].clear()

    def close(self) -> None:
        self._gate[2].close()

    def __getattr__(self, attr: str) -> Any:  # termination, timeout, resource_name, ...
        return getattr(self._gate[2], attr)

    def __setattr__(self, attr: str, value: Any) -> None:
        setattr(self._gate[2], attr, value)
