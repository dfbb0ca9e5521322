"""Zurich Instruments HF2LI (PLL + PID options) over zhinst-toolkit: the gyroscope's loops and its data stream.

Transport: a ``zhinst.toolkit.Session`` to an HF2 data server (API level 1, port 8005): hardware with
``Session(host, port, hf2=True)``, the twin with ``Session(host, hf2=True, connection=twin)``. The same code runs
on both. Node settings and channel assignment: drivers/hf2_nodes.py and docs/wiring.md.

Stream protocol (docs/wiring.md): ``session.sync()``, subscribe the drive and the sense demodulator's ``sample``
(demods 0 and 1 unless a PLL uses demod 1: drivers/hf2_nodes.py ``carrier_plan``), then ``session.poll(duration)``
returns every sample since the last poll.

Pairing: no source says two HF2 demodulators stamp their samples identically, so each sense sample is paired with
the drive sample nearest in time when |t_sense - t_drive| < T/2, T = clockbase / rate ticks (``pair_nearest``):
``clockbase`` is read from the device (210 MHz on an HF2, nodedoc "Provides clockbase value for the device"), the
rate read back after the device rounded it; at 1800 Sa/s T = 116 667 ticks and the tolerance 58 333 ticks
(278 us). The unpaired samples at a block's end that may pair with the next poll's are held back for it; every
other unpaired sample leaves a gap in the paired timestamps and is counted as lost. t = (timestamp_sense -
t0_ticks) / clockbase with t0_ticks the first paired sense timestamp of the stream. Lost samples = sum over gaps
of the paired timestamps of (gap / T - 1), including the gap between the last pair of the previous block and the
first of this one; the device flag ``status/flags/demodsampleloss`` counts as at least one lost sample when the
gaps show none. ``demod_timestamp_offset()`` (in ``state()``, hence ``qmg-lab instruments``) reports the offset
of the two demodulators' timestamps.

PLL lock: ``pll_locked`` of a block is true when every PLL the carriers need (PLL 1, and the PLL that locks the
forcer carrier's oscillator without MF) reports ``plls/n/locked`` = 1 ("Lock indicator for the PLL", nodedoc_hf2
.json) and its bit of ``status/flags/binary`` ("b20": PLL 1 locked, "b21": PLL 2 locked), read after each poll.

Instrument as it is: at connect the driver reads ``features/devtype`` and ``features/options`` (kept in state(),
hence in the run file's snapshot), refuses an instrument without the PLL or PID option (MissingOptionError) and
derives the output mixer channels from the options (drivers/hf2_nodes.py ``mixer_layout``).

Versions: zhinst-core refuses, by default, a data server of another LabOne version ("ZIAPIVersionMismatchException
... The server is at LabOne version 'A' but the client is at LabOne version 'B'", zhinst-toolkit issues #291 and
#294; zhinst-core 26.x also says "Incompatible server version. Please ensure the client and server run on the
same LabOne version.", naming neither, and "The server/client version is too old ..."); ``allow_version_mismatch``
is passed to ``Session`` ([lockin] allow_version_mismatch) and a refusal is reported with both versions (the
server's read over a mismatch-allowing connection when the text names none) and the two ways out, the install as
``zhinst-core==X.Y.*`` (``zhinst_core_pin``: zhinst-core releases have four-part versions, 25.1.0.834).
``reconnect()`` opens a new session: a new data-server connection on hardware, a new Session over the same twin
otherwise.
"""

from __future__ import annotations

import contextlib
import logging
import re
from typing import Any

import numpy as np
import zhinst.core
from zhinst.toolkit import PollFlags, Session

from drivers.hf2_nodes import (
    AGC_PID,
    AUXIN_ADC_RATE_HZ,
    DRIVE_PLL,
    QUAD_PID,
    RATE_PID,
    CarrierPlan,
    LockInWiring,
    MixerLayout,
    carrier_plan,
    check_options,
    check_setup,
    forcer_amplitude,
    mixer_layout,
    parse_options,
    safe_nodes,
    setup_nodes,
)
from qmg_lab.instruments import (
    InstrumentError,
    LimitError,
    LockIn,
    LockInBlock,
    LockInSetup,
    StreamTiming,
    check_limit,
)

log = logging.getLogger(__name__)

PLL_LOCKED_BITS = (1 << 20, 1 << 21)  # status/flags/binary "b20": PLL 1 locked, "b21": PLL 2 locked (nodedoc)
N_PLLS = 2  # the HF2-PLL option's two PLLs (HF2 user manual, PLL tab)
DEFAULT_HF2_PORT = 8005
# zhinst-core's refusals of a data server of another LabOne version (strings of zhinst-core 26.7's _core.so; the
# first as zhinst-toolkit issues #291 and #294 quote it), each with the server's version where the text has one
_MISMATCH_TEXTS = (
    "version mismatch",  # "Version mismatch detected. The server is at LabOne version 'A' but the client is at ..."
    "versionmismatch",  # "ZIAPIVersionMismatchException ..."
    "incompatible server version",  # 26.x: "Incompatible server version. Please ensure the client and server run
    # on the same LabOne version." (no version named)
    "server version is too old",  # "The server version is too old. The server runs on version 'A' but ..."
    "client version is too old",  # "The client version is too old ... The client is on version B while the
    # server is on version A"
)
_SERVER_VERSION = (
    re.compile(r"server is at LabOne version '([^']*)'", re.IGNORECASE),
    re.compile(r"server runs on version '([^']*)'", re.IGNORECASE),
    re.compile(r"while the server is on version '?([0-9][0-9.]*[0-9])", re.IGNORECASE),
)
_RELEASE = re.compile(r"^\s*v?(\d+)\.(\d+)")


def zhinst_core_pin(labone_version: str) -> str | None:
    """The pip requirement of the zhinst-core that matches a LabOne version: ``zhinst-core==X.Y.*`` from its first
    two numbers (leading zeros dropped: LabOne says "26.07", PyPI has 26.7.2.5). zhinst-core's releases have three
    or four parts (24.10.65175, 25.1.0.834), so an exact ``==25.1.0`` matches none; ``==25.1.*`` matches every
    release of that LabOne version (PEP 440 prefix match). None for a text that is not a version."""
    found = _RELEASE.match(labone_version)
    if found is None:
        return None
    return f"zhinst-core=={int(found.group(1))}.{int(found.group(2))}.*"


def server_labone_version(host: str, port: int) -> str | None:
    """The data server's LabOne version (``/zi/about/version``), read over a connection that allows the mismatch
    and is closed at once; None when that fails too. For a refusal that does not name the server's version."""
    try:
        daq = zhinst.core.ziDAQServer(host, port, 1, allow_version_mismatch=True)
    except Exception:
        return None
    try:
        return str(daq.getString("/zi/about/version"))
    except Exception:
        return None
    finally:
        with contextlib.suppress(Exception):
            daq.disconnect()


def is_version_refusal(error: str) -> bool:
    """Whether zhinst-core's error text is one of its LabOne version refusals (``_MISMATCH_TEXTS``)."""
    text = error.lower()
    return any(t in text for t in _MISMATCH_TEXTS)


def version_mismatch_message(host: str, port: int, error: str, server_version: str | None = None) -> str | None:
    """The explanation of a data server's refusal for a LabOne version mismatch (None for any other error):
    both versions (the server's from zhinst-core's message, else `server_version` as read otherwise; the
    client's = the installed zhinst-core) and the two ways out: install the zhinst-core of the server's LabOne
    version (``zhinst_core_pin``), or allow the mismatch."""
    if not is_version_refusal(error):
        return None
    found = next((m.group(1) for rx in _SERVER_VERSION if (m := rx.search(error))), None) or server_version
    server = found or "(unknown: see the message below)"
    client = str(getattr(zhinst.core, "__version__", "unknown"))
    pin = zhinst_core_pin(found) if found else None
    install = f'pip install "{pin}"' if pin else 'pip install "zhinst-core==<X.Y of the server\'s LabOne>.*"'
    return (
        f"the HF2 data server at {host}:{port} runs LabOne {server}, but the installed zhinst-core is {client}: "
        f"zhinst-core refuses a data server of another LabOne version. Either install the matching client ({install}"
        "), or set allow_version_mismatch = true in [lockin] (the connection is then made; the two versions may not "
        f"agree on every node). zhinst-core said: {error}"
    )


def data_server_session(host: str, port: int, allow_version_mismatch: bool) -> Session:
    """One new connection to the HF2 data server at host:port (zhinst-toolkit 1.4's Session keyword
    ``allow_version_mismatch``, passed on to zhinst.core.ziDAQServer)."""
    return Session(host, port, hf2=True, allow_version_mismatch=allow_version_mismatch)


def open_hf2_session(host: str, port: int, allow_version_mismatch: bool = False) -> Session:
    """A zhinst-toolkit Session to the HF2 data server at host:port (API level 1); InstrumentError on refusal,
    with both versions and the ways out when the LabOne versions differ."""
    try:
        return data_server_session(host, port, allow_version_mismatch)
    except Exception as exc:  # zhinst.core raises RuntimeError (or its CoreError subclasses)
        error = str(exc)
        named = any(rx.search(error) for rx in _SERVER_VERSION)
        probed = server_labone_version(host, port) if is_version_refusal(error) and not named else None
        explained = version_mismatch_message(host, port, error, probed)
        raise InstrumentError(explained or f"cannot reach the HF2 data server at {host}:{port}: {exc}") from exc


class HF2LI(LockIn):
    """The HF2LI closing the PLL, AGC, rate and quadrature loops and streaming demods 0 (drive) and 1 (sense).

    ``HF2LI(session_or_host, device_id, wiring, output_safe_v=0.0, port=8005, allow_version_mismatch=False)``:
    pass a toolkit Session (already constructed; the device is connected here) or a host name (a Session is
    created, hf2=True). ``wiring`` is the validated qmg_lab.config.schema.LockInSection (`LockInWiring`), whose
    schema is the one place of the wiring's defaults and bounds (drivers/hf2_nodes.py).
    """

    def __init__(
        self,
        session: Session | str,
        device_id: str,
        wiring: LockInWiring,
        output_safe_v: float = 0.0,
        port: int = DEFAULT_HF2_PORT,
        allow_version_mismatch: bool = False,
    ) -> None:
        check_limit("output_safe_v", output_safe_v, -10.0, 10.0, "V")
        self.device_id = device_id.lower()
        self.wiring = wiring
        self.output_safe_v = float(output_safe_v)
        self.allow_version_mismatch = bool(allow_version_mismatch)
        if isinstance(session, Session):
            self._host, self._port = str(session.server_host), int(session.server_port)
            # a data-server connection of zhinst-core is hardware: reconnect() opens a new one; any other
            # connection object (the twin) is reused by a new Session
            daq = session.daq_server
            self._connection: Any = None if isinstance(daq, zhinst.core.ziDAQServer) else daq
            self._session = session
        else:
            self._host, self._port, self._connection = str(session), int(port), None
            self._session = self._open_session()
        self._setup: LockInSetup | None = None
        self._forcer_gain = 1.0
        self._streaming = False
        self._stream_wanted = False  # a reconnect that failed half-way still owes the stream (reconnect)
        self._t0_ticks: int | None = None  # the stream's time origin and last sample, device clock ticks
        self._carry: list[dict[str, np.ndarray] | None] = [None, None]  # unpaired stream tails held for next poll
        self._pair_tolerance_ticks = 0.0  # half a sample period (start_stream)
        self._measured_offset: int | None = None  # sense minus drive timestamp of the last pair, ticks
        self._last_ts: int | None = None
        self._attach()

    # ------------------------------------------------------------------ connection
    def _open_session(self) -> Session:
        if self._connection is None:
            return open_hf2_session(self._host, self._port, self.allow_version_mismatch)
        try:
            return Session(self._host, self._port, hf2=True, connection=self._connection)
        except Exception as exc:  # toolkit raises RuntimeError/ToolkitError from zhinst.core
            raise InstrumentError(f"HF2 data server at {self._host}:{self._port}: {exc}") from exc

    def _attach(self) -> None:
        try:
            self._device = self._session.connect_device(self.device_id)
            devtype = str(self._device.features.devtype())
            options = parse_options(self._device.features.options())
        except Exception as exc:
            raise InstrumentError(f"HF2LI {self.device_id}: cannot connect: {exc}") from exc
        if "HF2" not in devtype.upper():
            raise InstrumentError(f"{self.device_id} identifies as {devtype!r}, not an HF2 instrument")
        check_options(devtype, options)
        try:
            self.layout: MixerLayout = mixer_layout(options, self.wiring)
        except ValueError as exc:
            raise InstrumentError(f"HF2LI {self.device_id} (options {', '.join(options)}): {exc}") from exc
        self.devtype, self.options = devtype, options
        try:
            self._clockbase = float(self._device.clockbase())
            # the PLL option (required above) brings both PLLs; which oscillator and demodulator each one uses is
            # read-only on the HF2 (nodedoc_hf2.json): read, never assumed
            pll_oscs = tuple(int(self._device.plls[n].oscselect()) for n in range(N_PLLS))
            pll_demods = tuple(int(self._device.plls[n].demodselect()) for n in range(N_PLLS))
        except Exception as exc:
            raise InstrumentError(f"HF2LI {self.device_id}: reading the clockbase and PLL nodes failed: {exc}") from exc
        try:
            self.carriers: CarrierPlan = carrier_plan(self.layout, self.wiring, pll_oscs, pll_demods)
        except ValueError as exc:
            raise InstrumentError(f"HF2LI {self.device_id} (options {', '.join(options)}): {exc}") from exc
        self._demods = (self.carriers.drive_demod, self.carriers.sense_demod)
        dev = f"/{self.device_id}"  # the nodes every poll reads (plain getInt on the data server)
        self._locked_plls = (DRIVE_PLL, *self.carriers.tracking_plls)  # every PLL a carrier's coherence needs
        self._loss_node, self._binary_node = f"{dev}/status/flags/demodsampleloss", f"{dev}/status/flags/binary"
        self._locked_nodes = tuple(f"{dev}/plls/{n}/locked" for n in self._locked_plls)
        self._locked_mask = sum(PLL_LOCKED_BITS[n] for n in self._locked_plls)

    def _send(self, pairs: list[tuple[str, Any]]) -> None:
        """All pairs in one transaction: one set([...]) call to the data server."""
        try:
            with self._session.set_transaction():
                for path, value in pairs:
                    self._device[path](value)
        except Exception as exc:
            raise InstrumentError(f"HF2LI {self.device_id}: setting nodes failed: {exc}") from exc

    def _get(self, path: str) -> Any:
        try:
            return self._device[path]()
        except Exception as exc:
            raise InstrumentError(f"HF2LI {self.device_id}: reading {path} failed: {exc}") from exc

    # ------------------------------------------------------------------ Instrument
    def identify(self) -> str:
        d = self._device
        version = self._session.about.version()
        revision = self._session.about.revision()
        options = str(d.features.options()).replace("\n", ",").strip(",")
        return (
            f"Zurich Instruments {d.features.devtype()} {d.features.serial()} (options {options}); "
            f"HF2 data server {version} (revision {revision})"
        )

    def state(self) -> dict[str, Any]:
        g = self._get
        w, fm = self.wiring, self.layout.forcer
        pids = {}
        for name, n in (("agc", AGC_PID), ("rate", RATE_PID), ("quadrature", QUAD_PID)):
            pids[name] = {
                leaf: float(g(f"pids/{n}/{leaf}"))
                for leaf in ("p", "i", "setpoint", "center", "range", "error", "shift")
            }
            pids[name]["enable"] = int(g(f"pids/{n}/enable"))
        return {
            "device": self.device_id,
            "devtype": self.devtype,
            "options": list(self.options),
            "demod_timestamp_offset_ticks": self.demod_timestamp_offset(),  # None while the demods are off
            "mixer_channels": {"drive": self.layout.drive, "forcer": self.layout.forcer},
            "carriers": {
                "reference_oscillator": self.carriers.ref_osc,
                "drive_oscillator": self.carriers.drive_osc,
                "forcer_oscillator": self.carriers.forcer_osc,
                "tracking_plls": list(self.carriers.tracking_plls),
                "demods": {"drive": self.carriers.drive_demod, "sense": self.carriers.sense_demod},
            },
            "clockbase_hz": self._clockbase,
            "streaming": self._streaming,
            "pll": self._pll_state(DRIVE_PLL),
            "tracking_plls": {str(n): self._pll_state(n) for n in self.carriers.tracking_plls},
            "pids": pids,
            "demod_rate_hz": [float(g(f"demods/{d}/rate")) for d in self._demods],
            "auxout_v": {
                "rate": float(g(f"auxouts/{w.rate_auxout}/value")),
                "quadrature": float(g(f"auxouts/{w.quadrature_auxout}/value")),
            },
            "sigouts_on": {
                "drive": int(g(f"sigouts/{w.drive_sigout}/on")),
                "forcer": int(g(f"sigouts/{w.forcer_sigout}/on")),
            },
            "forcer_amplitude": float(g(f"sigouts/{w.forcer_sigout}/amplitudes/{fm}")),
            "forcer_gain": self._forcer_gain,
        }

    def _pll_state(self, n: int) -> dict[str, float | int]:
        g = self._get
        return {
            "enable": int(g(f"plls/{n}/enable")),
            "locked": int(g(f"plls/{n}/locked")),
            "oscselect": int(g(f"plls/{n}/oscselect")),
            "freqcenter_hz": float(g(f"plls/{n}/freqcenter")),
            "freqdelta_hz": float(g(f"plls/{n}/freqdelta")),
            "p": float(g(f"plls/{n}/p")),
            "i": float(g(f"plls/{n}/i")),
        }

    def demod_timestamp_offset(self) -> int | None:
        """Timestamp of a sense sample minus that of the drive sample it pairs with, clockbase ticks: from the last
        pair the stream delivered, else from ``demods/n/sample`` read once each (None when either demodulator has
        no sample, e.g. both disabled, or they run at different rates). The two reads need not see the same
        sample, so that offset is folded into [-T/2, T/2), T = clockbase / rate: the pairing's own window."""
        if self._measured_offset is not None:
            return self._measured_offset
        d, s = self._demods
        try:
            rate = float(self._get(f"demods/{s}/rate"))
            if rate <= 0 or rate != float(self._get(f"demods/{d}/rate")):
                return None
            server = self._session.daq_server
            ts = [
                np.atleast_1d(np.asarray(server.getSample(f"/{self.device_id}/demods/{k}/sample")["timestamp"]))
                for k in (d, s)
            ]
        except Exception as exc:
            log.info("HF2LI %s: demod timestamps not readable: %s", self.device_id, exc)
            return None
        if any(len(t) == 0 for t in ts):
            return None
        period = self._clockbase / rate
        diff = float(int(ts[1][-1]) - int(ts[0][-1]))
        return int(round((diff + period / 2) % period - period / 2))

    def safe_state(self) -> None:
        """PIDs off, loop AuxOuts at output_safe_v, forcer carrier 0, signal outputs off (idempotent).

        One transaction first; if it fails, every node is set on its own, so that one node the instrument
        refuses (or does not list) never keeps the others from being made safe. Each failure is logged and the
        InstrumentError raised at the end names every node that failed."""
        failed: list[str] = []
        if self._streaming:
            try:
                self.stop_stream()
            except InstrumentError as exc:
                failed.append(f"stop stream ({exc})")
        pairs = safe_nodes(self.wiring, self.output_safe_v, self.layout)
        try:
            self._send(pairs)
        except InstrumentError as exc:
            log.warning("HF2LI %s: safe state in one transaction failed (%s): node by node", self.device_id, exc)
            for path, value in pairs:
                try:
                    self._device[path](value)
                except Exception as node_exc:
                    log.error("HF2LI %s: safe state: %s = %r failed: %s", self.device_id, path, value, node_exc)
                    failed.append(f"{path} = {value!r} ({node_exc})")
        if failed:
            raise InstrumentError(
                f"HF2LI {self.device_id}: safe state incomplete, the other nodes were set; failed: " + "; ".join(failed)
            )

    def close(self) -> None:
        try:
            if self._streaming:
                self.stop_stream()
        finally:
            self._streaming = self._stream_wanted = False

    def reconnect(self) -> None:
        """A new session to the same server (a new data-server connection on hardware, a new Session over the
        same connection object for the twin), re-identify (options included), re-apply the last configuration
        and forcer gain, restart the stream if it ran: also when the stream ran before an earlier reconnect that
        failed (the link still down), which left `_streaming` False. On hardware the old connection is closed
        first (ziDAQServer.disconnect, best effort: it is usually the one that failed)."""
        was_streaming, gain = self._streaming or self._stream_wanted, self._forcer_gain
        log.info("HF2LI %s: reconnecting (streaming %s)", self.device_id, was_streaming)
        self._streaming, self._stream_wanted = False, was_streaming
        if self._connection is None:
            with contextlib.suppress(Exception):
                self._session.daq_server.disconnect()
        self._session = self._open_session()
        self._attach()
        if self._setup is not None:
            self.configure(self._setup)
            self.set_forcer_gain(gain)
        if was_streaming:
            # the device's clock ran on while the host was away: the same stream time origin and last sample, so
            # the samples it missed are a timestamp gap counted as lost (a device that restarted its clock goes
            # back in time instead, which the campaign takes as a new stream)
            t0_ticks, last_ts = self._t0_ticks, self._last_ts
            self.start_stream()
            self._t0_ticks, self._last_ts = t0_ticks, last_ts

    # ------------------------------------------------------------------ LockIn
    def configure(self, setup: LockInSetup) -> None:
        """Oscillator, demods 0/1, PLL 0, PIDs 0-2, outputs and AuxOuts in one transaction (limits first)."""
        check_setup(setup, self.wiring)
        self._send(setup_nodes(setup, self.wiring, self.carriers, self.layout))
        self._setup = setup
        self._forcer_gain = float(setup.forcer_gain)

    def start_stream(self) -> None:
        rates = [float(self._get(f"demods/{d}/rate")) for d in self._demods]
        if rates[0] != rates[1]:
            raise InstrumentError(f"demods {self._demods} stream at different rates {rates} Sa/s: configure first")
        self._rate_hz = rates[1]
        self._ticks_per_sample = self._clockbase / self._rate_hz
        self._pair_tolerance_ticks = self._ticks_per_sample / 2.0
        self._carry = [None, None]
        try:
            self._session.sync()
            for d in self._demods:
                self._device.demods[d].sample.subscribe()
        except Exception as exc:
            raise InstrumentError(f"HF2LI {self.device_id}: subscribe failed: {exc}") from exc
        self._t0_ticks = None
        self._last_ts = None
        self._streaming, self._stream_wanted = True, False

    def stop_stream(self) -> None:
        try:
            for d in self._demods:
                self._device.demods[d].sample.unsubscribe()
        except Exception as exc:
            raise InstrumentError(f"HF2LI {self.device_id}: unsubscribe failed: {exc}") from exc
        finally:
            self._streaming = self._stream_wanted = False

    def poll(self, duration_s: float) -> LockInBlock:
        """The samples since the last poll, drive and sense demodulators paired (module docstring: pairing), the
        samples lost, and whether every PLL the carriers need reports locked (``pll_locked``)."""
        if not self._streaming:
            raise InstrumentError("HF2LI.poll: the stream is not started (call start_stream)")
        check_limit("poll duration_s", duration_s, 1e-3, 60.0, "s")
        try:
            raw = self._session.poll(duration_s, timeout=0.5, flags=PollFlags.DETECT)
            server = self._session.daq_server  # plain getInt: the toolkit node layer costs ~0.1 ms per read
            flag = server.getInt(self._loss_node)
            locked = all(server.getInt(node) for node in self._locked_nodes)
            binary = server.getInt(self._binary_node)
        except Exception as exc:
            raise InstrumentError(f"HF2LI {self.device_id}: poll failed: {exc}") from exc
        drive = self._with_carry(self._samples(raw, self._demods[0]), 0)
        sense = self._with_carry(self._samples(raw, self._demods[1]), 1)
        d_ts, s_ts = _as_int64(drive["timestamp"]), _as_int64(sense["timestamp"])
        i_d, i_s = pair_nearest(d_ts, s_ts, self._pair_tolerance_ticks)
        self._keep_unpaired_tail(drive, sense, d_ts, s_ts, i_d, i_s)
        ticks = s_ts[i_s]
        if len(ticks):
            self._measured_offset = int(ticks[-1]) - int(d_ts[i_d][-1])
            lost = self._count_lost(ticks)
        else:  # nothing paired: every sample it did not hold back is lost, and the stream's clock moves past them
            lost = self._lost_unpaired(d_ts, s_ts)
        if flag and lost == 0:
            lost = 1
        if len(ticks):
            if self._t0_ticks is None:
                self._t0_ticks = int(ticks[0])
            self._last_ts = int(ticks[-1])
        t0 = self._t0_ticks if self._t0_ticks is not None else 0
        w = self.wiring
        rate_key, dither_key = f"auxin{w.rate_auxin}", f"auxin{w.dither_auxin}"
        return LockInBlock(
            time=(ticks - t0) / self._clockbase,
            x_sense=np.asarray(sense["x"])[i_s],
            y_sense=np.asarray(sense["y"])[i_s],
            rate_output=np.asarray(sense[rate_key])[i_s],
            drive_amplitude=np.hypot(np.asarray(drive["x"])[i_d], np.asarray(drive["y"])[i_d]),
            drive_frequency=np.asarray(drive["frequency"])[i_d],
            dither=np.asarray(sense[dither_key])[i_s],
            table_encoder=np.asarray(sense["dio"], dtype=np.float64)[i_s],  # the DIO word (the table encoder)
            pll_locked=locked and binary & self._locked_mask == self._locked_mask,
            samples_lost=int(lost),
        )

    def _with_carry(self, fresh: dict[str, np.ndarray], k: int) -> dict[str, np.ndarray]:
        """Stream k's samples of this poll behind those the previous poll held back (``_keep_unpaired_tail``)."""
        held = self._carry[k]
        self._carry[k] = None
        if held is None:
            return fresh
        return {key: np.concatenate((held[key], fresh[key])) for key in fresh if key in held}

    def _keep_unpaired_tail(
        self,
        drive: dict[str, np.ndarray],
        sense: dict[str, np.ndarray],
        d_ts: np.ndarray,
        s_ts: np.ndarray,
        i_d: np.ndarray | slice,
        i_s: np.ndarray | slice,
    ) -> None:
        """Hold back the unpaired samples at the end of a stream whose partner may still come with the next poll
        (timestamp later than the other stream's last one minus the tolerance); only while both streams deliver,
        so that a stream that stopped never makes the other one's samples wait. Every other unpaired sample is a
        gap in the paired timestamps, counted as lost."""
        if isinstance(i_d, slice) or isinstance(i_s, slice) or not len(d_ts) or not len(s_ts):
            return
        tol = self._pair_tolerance_ticks
        for k, (data, ts, paired, other) in enumerate(((drive, d_ts, i_d, s_ts), (sense, s_ts, i_s, d_ts))):
            after = int(paired[-1]) + 1 if len(paired) else 0
            tail = np.arange(after, len(ts))
            tail = tail[ts[tail] > other[-1] - tol]
            if len(tail):
                self._carry[k] = {key: np.asarray(v)[tail] for key, v in data.items()}

    def _lost_unpaired(self, d_ts: np.ndarray, s_ts: np.ndarray) -> int:
        """Samples lost in a block where no sample paired: the gap count up to the last sample either stream
        delivered and did not hold back for the next poll (its timestamp then stands for the block's end), so that
        the next block's first gap does not count them again. 0 for a block that delivered nothing."""
        held = [0 if c is None else len(c["timestamp"]) for c in self._carry]
        ends = [int(ts[len(ts) - h - 1]) for ts, h in ((d_ts, held[0]), (s_ts, held[1])) if len(ts) > h]
        if not ends:
            return 0
        end = max(ends)
        if self._last_ts is None:  # the stream's first block: count from its first delivered sample
            first = min(int(ts[0]) for ts in (d_ts, s_ts) if len(ts))
            self._last_ts = first - int(round(self._ticks_per_sample))
        lost = max(int(np.rint((end - self._last_ts) / self._ticks_per_sample)), 0)
        self._last_ts = end
        return lost

    def _samples(self, raw: Any, demod: int) -> dict[str, np.ndarray]:
        key = f"/{self.device_id}/demods/{demod}/sample"
        try:
            data = raw[key]
        except KeyError:
            return {
                k: np.zeros(0, dtype=np.uint64 if k == "timestamp" else float)
                for k in ("timestamp", "x", "y", "frequency", "dio", "auxin0", "auxin1")
            }
        return {k: np.asarray(v) for k, v in data.items() if k != "time"}

    def _count_lost(self, ticks: np.ndarray) -> int:
        """Samples lost in the gaps of the block's timestamps `ticks` (int64) and in the gap from the previous
        block's last sample: sum over gaps of max(rint(gap / ticks_per_sample) - 1, 0) (module docstring).

        rint is monotonic, so no gap spans two samples exactly when the largest one does not: that is checked
        first (the usual block), and the per-gap sum is formed only for a block that lost samples."""
        n = len(ticks)
        if n == 0 or (n == 1 and self._last_ts is None):
            return 0
        inner = ticks[1:] - ticks[:-1]  # np.diff's subtraction without its argument handling
        first = [] if self._last_ts is None else [int(ticks[0]) - self._last_ts]
        widest = max(first + ([int(inner.max())] if n > 1 else []))
        if np.rint(widest / self._ticks_per_sample) <= 1:
            return 0
        gaps = np.concatenate((first, inner)) if first else inner
        steps = np.rint(gaps / self._ticks_per_sample).astype(np.int64)
        return int(np.sum(np.maximum(steps - 1, 0)))

    def set_forcer_gain(self, gain: float) -> None:
        """Forcer carrier amplitude = nominal * gain; LimitError for gain outside [0.5, 2] or amplitude > 1."""
        amplitude = forcer_amplitude(self.wiring, gain)
        fm = self.layout.forcer
        self._send([(f"sigouts/{self.wiring.forcer_sigout}/amplitudes/{fm}", amplitude)])
        self._forcer_gain = float(gain)

    def stream_timing(self) -> StreamTiming:
        """Read back what the HF2 applies: the sense demod's rate (the device rounds a requested rate), filter
        order and time constant, and the AuxIn averaging (window = 2^averaging / AUXIN_ADC_RATE_HZ)."""
        d = self._demods[1]
        avg = int(self._get("auxins/0/averaging"))
        return StreamTiming(
            rate_hz=float(self._get(f"demods/{d}/rate")),
            filter_order=int(self._get(f"demods/{d}/order")),
            filter_tc_s=float(self._get(f"demods/{d}/timeconstant")),
            auxin_window_s=float(2 ** max(0, min(15, avg))) / AUXIN_ADC_RATE_HZ,
        )

    def pll_locked(self) -> bool:
        """Every PLL the carriers need reports locked: ``plls/n/locked`` ("Lock indicator for the PLL", 1 = "PLL
        locked", nodedoc_hf2.json) and its bit of ``status/flags/binary`` (b20 PLL 1, b21 PLL 2 locked)."""
        locked = all(int(self._get(f"plls/{n}/locked")) for n in self._locked_plls)
        binary = int(self._get("status/flags/binary"))
        return locked and binary & self._locked_mask == self._locked_mask


__all__ = ["HF2LI", "LimitError"]


def _as_int64(timestamps: np.ndarray) -> np.ndarray:
    """Timestamps (clockbase ticks, uint64 from the data server) as int64: a view of the same 8-byte integers
    when they are 64-bit (the values astype(int64) gives: ticks stay below 2**63 for 1390 years at 210 MHz),
    else a converted copy."""
    if timestamps.dtype in (np.uint64, np.int64):
        return timestamps.view(np.int64)
    return timestamps.astype(np.int64)


def pair_nearest(drive_ts: np.ndarray, sense_ts: np.ndarray, tolerance_ticks: float) -> tuple[Any, Any]:
    """Indices (into the drive and the sense stream) of the pairs: each sense sample with the drive sample nearest
    in time, kept when |t_sense - t_drive| < tolerance_ticks (sorted int64 timestamps, clockbase ticks).

    With a tolerance of half a sample period T, a drive sample is the nearest of at most one sense sample (two
    sense samples T apart cannot both be closer than T/2 to it), so the pairs are one to one. Usually both streams
    carry the same samples, perhaps with a constant offset: then the samples pair in order and no search is
    needed (slices); otherwise a binary search for each sense sample."""
    n_d, n_s = len(drive_ts), len(sense_ts)
    if n_d == n_s and (n_d == 0 or np.abs(sense_ts - drive_ts).max() < tolerance_ticks):
        return slice(None), slice(None)
    if n_d == 0 or n_s == 0:
        return np.zeros(0, dtype=np.intp), np.zeros(0, dtype=np.intp)
    hi = np.minimum(np.searchsorted(drive_ts, sense_ts), n_d - 1)
    lo = np.maximum(hi - 1, 0)
    d_hi, d_lo = np.abs(drive_ts[hi] - sense_ts), np.abs(drive_ts[lo] - sense_ts)
    nearest = np.where(d_lo <= d_hi, lo, hi)
    ok = np.minimum(d_lo, d_hi) < tolerance_ticks
    return nearest[ok], np.flatnonzero(ok)
