"""A duck-typed HF2 data-server connection: the HF2LI twin at zhinst-toolkit's connection boundary.

``zhinst.toolkit.Session(host, hf2=True, connection=HF2DataServerTwin(...))`` runs toolkit's unchanged code path
against it: ``getString("/zi/about/dataserver")`` answers "HF2DataServer", ``listNodes`` lists the device's leaves
(toolkit then takes their documentation from its bundled nodedoc_hf2.json, like on a real HF2), ``listNodesJSON``
raises (API level 1 has none), ``get``/``getInt``/``getDouble``/``getString``/``set`` (single and list form, the
latter used by ``set_transaction``), ``sync``, ``subscribe``/``unsubscribe`` and ``poll`` behave like
``zhinst.core.ziDAQServer`` at API level 1.

Physics coupling (protocol of one ``poll(rec_s, ...)``):
1. n = round(rec_s * rate) steps of dt = 1/rate, rate = ``demods/<sense>/rate``. A requested rate is rounded
   at set time to a rate the instrument offers (``rate_set``): "hf2", the HF2's binary ladder
   HF2_RATE_BASE_HZ / 2^k (1800, 3600, 7200, ... and 900, 450, 225 Sa/s; the power-on 1800 Sa/s is one of
   them), each then an integer number of clockbase ticks so that timestamps are exact; or "ticks", any
   clockbase / integer rate (a test stand for rates no HF2 offers). Nothing subscribed -> no data and the world
   stands still.
   *Assumed*: the HF2 documentation says a requested rate "may be approximated to the nearest value supported"
   without listing them; the binary ladder through the power-on 1800 Sa/s is what the twin offers, and the
   driver always reads the applied rate back, so the application never depends on this list.
2. ``world.advance(n, dt)`` gives the per-step inputs; ``identify_loops`` reads the node values into
   LoopSettings (sims/hf2_loops.py); ``GyroSim.run`` integrates the block (re-created when dt changes).
3. Every subscribed and enabled demod gets n samples: timestamp = clockbase ticks of the world time at the end
   of each step (plus ``timestamp_offset_ticks`` for every demod but demods/0, the [sim]
   hf2_timestamp_offset_ticks key: no source says two HF2 demodulators stamp their samples identically, so the
   twin can play an offset); x, y from the physics for drive/sense demods (rotated by
   exp(-i(phi_osc + phaseshift - phi_ref)) if the demod's oscillator is not the reference); frequency and phase
   (rad) of its oscillator;
   auxin[rate_auxin] = the rate AuxOut looped to the AuxIn, auxin[dither_auxin] = the DS345 output, each as the
   AuxIn reports it: the mean of the input over the AuxIn averaging window W = 2^auxins/0/averaging /
   AUXIN_ADC_RATE_HZ that ends at the sample's timestamp (the HF2 averages 1..32768 AuxIn ADC samples and aligns
   the result with the demodulator sample by timestamp). The AuxOut voltage is piecewise linear between sample
   instants (sims/gyro_kernel.py), so its window mean is exact; the dither's is the exact integral of the
   square wave (sims/world.py), edges between samples included. *Assumed*: AUXIN_ADC_RATE_HZ (not found in the
   HF2 documentation); with the default averaging 0 the window is one ADC sample and its value hardly matters.
   Each reading then gets the AuxIn's own white noise (GyroParams.auxin_noise_v_rms) and is rounded to its ADC
   step (auxin_bits over +-auxin_range_v) and clipped to the range (docs/noise-budget.md).
   dio = the DIO input word at the sample's timestamp: the rate table's encoder A/B (``table_encoder``,
   sims/table_twin.TableEncoder) at the table angle of that instant, 0 with nothing wired (the node doc's
   demod sample carries the DIO state in its ``dio`` field).
4. Read-only nodes reflect the end of the block: plls/0/freqdelta, locked, error; plls/1/locked, freqdelta of
   a PLL that tracks the drive for another oscillator (sims/hf2_loops.py: the forcer carrier without MF), bit 21
   of status/flags/binary (PLL 2 locked); pids/n/error (= setpoint -
   input), shift (= output - center); auxouts/n/value; auxins/0/values/k; status/flags/binary bit 20 (PLL 1
   locked); status/flags/demodsampleloss; status/time. The truth of the block goes to ``world.record_truth``.

Fault hooks: ``drop_samples(n, demod=None)`` removes n samples from the middle of the next poll, from every demod
or from one (timestamp gap + sample-loss flag); ``force_pll_unlock(duration_s)`` opens the PLL (frequency held at
its centre) and reports unlock for that much world time from now; ``run_unobserved(seconds)`` runs the instrument
on while its host link is down.
"""

from __future__ import annotations

import fnmatch
import math
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Any

import numpy as np

from sims import hf2_kernel as hk
from sims.hf2_loops import HF2Wiring, LoopPlan, identify_loops
from sims.hf2_nodetree import HF2NodeTree, NodeError
from sims.noise import NormalStream
from sims.table_twin import TableEncoder
from sims.world import BlockInputs, TruthRecord, World

if TYPE_CHECKING:
    from sims.gyro import GyroBlock, GyroParams, LoopSettings

__all__ = ["HF2DataServerTwin", "HF2Wiring", "NodeError"]

DEMOD_FIELDS = ("timestamp", "x", "y", "frequency", "phase", "dio", "trigger", "auxin0", "auxin1")
PLL_LOCKED_BITS = (1 << 20, 1 << 21)
HF2_RATE_BASE_HZ = 921.6e3  # the binary ladder of demodulator rates: 921.6 kSa/s / 2^k (assumed, see above)
AUXIN_ADC_RATE_HZ = 400e3  # AuxIn ADC sample rate (assumed, see above)
RATE_SETS = ("hf2", "ticks")
SERVER_VERSION = "26.07"
SERVER_REVISION = 26070250


def _zi_nodes(port: int, clockbase_hz: float) -> dict[str, Any]:
    return {
        "/zi/about/version": SERVER_VERSION,
        "/zi/about/revision": SERVER_REVISION,
        "/zi/about/commit": "twin",
        "/zi/about/fwrevision": SERVER_REVISION,
        "/zi/about/copyright": "qmg-lab HF2 twin",
        "/zi/about/dataserver": "HF2DataServer",
        "/zi/config/port": port,
        "/zi/config/open": 0,
        "/zi/mds/groups/0/devices": "",
        "/zi/mds/groups/0/status": 0,
        "/zi/mds/groups/0/locked": 0,
        "/zi/debug/level": 3,
        "/zi/debug/logpath": "",
        "/zi/debug/log": "",
        "/zi/clockbase": int(round(clockbase_hz)),
    }


@dataclass(frozen=True)
class _DemodSpec:
    """One subscribed, enabled demodulator as the settings configure it."""

    path: str
    sigin: int
    osc: int
    harmonic: int
    shift_rad: float  # demods/n/phaseshift, rad


@dataclass(frozen=True)
class _ReflectPaths:
    """The absolute paths of the read-only nodes a poll writes (`_reflect`), built once per layout."""

    ref_osc_freq: str
    pll_locked: str
    pll_freqdelta: str
    pll_freqcenter: str
    pll_error: str
    flags_binary: str
    flags_sampleloss: str
    status_time: str
    pid_error: dict[str, str]  # by loop name ("agc", "rate", "quadrature"), for the PIDs the loop plan uses
    pid_shift: dict[str, str]
    rate_auxout: str
    quadrature_auxout: str
    auxin_values: tuple[str, str]


@dataclass(frozen=True)
class _PollLayout:
    """The settings a poll needs, valid for one (settings version, subscribed demods) `key`."""

    key: tuple[int, tuple[str, ...]]
    plan: LoopPlan
    ticks_per_sample: int  # clockbase ticks per sample of the sense demod's rate
    dt: float  # s per sample = ticks_per_sample / clockbase
    demods: tuple[_DemodSpec, ...]
    used_oscs: frozenset[int]  # the reference oscillator and those of every subscribed demod
    fixed_osc_hz: dict[int, float]  # the set frequency of every oscillator but the reference
    auxin_window_s: float
    pid_settings: dict[str, tuple[float, float]]  # (setpoint, center) of every PID the loop plan uses, by loop
    paths: _ReflectPaths


def _slice_inputs(inp: BlockInputs, sl: slice) -> BlockInputs:
    return BlockInputs(
        t=inp.t[sl],
        table_rate_dps=inp.table_rate_dps[sl],
        table_angle_deg=inp.table_angle_deg[sl],
        chamber_c=inp.chamber_c[sl],
        gyro_c=inp.gyro_c[sl],
        dither_v=inp.dither_v[sl],
    )


class HF2DataServerTwin:
    """HF2 data server + one HF2LI whose loops drive ``sims.gyro.GyroSim``. ``options``: its installed options
    (``features/options``); the node tree lists what such an instrument lists (sims/hf2_nodetree.py, with the
    sources of each count). ``rate_set``: the demodulator rates it offers (RATE_SETS). Both are the
    configuration's [sim] hf2_options and hf2_rate_set, whose defaults live in the schema only (the station passes
    them)."""

    api_level = 1

    def __init__(
        self,
        world: World,
        gyro_params: GyroParams,
        seed: int,
        wiring: HF2Wiring,
        *,
        rate_set: str,
        options: tuple[str, ...],
        device_id: str = "dev1234",
        clockbase_hz: float = 210e6,
        host: str = "localhost",
        port: int = 8005,
        timestamp_offset_ticks: int = 0,
    ) -> None:
        if clockbase_hz <= 0:
            raise ValueError(f"clockbase_hz = {clockbase_hz!r} must be positive")
        if rate_set not in RATE_SETS:
            raise ValueError(f"rate_set = {rate_set!r} must be one of {RATE_SETS}")
        self.rate_set = rate_set
        self.timestamp_offset_ticks = int(timestamp_offset_ticks)  # added to every demod's but demods/0's ([sim])
        self._auxout_prev: float | None = None  # the rate AuxOut voltage at the previous sample instant
        self.world, self.gyro_params, self.seed, self.wiring = world, gyro_params, int(seed), wiring
        # the AuxIn readings' own noise: a stream of its own, independent of the gyro's (spawn key 7)
        self._auxin_noise = NormalStream(
            np.random.Generator(np.random.PCG64(np.random.SeedSequence(int(seed), spawn_key=(7,))))
        )
        self._no_auxin_noise = np.empty((2, 0))  # what the readings get without AuxIn noise (not read)
        self.host, self.port = host, port
        self.clockbase_hz = float(clockbase_hz)
        self.nodes = HF2NodeTree(device_id, clockbase_hz, tuple(options))
        self.device_id = self.nodes.device_id
        self._zi = _zi_nodes(port, clockbase_hz)
        self.connected = False
        self.subscribed: set[str] = set()
        self._read_paths: dict[str, str] = {}  # device paths as a client spelled them -> the readable value node
        self._gyro: Any = None
        self._gyro_dt: float | None = None
        self._gyro_count = 0
        self._ticks: int | None = None
        self._osc_phase = [
            0.0
        ] * self.nodes.n_oscillators  # each oscillator's phase at the end of the last block, rad in [0, 2 pi)
        self._drop_next = 0
        self._drop_demod: int | None = None  # the demod the next drop applies to (None: every demod)
        self._unlock_until: float | None = None
        # the rate table's encoder on the DIO input (sims/table_twin.TableEncoder; None: nothing wired, DIO reads 0)
        self.table_encoder: TableEncoder | None = None
        self._last_sample: dict[str, dict[str, np.ndarray]] = {}
        self.last_plan: LoopPlan | None = None
        self._settings_version = 0  # bumped by every client set: the loop plan is re-read only then
        self._plan_version = -1
        self._layout: _PollLayout | None = None
        for d in range(6):  # round the power-on rates like a set would
            self._round_rate(f"/{self.device_id}/demods/{d}/rate")

    # ================================================================== connection API (ziDAQServer, level 1)
    def _check_device(self, path: str) -> None:
        p = path.lower()
        if p.startswith("/zi/"):
            return
        dev = p.split("/")[1] if p.startswith("/") else self.device_id
        if dev != self.device_id and not any(c in dev for c in "*?["):
            raise NodeError(f"ZIAPINotFoundException: device {dev} is not connected to this HF2 data server")
        if not self.connected:
            raise NodeError(f"ZIAPINotFoundException: device {self.device_id} is not connected (connectDevice)")

    def connectDevice(self, dev: str, interface: str = "USB", params: str = "") -> None:
        if dev.lower() != self.device_id:
            raise NodeError(f"ZIAPIServerException: device {dev} not found by the HF2 data server")
        if interface.upper() != "USB":
            raise NodeError(f"ZIAPIServerException: HF2 devices connect over USB only, not {interface!r}")
        self.connected = True

    def disconnectDevice(self, dev: str) -> None:
        if dev.lower() == self.device_id:
            self.connected = False
            self.subscribed.clear()

    def update(self) -> None:
        """Device detection on Linux HF2 servers: nothing to do for the twin."""

    def listNodesJSON(self, path: str, *args: Any, **kwargs: Any) -> str:
        raise NodeError(
            "ZIAPINotSupportedException: listNodesJSON is not available on the HF2 data server (API level 1)"
        )

    def listNodes(self, path: str, *args: Any, **kwargs: Any) -> list[str]:
        p = path.lower()
        if p.startswith("/zi"):
            pat = p if any(c in p for c in "*?[") else p.rstrip("/") + "/*"
            return [k.upper() for k in self._zi if fnmatch.fnmatchcase(k, pat)]
        self._check_device(p)
        return self.nodes.list(
            p,
            settings_only=kwargs.get("settingsonly", False),
            streaming_only=kwargs.get("streamingonly", False),
            exclude_streaming=kwargs.get("excludestreaming", False),
        )

    def _read(self, path: str) -> Any:
        """A node's value. A device path read once before goes straight to its value (the driver reads three
        nodes every poll): what the checks decided for it cannot change but for the connection, checked anew."""
        known = self._read_paths.get(path)
        if known is not None and self.connected:
            return self.nodes.values[known]
        p = path.lower()
        if p.startswith("/zi/"):
            if p not in self._zi:
                raise NodeError(f"ZIAPINotFoundException: node {p} does not exist")
            return self._zi[p]
        self._check_device(p)
        value = self.nodes.read(p)
        self._read_paths[path] = self.nodes.meta_of(p).path
        return value

    def getInt(self, path: str) -> int:
        v = self._read(path)
        if isinstance(v, str):
            raise NodeError(f"ZIAPIException: node {path} holds a string, not an integer")
        return int(v)

    def getDouble(self, path: str) -> float:
        v = self._read(path)
        if isinstance(v, str):
            raise NodeError(f"ZIAPIException: node {path} holds a string, not a number")
        return float(v)

    def getString(self, path: str) -> str:
        v = self._read(path)
        if not isinstance(v, str):
            raise NodeError(f"ZIAPIException: node {path} is numeric, not a string")
        return v

    def getSample(self, path: str) -> dict[str, np.ndarray]:
        p = self.nodes.absolute(path)
        self._check_device(p)
        if not fnmatch.fnmatchcase(p, f"/{self.device_id}/demods/*/sample"):
            raise NodeError(f"ZIAPIException: node {p} is not a demodulator sample node")
        if p in self._last_sample:
            return {k: v[-1:].copy() for k, v in self._last_sample[p].items()}
        d = int(p.split("/")[3])
        if not int(self.nodes.peek(f"demods/{d}/enable")):  # *assumed*: a disabled demod sends no sample
            raise NodeError(f"ZIAPITimeoutException: no sample of {p} (the demodulator is disabled)")
        sample = {k: np.zeros(1, dtype=np.uint64 if k == "timestamp" else float) for k in DEMOD_FIELDS}
        ticks = int(round(self.world.now() * self.clockbase_hz)) + (self.timestamp_offset_ticks if d else 0)
        sample["timestamp"] = np.array([ticks], dtype=np.uint64)  # an enabled demod's latest: stamped about now
        return sample

    def get(self, paths: str, *args: Any, flat: bool = False, settingsonly: bool = True, **kwargs: Any) -> dict:
        """Values of the matching nodes: flat {path: array([v])} or nested {dev: {branch: ...}}. Streams are
        never returned; settingsonly (default True) filters wildcard/branch matches, not explicit leaves."""
        flags = args[0] if args else kwargs.get("flags")
        if flags is not None:
            settingsonly = bool(int(flags) & 8)
        out: dict[str, Any] = {}
        for raw_expr in str(paths).split(","):
            expr = raw_expr.strip().lower()
            if expr.startswith("/zi"):
                pat = expr
                for k, v in self._zi.items():
                    if fnmatch.fnmatchcase(k, pat) or k.startswith(pat.rstrip("/") + "/"):
                        out[k] = [v] if isinstance(v, str) else np.array([v])
                continue
            self._check_device(expr)
            hits = self.nodes.resolve(expr)
            explicit = len(hits) == 1 and hits[0] == self.nodes.absolute(expr)
            for p in hits:
                m = self.nodes.meta[p]
                if not m.is_value or not m.readable or (settingsonly and not explicit and not m.setting):
                    continue
                v = self.nodes.values[p]
                out[p] = [v] if isinstance(v, str) else np.array([v])
        if flat:
            return out
        nested: dict[str, Any] = {}
        for p, v in out.items():
            cur = nested
            parts = p.strip("/").split("/")
            for part in parts[:-1]:
                cur = cur.setdefault(part, {})
            cur[parts[-1]] = v
        return nested

    def set(self, path: Any, value: Any = None, **kwargs: Any) -> None:
        """set(path, value) or set([(path, value), ...]); the list is validated whole before any node changes."""
        items = [(path, value)] if isinstance(path, str) else list(path)
        checked = []
        for raw_path, v in items:
            p = str(raw_path).lower()
            if p.startswith("/zi/"):
                checked.append((p, v))
                continue
            self._check_device(p)
            hits = self.nodes.resolve(p)
            if not hits:
                raise NodeError(f"ZIAPINotFoundException: node {p} does not exist")
            checked.extend(self.nodes.coerce(h, v) for h in hits if len(hits) == 1 or self.nodes.meta[h].writable)
        self._settings_version += 1
        for p, v in checked:
            if p.startswith("/zi/"):
                if p not in ("/zi/config/open", "/zi/debug/level"):
                    raise NodeError(f"ZIAPIWriteException: node {p} is read-only")
                self._zi[p] = int(v)
                continue
            self.nodes.values[p] = v
            if fnmatch.fnmatchcase(p, "/*/demods/*/rate"):
                self._round_rate(p)

    def setInt(self, path: str, value: int) -> None:
        self.set(path, int(value))

    def setDouble(self, path: str, value: float) -> None:
        self.set(path, float(value))

    def setString(self, path: str, value: str) -> None:
        self.set(path, str(value))

    def syncSetInt(self, path: str, value: int) -> int:
        self.set(path, int(value))
        return self.getInt(path)

    def syncSetDouble(self, path: str, value: float) -> float:
        self.set(path, float(value))
        return self.getDouble(path)

    def syncSetString(self, path: str, value: str) -> str:
        self.set(path, str(value))
        return self.getString(path)

    def sync(self) -> None:
        """All sets are applied at once and nothing is buffered between polls: nothing to flush."""

    def echoDevice(self, dev: str) -> None:
        self._check_device(f"/{dev}")

    def _stream_paths(self, path: Any) -> list[str]:
        paths = [path] if isinstance(path, str) else list(path)
        out = []
        for p in paths:
            self._check_device(str(p))
            hits = [h for h in self.nodes.resolve(str(p)) if self.nodes.meta[h].stream]
            if not hits:
                raise NodeError(f"ZIAPINotFoundException: no streaming node matches {p}")
            out.extend(hits)
        return out

    def subscribe(self, path: Any, group_id: int = 1) -> None:
        self.subscribed.update(self._stream_paths(path))

    def unsubscribe(self, path: Any, group_id: int = 1) -> None:
        self.subscribed.difference_update(self._stream_paths(path))

    def poll(
        self, recording_time_s: float, timeout_ms: int = 500, flags: int = 0, flat: bool = False, group_id: int = 1
    ) -> dict:
        """Advance the world by the recording time and return the subscribed demodulators' samples."""
        if recording_time_s <= 0:
            raise NodeError(f"ZIAPIException: poll recording time {recording_time_s!r} s must be positive")
        demods = sorted(p for p in self.subscribed if p.endswith("/sample") and "/demods/" in p)
        if not self.subscribed:
            return {}
        data = self._advance(recording_time_s, demods)
        if flat:
            return data
        nested: dict[str, Any] = {}
        for p, v in data.items():
            _, dev, branch, idx, leaf = p.split("/")
            nested.setdefault(dev, {}).setdefault(branch, {}).setdefault(idx, {})[leaf] = v
        return nested

    # ================================================================== fault hooks
    def drop_samples(self, n: int, demod: int | None = None) -> None:
        """The next poll loses n samples from the middle of its block (timestamp gap, sample-loss flag): from every
        demodulator's stream, or from demodulator `demod`'s only."""
        if int(n) < 0:
            raise ValueError(f"drop_samples: n = {n!r} must be >= 0")
        self._drop_next += int(n)
        self._drop_demod = None if demod is None else int(demod)

    def run_unobserved(self, seconds: float) -> None:
        """The instrument runs on for `seconds` of world time while no client sees it (a dropped host link,
        sims/faults.py): the world and the loops advance, the samples are not delivered (the next delivered
        block's timestamps show the gap, as a real HF2's do after a reconnect)."""
        if seconds > 0:
            self._advance(seconds, [])

    def force_pll_unlock(self, duration_s: float) -> None:
        """The PLL runs open (frequency at its centre) and reports unlock for duration_s of world time from now."""
        if not duration_s >= 0:
            raise ValueError(f"force_pll_unlock: duration_s = {duration_s!r} must be >= 0")
        self._unlock_until = self.world.now() + float(duration_s)

    # ================================================================== physics
    def _round_rate(self, path: str) -> None:
        rate = float(self.nodes.values[path])
        if rate <= 0:
            raise NodeError(f"node {path}: rate {rate!r} Sa/s must be positive")
        if self.rate_set == "hf2":  # nearest rung of the binary ladder (in log scale), at most the base rate
            k = max(1, round(math.log2(HF2_RATE_BASE_HZ / rate)))
            rate = HF2_RATE_BASE_HZ / 2.0**k
        ticks = max(1, round(self.clockbase_hz / rate))
        self.nodes.values[path] = self.clockbase_hz / ticks

    def auxin_window_s(self) -> float:
        """The AuxIn averaging window: 2^averaging ADC samples, s."""
        avg = int(self.nodes.peek("auxins/0/averaging"))
        return float(2 ** max(0, min(15, avg))) / AUXIN_ADC_RATE_HZ

    def _auxin_records(self, blk: GyroBlock, dt: float, window_s: float) -> tuple[np.ndarray, np.ndarray]:
        """(rate AuxOut, dither) as the AuxIns report them at the block's sample instants (module docstring), for
        the averaging window `window_s` (`auxin_window_s`), in one compiled pass (sims/hf2_kernel.py).

        The AuxOut voltage V is linear between instants, V(t_i) = rate_auxout_v[i]; its mean over
        [t_i - W, t_i] (W <= dt) is V(t_i) - (V(t_i) - V(t_(i-1))) W / (2 dt). Each reading then gets white
        reading noise of sigma `auxin_noise_v_rms` (one stream, drawn row after row: the rate AuxIn's block,
        then the dither's), is rounded to the ADC step 2 R / 2^bits and clipped to +-R (R = `auxin_range_v`;
        bits = 0: ideal ADC)."""
        w = min(window_s, dt)
        v = np.ascontiguousarray(blk.rate_auxout_v if blk.rate_auxout_v is not None else blk.rate_output_v, dtype=float)
        if self.world.dither.amplitude_vpp == 0.0:
            dither = np.full(v.shape[0], self.world.dither.offset_v)
        else:
            dither = self.world.window_means_at_step_ends(w)
        n = v.shape[0]
        both = np.empty((2, n))  # row 0 the rate AuxIn, row 1 the dither AuxIn
        p = self.gyro_params
        if p.auxin_noise_v_rms > 0.0:  # one stream, row after row (C order): the rate AuxIn's n, then the dither's
            normals = self._auxin_noise.take(2 * n).reshape(2, n)
        else:
            if self._no_auxin_noise.shape[1] != n:
                self._no_auxin_noise = np.empty((2, n))
            normals = self._no_auxin_noise
        previous = float(v[0]) if self._auxout_prev is None else self._auxout_prev
        hk.auxin_readings(
            v,
            previous,
            w / (2.0 * dt),
            dither,
            normals,
            p.auxin_noise_v_rms,
            p.auxin_lsb_v,
            p.auxin_range_v,
            both,
        )
        self._auxout_prev = float(v[-1])
        return both[0], both[1]

    def _ensure_gyro(self, dt: float) -> Any:
        if self._gyro is None or self._gyro_dt != dt:
            from sims.gyro import GyroSim  # the physics module

            self._gyro = GyroSim(self.gyro_params, dt, self.seed + self._gyro_count)
            self._gyro.reset(settled=True)
            self._gyro_dt = dt
            self._gyro_count += 1
        return self._gyro

    def _run_gyro(self, inputs: BlockInputs, settings: LoopSettings, dt: float) -> tuple[GyroBlock, bool]:
        """Run the block under `settings`, split where a forced PLL unlock ends; returns the block and whether the
        PLL stayed locked (closed and within its lock error) through every step of it."""
        gyro = self._ensure_gyro(dt)
        if self._unlock_until is None:  # the usual poll: one run over the whole block
            blk = gyro.run(inputs, settings)
            return blk, blk.pll_locked
        n = len(inputs.t)
        t_end = inputs.t + dt
        cut = int(np.searchsorted(t_end, self._unlock_until, side="right"))  # steps [0, cut) end while forced open
        blocks, locked = [], True  # locked: no step forced open, every part's PLL within its lock error
        for a, b, forced in ((0, cut, True), (cut, n, False)):
            if b <= a:
                continue
            s = settings
            if forced:
                s = replace(s, pll=replace(s.pll, enabled=False))
            blk = gyro.run(_slice_inputs(inputs, slice(a, b)), s)
            locked = locked and not forced and blk.pll_locked
            blocks.append(blk)
        if t_end[-1] >= self._unlock_until:
            self._unlock_until = None
        if len(blocks) == 1:
            return blocks[0], locked
        merged = {f: np.concatenate([getattr(b, f) for b in blocks]) for f in _ARRAY_FIELDS}
        return type(blocks[0])(**merged, pll_locked=locked), locked

    def _poll_layout(self, demods: list[str]) -> _PollLayout:
        """What a poll reads from the settings, read once per change of the settings or of the subscriptions: the
        nodes change only through `set` (which bumps the settings version) or `poke` of read-only nodes and of the
        PLL's own oscillator frequency (which the layout does not hold)."""
        key = (self._settings_version, tuple(demods))
        if self._layout is not None and self._layout.key == key:
            return self._layout
        if self.last_plan is None or self._plan_version != self._settings_version:
            self.last_plan = identify_loops(self.nodes, self.wiring)
            self._plan_version = self._settings_version
        plan = self.last_plan
        nd = self.nodes
        rate = float(nd.peek(f"demods/{plan.sense_demod}/rate"))
        tps = int(round(self.clockbase_hz / rate))
        specs = []
        used = {plan.ref_osc}
        for path in demods:
            d = int(path.split("/")[3])
            osc = int(nd.peek(f"demods/{d}/oscselect"))
            used.add(osc)
            if not int(nd.peek(f"demods/{d}/enable")):
                continue
            specs.append(
                _DemodSpec(
                    path=path,
                    sigin=int(nd.peek(f"demods/{d}/adcselect")),
                    osc=osc,
                    harmonic=int(nd.peek(f"demods/{d}/harmonic")),
                    shift_rad=math.radians(float(nd.peek(f"demods/{d}/phaseshift"))),
                )
            )
        fixed_hz = {o: float(nd.peek(f"oscs/{o}/freq")) for o in range(nd.n_oscillators) if o != plan.ref_osc}
        self._layout = _PollLayout(
            key=key,
            plan=plan,
            ticks_per_sample=tps,
            dt=tps / self.clockbase_hz,
            demods=tuple(specs),
            used_oscs=frozenset(used),
            fixed_osc_hz=fixed_hz,
            auxin_window_s=self.auxin_window_s(),
            pid_settings={
                name: (float(nd.peek(f"pids/{n}/setpoint")), float(nd.peek(f"pids/{n}/center")))
                for name, n in plan.pid_of.items()
                if n is not None
            },
            paths=self._reflect_paths(plan),
        )
        return self._layout

    def _advance(self, rec_s: float, demods: list[str]) -> dict[str, dict[str, np.ndarray]]:
        layout = self._poll_layout(demods)
        plan = layout.plan
        tps, dt = layout.ticks_per_sample, layout.dt
        n = int(round(rec_s / dt))
        if n < 1:
            return {}
        world_ticks = int(round(self.world.now() * self.clockbase_hz))
        if self._ticks is None or abs(world_ticks - self._ticks) > tps // 2:
            self._ticks = world_ticks
        # a PLL besides PLL 1 that the forcer carrier depends on tracks only while the drive frequency lies in its
        # range (checked at the start of the block, sims/hf2_loops.py): out of range its carrier is not coherent
        settings = plan.settings
        drive_hz = float(self.nodes.values[layout.paths.ref_osc_freq])
        tracking = {o: t.tracks(drive_hz) for o, t in plan.trackers.items()}
        if plan.forcer_tracker is not None and not tracking[plan.forcer_tracker.osc]:
            settings = replace(settings, forcer_gain=0.0)
        inputs = self.world.advance(n, dt)
        self.world.set_forcer_gain(settings.forcer_gain)
        blk, locked = self._run_gyro(inputs, settings, dt)
        timestamps, truth_time = np.empty(n, dtype=np.uint64), np.empty(n)
        hk.sample_times(self._ticks, tps, self.clockbase_hz, timestamps, truth_time)
        self._ticks += n * tps
        # oscillator frequencies, unwrapped phases (rad) at the end of each step and the demods' wrapped phases
        freqs: dict[int, np.ndarray] = {}
        phases: dict[int, np.ndarray] = {}
        osc_streams: dict[tuple[int, int], tuple[np.ndarray, np.ndarray]] = {}
        for o in range(len(self._osc_phase)):
            if o not in layout.used_oscs:  # keep its phase running without building arrays (float % is np.mod)
                self._osc_phase[o] = (self._osc_phase[o] + 2 * np.pi * layout.fixed_osc_hz[o] * n * dt) % (2 * np.pi)
                continue
            follows = o == plan.ref_osc or tracking.get(o, False)  # the reference, or locked by a tracking PLL
            f_o = blk.frequency_hz if follows else np.full(n, layout.fixed_osc_hz[o])
            ph, wrapped = np.empty(n), np.empty(n)
            hk.oscillator_phases(f_o, self._osc_phase[o], dt, 1.0, ph, wrapped)
            freqs[o], phases[o] = f_o, ph
            osc_streams[o, 1] = (f_o, wrapped)
            self._osc_phase[o] = float(ph[-1]) % (2 * np.pi)
        if plan.pll_closed:  # the PLL writes its oscillator's frequency
            self.nodes.values[layout.paths.ref_osc_freq] = float(freqs[plan.ref_osc][-1])
        for o, on in tracking.items():  # and so does a tracking PLL, while it tracks
            if on:
                self.nodes.values[f"/{self.device_id}/oscs/{o}/freq"] = float(blk.frequency_hz[-1])
        wired: list[np.ndarray | None] = [None, None]
        rate_aux, dither_aux = self._auxin_records(blk, dt, layout.auxin_window_s)
        wired[self.wiring.rate_auxin], wired[self.wiring.dither_auxin] = rate_aux, dither_aux
        aux = [a if a is not None else np.zeros(n) for a in wired]  # an AuxIn with nothing wired reads 0 V
        dio = self._dio_inputs(inputs, dt)
        keep = None
        dropped = min(self._drop_next, max(0, n - 2))
        drop_demod, self._drop_demod = self._drop_demod, None
        if dropped:
            keep = np.ones(n, dtype=bool)
            i0 = (n - dropped) // 2
            keep[i0 : i0 + dropped] = False
        self._drop_next = 0
        offset = self.timestamp_offset_ticks
        shifted = (timestamps.view(np.int64) + offset).view(np.uint64) if offset else timestamps
        out: dict[str, dict[str, np.ndarray]] = {}
        for spec in layout.demods:
            osc, harmonic = spec.osc, spec.harmonic
            if (osc, harmonic) not in osc_streams:  # a harmonic other than 1: (h phi) mod 2 pi
                wrapped = np.mod(phases[osc] * harmonic, 2 * np.pi)
                osc_streams[osc, harmonic] = (freqs[osc] * harmonic, wrapped)
            frequency, phase = osc_streams[osc, harmonic]
            x, y = self._demod_xy(blk, spec, plan.ref_osc, phases, n)
            d = int(spec.path.split("/")[3])
            sample = {
                "timestamp": shifted if d != 0 else timestamps,
                "x": x,
                "y": y,
                "frequency": frequency,
                "phase": phase,
                "dio": dio,
                "trigger": np.zeros(n, dtype=np.uint32),
                "auxin0": aux[0],
                "auxin1": aux[1],
            }
            if keep is not None and drop_demod in (None, d):
                sample = {k: v[keep] for k, v in sample.items()}
            out[spec.path] = sample
            self._last_sample[spec.path] = sample  # getSample copies its last entries
        self._reflect(layout, blk, locked, aux, dropped, tracking)
        self.world.record_truth(
            TruthRecord(
                time=truth_time,
                scale_factor=np.array(blk.sf_true_v_per_dps, dtype=float),  # a copy: the truth outlives the block
                temperature=np.asarray(inputs.gyro_c, dtype=float),
                rate=np.asarray(blk.rate_true_dps, dtype=float),
            )
        )
        return out

    def _dio_inputs(self, inputs: BlockInputs, dt: float) -> np.ndarray:
        """The DIO input word of each sample: the table encoder's A/B at the sample instant, the end of its step
        (angle at the step start + the step's mean delivered rate x dt); zeros with nothing wired."""
        if self.table_encoder is None:
            return np.zeros(inputs.t.shape[0], dtype=np.uint32)
        return self.table_encoder.dio_word(inputs.table_angle_deg + inputs.table_rate_dps * dt)

    def _demod_xy(
        self, blk: GyroBlock, spec: _DemodSpec, ref_osc: int, phases: dict[int, np.ndarray], n: int
    ) -> tuple[np.ndarray, np.ndarray]:
        """x, y of one demod: the physics' drive or sense signal (zero for another input or a harmonic != 1),
        rotated by exp(-i(phi_osc + phaseshift - phi_ref)) if its oscillator is not the reference or it has a
        phase shift."""
        if spec.harmonic != 1 or spec.sigin not in (self.wiring.drive_sigin, self.wiring.sense_sigin):
            return np.zeros(n), np.zeros(n)
        drive = spec.sigin == self.wiring.drive_sigin
        x = np.asarray(blk.x_drive if drive else blk.x_sense, dtype=float)
        y = np.asarray(blk.y_drive if drive else blk.y_sense, dtype=float)
        if spec.osc == ref_osc and spec.shift_rad == 0.0:  # the block's own rows (fresh every block: no copy)
            return x, y
        z = (x + 1j * y) * np.exp(-1j * (phases[spec.osc] + spec.shift_rad - phases[ref_osc]))
        return z.real.copy(), z.imag.copy()

    def _reflect_paths(self, plan: LoopPlan) -> _ReflectPaths:
        dev = f"/{self.device_id}"
        pids = {name: n for name, n in plan.pid_of.items() if n is not None}
        return _ReflectPaths(
            ref_osc_freq=f"{dev}/oscs/{plan.ref_osc}/freq",
            pll_locked=f"{dev}/plls/0/locked",
            pll_freqdelta=f"{dev}/plls/0/freqdelta",
            pll_freqcenter=f"{dev}/plls/0/freqcenter",
            pll_error=f"{dev}/plls/0/error",
            flags_binary=f"{dev}/status/flags/binary",
            flags_sampleloss=f"{dev}/status/flags/demodsampleloss",
            status_time=f"{dev}/status/time",
            pid_error={name: f"{dev}/pids/{n}/error" for name, n in pids.items()},
            pid_shift={name: f"{dev}/pids/{n}/shift" for name, n in pids.items()},
            rate_auxout=f"{dev}/auxouts/{self.wiring.rate_auxout}/value",
            quadrature_auxout=f"{dev}/auxouts/{self.wiring.quadrature_auxout}/value",
            auxin_values=(f"{dev}/auxins/0/values/0", f"{dev}/auxins/0/values/1"),
        )

    def _reflect(
        self,
        layout: _PollLayout,
        blk: GyroBlock,
        locked: bool,
        aux: list[np.ndarray],
        dropped: int,
        tracking: dict[int, bool],
    ) -> None:
        """Read-only nodes at the end of the block (module docstring, item 4), written straight into the node
        values under the layout's absolute paths. A tracking PLL (sims/hf2_loops.py) reports locked while it tracks
        a drive PLL 1 holds locked (the signal both lock to), with its frequency offset from its own centre."""
        plan, paths, values = layout.plan, layout.paths, self.nodes.values
        pll_locked = bool(plan.pll_closed and blk.pll_locked and locked)
        f_end = float(blk.frequency_hz[-1])
        values[paths.pll_locked] = int(pll_locked)
        values[paths.pll_freqdelta] = f_end - float(values[paths.pll_freqcenter]) if plan.pll_closed else 0.0
        values[paths.pll_error] = float(blk.pll_error_deg[-1]) if plan.pll_closed else 0.0
        binary = int(values[paths.flags_binary]) & ~(PLL_LOCKED_BITS[0] | PLL_LOCKED_BITS[1])
        binary |= PLL_LOCKED_BITS[0] if pll_locked else 0
        dev = f"/{self.device_id}"
        for n in range(1, len(PLL_LOCKED_BITS)):
            tracker = next((t for t in plan.trackers.values() if t.index == n), None)
            on = tracker is not None and pll_locked and tracking[tracker.osc]
            if self.nodes.has(f"{dev}/plls/{n}/locked"):
                values[f"{dev}/plls/{n}/locked"] = int(on)
                values[f"{dev}/plls/{n}/freqdelta"] = f_end - tracker.center_hz if on and tracker else 0.0
            binary |= PLL_LOCKED_BITS[n] if on else 0
        values[paths.flags_binary] = binary
        values[paths.flags_sampleloss] = int(dropped > 0)
        values[paths.status_time] = self.world.now()
        ends = {
            "agc": (abs(complex(float(blk.x_drive[-1]), float(blk.y_drive[-1]))), float(blk.drive_output_v[-1])),
            "rate": (float(blk.x_sense[-1]), float(blk.rate_output_v[-1])),
            "quadrature": (float(blk.y_sense[-1]), float(blk.quadrature_output_v[-1])),
        }
        for name, (setpoint, center) in layout.pid_settings.items():
            inp, out = ends[name]
            values[paths.pid_error[name]] = setpoint - inp
            values[paths.pid_shift[name]] = out - center
        values[paths.rate_auxout] = ends["rate"][1]
        values[paths.quadrature_auxout] = ends["quadrature"][1]
        values[paths.auxin_values[0]] = float(aux[0][-1])
        values[paths.auxin_values[1]] = float(aux[1][-1])


_ARRAY_FIELDS = (
    "x_drive",
    "y_drive",
    "x_sense",
    "y_sense",
    "frequency_hz",
    "drive_output_v",
    "rate_output_v",
    "rate_auxout_v",
    "quadrature_output_v",
    "pll_error_deg",
    "sf_true_v_per_dps",
    "rate_true_dps",
)
