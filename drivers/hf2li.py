"""Zurich Instruments HF2LI (PLL + PID options) over zhinst-toolkit: the gyroscope's loops and its data stream.

Transport: a ``zhinst.toolkit.Session`` to an HF2 data server (API level 1, port 8005): hardware with
``Session(host, port, hf2=True)``, the twin with ``Session(host, hf2=True, connection=twin)``. The same code runs
on both. Node settings and channel assignment: drivers/hf2_nodes.py and docs/wiring.md.

Stream protocol (docs/wiring.md): ``session.sync()``, subscribe ``demods/0/sample`` and ``demods/1/sample``,
then ``session.poll(duration)`` returns every sample since the last poll. The two demods' samples are merged on
equal timestamps; t = (timestamp - t0_ticks) / clockbase with t0_ticks the first timestamp of the stream.
Lost samples = sum over timestamp gaps of (gap / ticks_per_sample - 1), ticks_per_sample = clockbase / rate
(read back), including the gap between the last sample of the previous block and the first of this one; the
device flag ``status/flags/demodsampleloss`` counts as at least one lost sample when the gaps show none.

Instrument as it is: at connect the driver reads ``features/devtype`` and ``features/options`` (kept in state(),
hence in the run file's snapshot), refuses an instrument without the PLL or PID option (MissingOptionError) and
derives the output mixer channels from the options (drivers/hf2_nodes.py ``mixer_layout``).

Versions: zhinst-core refuses, by default, a data server of another LabOne version ("ZIAPIVersionMismatchException
... The server is at LabOne version 'A' but the client is at LabOne version 'B'", zhinst-toolkit issues #291 and
#294); ``allow_version_mismatch`` is passed to ``Session`` ([lockin] allow_version_mismatch) and a refusal is
reported with both versions and the two ways out (``version_mismatch_message``). ``reconnect()`` opens a new
session: a new data-server connection on hardware, a new Session over the same twin otherwise.
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
    DRIVE_DEMOD,
    QUAD_PID,
    RATE_PID,
    SENSE_DEMOD,
    LockInWiring,
    MixerLayout,
    check_options,
    check_setup,
    check_wiring,
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

PLL1_LOCKED_BIT = 1 << 20
DEFAULT_HF2_PORT = 8005
_SERVER_VERSION = re.compile(r"server is at LabOne version '([^']*)'", re.IGNORECASE)


def version_mismatch_message(host: str, port: int, error: str) -> str | None:
    """The explanation of a data server's refusal for a LabOne version mismatch (None for any other error):
    both versions (the server's from zhinst-core's message, the client's = the installed zhinst-core) and the two
    ways out: install the zhinst-core of the server's LabOne version, or allow the mismatch."""
    if "version mismatch" not in error.lower() and "versionmismatch" not in error.lower():
        return None
    found = _SERVER_VERSION.search(error)
    server = found.group(1) if found else "(see the message below)"
    client = str(getattr(zhinst.core, "__version__", "unknown"))
    wanted = server if found else "<LabOne version of the data server>"
    return (
        f"the HF2 data server at {host}:{port} runs LabOne {server}, but the installed zhinst-core is {client}: "
        "zhinst-core refuses a data server of another LabOne version. Either install the matching client "
        f'(pip install "zhinst-core=={wanted}"), or set allow_version_mismatch = true in [lockin] '
        f"(the connection is then made; the two versions may not agree on every node). zhinst-core said: {error}"
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
        explained = version_mismatch_message(host, port, str(exc))
        raise InstrumentError(explained or f"cannot reach the HF2 data server at {host}:{port}: {exc}") from exc


class HF2LI(LockIn):
    """The HF2LI closing the PLL, AGC, rate and quadrature loops and streaming demods 0 (drive) and 1 (sense).

    ``HF2LI(session_or_host, device_id, wiring, output_safe_v=0.0, port=8005, allow_version_mismatch=False)``:
    pass a toolkit Session (already constructed; the device is connected here) or a host name (a Session is
    created, hf2=True). ``wiring`` is qmg_lab.config.schema.LockInSection or any object with its cabling fields
    (and optionally drive_mixer_channel / forcer_mixer_channel overrides).
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
        check_wiring(wiring)
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
        self._clockbase = float(self._device.clockbase())
        self._pll_osc = int(self._device.plls[0].oscselect())
        dev = f"/{self.device_id}"  # the nodes every poll reads (plain getInt on the data server)
        self._poll_nodes = (f"{dev}/status/flags/demodsampleloss", f"{dev}/plls/0/locked", f"{dev}/status/flags/binary")

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
            "mixer_channels": {"drive": self.layout.drive, "forcer": self.layout.forcer},
            "clockbase_hz": self._clockbase,
            "streaming": self._streaming,
            "pll": {
                "enable": int(g("plls/0/enable")),
                "locked": int(g("plls/0/locked")),
                "freqcenter_hz": float(g("plls/0/freqcenter")),
                "freqdelta_hz": float(g("plls/0/freqdelta")),
                "p": float(g("plls/0/p")),
                "i": float(g("plls/0/i")),
            },
            "pids": pids,
            "demod_rate_hz": [float(g(f"demods/{d}/rate")) for d in (DRIVE_DEMOD, SENSE_DEMOD)],
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
        self._send(setup_nodes(setup, self.wiring, self._pll_osc, self.layout))
        self._setup = setup
        self._forcer_gain = float(setup.forcer_gain)

    def start_stream(self) -> None:
        rates = [float(self._get(f"demods/{d}/rate")) for d in (DRIVE_DEMOD, SENSE_DEMOD)]
        if rates[0] != rates[1]:
            raise InstrumentError(f"demods 0 and 1 stream at different rates {rates} Sa/s: configure first")
        self._rate_hz = rates[1]
        self._ticks_per_sample = self._clockbase / self._rate_hz
        try:
            self._session.sync()
            self._device.demods[DRIVE_DEMOD].sample.subscribe()
            self._device.demods[SENSE_DEMOD].sample.subscribe()
        except Exception as exc:
            raise InstrumentError(f"HF2LI {self.device_id}: subscribe failed: {exc}") from exc
        self._t0_ticks = None
        self._last_ts = None
        self._streaming, self._stream_wanted = True, False

    def stop_stream(self) -> None:
        try:
            self._device.demods[DRIVE_DEMOD].sample.unsubscribe()
            self._device.demods[SENSE_DEMOD].sample.unsubscribe()
        except Exception as exc:
            raise InstrumentError(f"HF2LI {self.device_id}: unsubscribe failed: {exc}") from exc
        finally:
            self._streaming = self._stream_wanted = False

    def poll(self, duration_s: float) -> LockInBlock:
        if not self._streaming:
            raise InstrumentError("HF2LI.poll: the stream is not started (call start_stream)")
        check_limit("poll duration_s", duration_s, 1e-3, 60.0, "s")
        try:
            raw = self._session.poll(duration_s, timeout=0.5, flags=PollFlags.DETECT)
            server = self._session.daq_server  # plain getInt: the toolkit node layer costs ~0.1 ms per read
            loss_node, locked_node, binary_node = self._poll_nodes
            flag = server.getInt(loss_node)
            locked = server.getInt(locked_node)
            binary = server.getInt(binary_node)
        except Exception as exc:
            raise InstrumentError(f"HF2LI {self.device_id}: poll failed: {exc}") from exc
        drive = self._samples(raw, DRIVE_DEMOD)
        sense = self._samples(raw, SENSE_DEMOD)
        ts, i_d, i_s = _common_samples(drive["timestamp"], sense["timestamp"])
        ticks = _as_int64(ts)
        lost = self._count_lost(ticks)
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
            pll_locked=bool(locked) and bool(binary & PLL1_LOCKED_BIT),
            samples_lost=int(lost),
        )

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
        d = SENSE_DEMOD
        avg = int(self._get("auxins/0/averaging"))
        return StreamTiming(
            rate_hz=float(self._get(f"demods/{d}/rate")),
            filter_order=int(self._get(f"demods/{d}/order")),
            filter_tc_s=float(self._get(f"demods/{d}/timeconstant")),
            auxin_window_s=float(2 ** max(0, min(15, avg))) / AUXIN_ADC_RATE_HZ,
        )

    def pll_locked(self) -> bool:
        locked = int(self._get("plls/0/locked"))
        binary = int(self._get("status/flags/binary"))
        return bool(locked) and bool(binary & PLL1_LOCKED_BIT)


__all__ = ["HF2LI", "LimitError"]


def _as_int64(timestamps: np.ndarray) -> np.ndarray:
    """Timestamps (clockbase ticks, uint64 from the data server) as int64: a view of the same 8-byte integers
    when they are 64-bit (the values astype(int64) gives: ticks stay below 2**63 for 1390 years at 210 MHz),
    else a converted copy."""
    if timestamps.dtype in (np.uint64, np.int64):
        return timestamps.view(np.int64)
    return timestamps.astype(np.int64)


def _common_samples(
    drive_ts: np.ndarray, sense_ts: np.ndarray
) -> tuple[np.ndarray, np.ndarray | slice, np.ndarray | slice]:
    """The timestamps both demodulators delivered, and where they sit in each (sorted, unique timestamps).

    Usually both streams carry the same samples: then every sample is common and no search is needed (the
    intersection of two sorted arrays costs a sort, ~1 ms per 10 s block at 1800 Sa/s)."""
    if drive_ts is sense_ts or (drive_ts.shape == sense_ts.shape and np.array_equal(drive_ts, sense_ts)):
        return drive_ts, slice(None), slice(None)
    ts, i_d, i_s = np.intersect1d(drive_ts, sense_ts, assume_unique=True, return_indices=True)
    return ts, i_d, i_s
