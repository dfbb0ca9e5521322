"""Abstract instrument interfaces and the types they exchange.

The campaign, the CLSF estimator and the CLI see only these interfaces. Real drivers (`drivers/`) and their
twins behind the same drivers implement them; `qmg_lab/station.py` is the only place that knows which.

Units are in the names: *_v volts, *_vrms volts rms, *_hz hertz, *_dps degrees per second, *_dps2 degrees per
second squared, *_deg degrees, *_c degrees Celsius, *_s seconds.
"""

from __future__ import annotations

import abc
import contextlib
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

#: the station's four instruments, by the names the configuration's sections, the station, the CLI and the run
#: file's `instrument_modes` attribute use (the one place they are spelled)
INSTRUMENT_NAMES: tuple[str, ...] = ("lockin", "generator", "table", "chamber")
#: how an instrument runs: on its simulated twin or on the hardware
INSTRUMENT_MODES: tuple[str, ...] = ("twin", "hardware")


class InstrumentError(RuntimeError):
    """An instrument did not do what it was told: timeout, garbled reply, disconnect, reported error."""


class LimitError(ValueError):
    """A command refused before anything was sent because it lies outside an instrument's limits."""


class InterlockError(InstrumentError):
    """The rate table's interlock tripped (or a similar hardware protection acted)."""


def check_limit(name: str, value: float, low: float, high: float, unit: str) -> float:
    """Return `value` if low <= value <= high, else raise LimitError naming the limit."""
    if not np.isfinite(value):
        raise LimitError(f"{name} = {value!r} is not a finite number")
    if value < low or value > high:
        raise LimitError(f"{name} = {value:g} {unit} is outside the limit [{low:g}, {high:g}] {unit}")
    return float(value)


# --------------------------------------------------------------------------------------------- lock-in


@dataclass(frozen=True)
class PidGains:
    """One HF2 PID (or PLL) in the lock-in's own units: output = center + P*e + I*integral(e) + D*de/dt,
    e = setpoint - input, output clamped to center +- range."""

    p: float
    i: float
    d: float = 0.0
    setpoint: float = 0.0
    center: float = 0.0
    range: float = 10.0


@dataclass(frozen=True)
class LockInSetup:
    """Everything the lock-in driver configures before a run (see qmg_lab/campaign/loops.py for the gain design).

    pll: PLL 0 on the drive demod, p in Hz/deg, i in Hz^2/deg, center = f0.
    agc: PID on R of the drive demod (Vrms) -> drive output amplitude (V).
    rate: PID on X of the sense demod (Vrms) -> rate AuxOut (V): the FTR rebalance command f_y.
    quadrature: PID on Y of the sense demod (Vrms) -> quadrature AuxOut (V).
    """

    f0_hz: float
    pll: PidGains
    pll_range_hz: float
    agc: PidGains
    rate: PidGains
    quadrature: PidGains
    demod_rate_hz: float
    demod_timeconstant_s: float
    demod_order: int
    forcer_gain: float = 1.0
    auxin_averaging: int = 0  # the AuxIns average 2^this ADC samples per reading


@dataclass(frozen=True)
class StreamTiming:
    """What the lock-in actually applies to the streamed samples (read back from the instrument), s and Sa/s.

    rate_hz: demodulator sample rate; filter_order, filter_tc_s: the demodulator low-pass on x_sense/y_sense
    (H(s) = 1/(1 + s tc)^order); auxin_window_s: the AuxIn averaging window that ends at each sample's timestamp
    (rate_output and dither are window means)."""

    rate_hz: float
    filter_order: int
    filter_tc_s: float
    auxin_window_s: float


@dataclass
class LockInBlock:
    """One polled block of demodulator samples, all arrays the same length, time in s since the stream start.

    x_sense/y_sense: c_y/s_y of the sense demod (Vrms); rate_output: the rate PID output recorded on an AuxIn
    (V); drive_amplitude: R of the drive demod (Vrms); drive_frequency: PLL oscillator (Hz); dither: the DS345
    output recorded on the other AuxIn (V); table_encoder: the HF2 DIO input word of each sample (the table
    encoder's A/B bits as cabled, docs/wiring.md; an integer held in a float). pll_locked: False if the PLL
    reported unlock during the block.
    samples_lost: number of samples the stream says were dropped (gaps in the timestamps).
    """

    time: np.ndarray
    x_sense: np.ndarray
    y_sense: np.ndarray
    rate_output: np.ndarray
    drive_amplitude: np.ndarray
    drive_frequency: np.ndarray
    dither: np.ndarray
    table_encoder: np.ndarray
    pll_locked: bool = True
    samples_lost: int = 0

    def __len__(self) -> int:
        return int(self.time.shape[0])

    FIELDS = (
        "time",
        "x_sense",
        "y_sense",
        "rate_output",
        "drive_amplitude",
        "drive_frequency",
        "dither",
        "table_encoder",
    )


class Instrument(abc.ABC):
    """What every instrument offers: identity, a state summary, the safe state, closing."""

    @abc.abstractmethod
    def identify(self) -> str:
        """The instrument's identity string (e.g. the *IDN? answer)."""

    @abc.abstractmethod
    def state(self) -> dict[str, Any]:
        """A JSON-serialisable summary of the current settings and readings."""

    @abc.abstractmethod
    def safe_state(self) -> None:
        """Bring the instrument to its safe state. Must be idempotent and must not raise on a healthy link."""

    @abc.abstractmethod
    def close(self) -> None:
        """Release the transport."""

    def reconnect(self) -> None:
        """Close and reopen the transport, re-verify identity and restore settings. Default: not supported."""
        raise InstrumentError(f"{type(self).__name__} cannot reconnect")

    def snapshot(self) -> dict[str, Any]:
        """A JSON-serialisable record for the run file (like a QCoDeS snapshot): identity, firmware, the
        driver's settings (limits, framing, ...) and state(). Drivers add what they know; the default has
        identity and state, and the firmware as far as an IEEE 488.2 identity string says (4th field)."""
        identity = self.identify()
        fields = [f.strip() for f in identity.split(",")]
        return {
            "identity": identity,
            "firmware": fields[3] if len(fields) == 4 else None,
            "settings": {},
            "state": self.state(),
        }


class LockIn(Instrument):
    """The HF2LI closing the gyroscope's loops and streaming the demodulators."""

    @abc.abstractmethod
    def configure(self, setup: LockInSetup) -> None:
        """Set oscillators, demodulators, PLL, the four PIDs and the outputs; enable the loops."""

    @abc.abstractmethod
    def start_stream(self) -> None:
        """Subscribe to the demodulator streams; the next poll returns samples from now on."""

    @abc.abstractmethod
    def poll(self, duration_s: float) -> LockInBlock:
        """Return the next block of about `duration_s` of samples (on hardware: waits for real time)."""

    @abc.abstractmethod
    def stop_stream(self) -> None:
        """Unsubscribe."""

    @abc.abstractmethod
    def set_forcer_gain(self, gain: float) -> None:
        """Scale the forcer path (rate command and dither alike) by `gain` (1.0 = nominal): CLSF correct mode."""

    @abc.abstractmethod
    def pll_locked(self) -> bool:
        """True if the PLL reports lock."""

    @abc.abstractmethod
    def stream_timing(self) -> StreamTiming:
        """The sample rate, demodulator filter and AuxIn window the instrument applies (read back, after
        configure): what the CLSF estimator must model."""


class FunctionGenerator(Instrument):
    """The DS345 that makes the CLSF dither."""

    @abc.abstractmethod
    def set_square(self, frequency_hz: float, amplitude_vpp: float, offset_v: float = 0.0) -> None:
        """Square wave of the given frequency and peak-to-peak amplitude; raises LimitError outside limits."""

    @abc.abstractmethod
    def set_sine(self, frequency_hz: float, amplitude_vpp: float, offset_v: float = 0.0) -> None:
        """Sine wave."""

    @abc.abstractmethod
    def mute(self) -> None:
        """Zero output amplitude (the DS345 has no output switch: AMPL 0VP)."""


@dataclass(frozen=True)
class TableReading:
    rate_dps: float
    position_deg: float
    status: int
    interlock: bool = False


class RateTable(Instrument):
    """The 1291BR single-axis rate table."""

    max_rate_dps: float
    max_accel_dps2: float

    @abc.abstractmethod
    def set_rate(self, rate_dps: float, accel_dps2: float) -> None:
        """Rate mode: ramp to `rate_dps` at `accel_dps2`; raises LimitError outside limits."""

    @abc.abstractmethod
    def set_sinusoid(self, amplitude_dps: float, frequency_hz: float, accel_dps2: float) -> None:
        """Sinusoidal rate: rate(t) = amplitude * sin(2 pi f t)."""

    @abc.abstractmethod
    def stop(self) -> None:
        """Decelerate to rest."""

    @abc.abstractmethod
    def read(self) -> TableReading:
        """Measured rate, position and status."""


@dataclass(frozen=True)
class ChamberReading:
    temperature_c: float
    setpoint_c: float
    ramping: bool = False


class ThermalChamber(Instrument):
    """The rate table's thermal chamber."""

    min_c: float
    max_c: float

    @abc.abstractmethod
    def set_setpoint(self, setpoint_c: float, ramp_c_per_min: float) -> None:
        """Ramp to `setpoint_c` at `ramp_c_per_min`; raises LimitError outside limits."""

    @abc.abstractmethod
    def read(self) -> ChamberReading:
        """Air temperature and the controller's current setpoint."""


@dataclass
class TruthBlock:
    """What only a twin knows, sampled at the lock-in's sample times (for /truth in run files)."""

    time: np.ndarray
    scale_factor: np.ndarray  # true FTR SF, V per deg/s
    temperature: np.ndarray  # gyro, deg C
    rate: np.ndarray  # true input rate, deg/s

    FIELDS = ("time", "scale_factor", "temperature", "rate")


class TruthSource(abc.ABC):
    """Twins only: drains the truth recorded since the last call."""

    @abc.abstractmethod
    def drain(self) -> TruthBlock | None:
        """Truth since the last call (None if nothing new)."""


SAFE_STATE_ORDER: tuple[str, ...] = ("table", "generator", "chamber", "lockin")
"""The one order in which a bench is made safe: the table first (it can hurt someone), the lock-in last (its
stream is the clock that keeps the run log going while the others are made safe and, if they refuse, retried)."""


@dataclass
class Station:
    """The four instruments of a bench (built by qmg_lab/station.py)."""

    lockin: LockIn
    generator: FunctionGenerator
    table: RateTable
    chamber: ThermalChamber
    simulated: dict[str, bool] = field(default_factory=dict)
    truth: TruthSource | None = None
    # Twins only: told where the physical world was when a resumed run's process died (last time, temperatures)
    restore: Callable[[dict[str, Any]], None] | None = None
    # length of each lock-in poll, s (the station knows whether the lock-in is a twin or real)
    poll_interval_s: float = 0.5
    # called by close() after the instruments (e.g. stopping a twin's pty or socket server)
    on_close: list[Callable[[], None]] = field(default_factory=list)
    # Twins only: the faults injected so far ([sim.faults]), as dicts time_s/kind/instrument/detail
    injected_faults: Callable[[], list[dict[str, Any]]] | None = None

    def instruments(self) -> dict[str, Instrument]:
        return {"lockin": self.lockin, "generator": self.generator, "table": self.table, "chamber": self.chamber}

    def safe_state(self) -> list[str]:
        """Every instrument to its safe state, in SAFE_STATE_ORDER, each tried once. Returns the failures."""
        failures: list[str] = []
        for name in SAFE_STATE_ORDER:
            try:
                self.instruments()[name].safe_state()
            except Exception as exc:
                failures.append(f"{name}: {exc}")
        return failures

    def close(self) -> None:
        for inst in self.instruments().values():
            with contextlib.suppress(Exception):
                inst.close()
        for fn in self.on_close:
            with contextlib.suppress(Exception):
                fn()
        self.on_close.clear()
