"""The TOML configuration of a campaign, validated with pydantic.

Every section is a strict model (unknown keys are errors) whose fields carry their unit in the name or in
the description, and their allowed range as constraints. `load_config(path)` reads and validates a file;
`ConfigError` carries a message that names the offending field and its allowed range (worded by
qmg_lab/config/errors.py), for the CLI to print with exit code 2. docs/configuration.md is generated from this
schema by qmg_lab/config/docs.py.

Why one module of this length: it is the whole schema, one strict model per TOML section with every field's
bounds, unit and description; the cross-section checks need every section in one place.
"""

from __future__ import annotations

import hashlib
import math
import os
import stat
import sys
import tomllib
from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import AfterValidator, BaseModel, ConfigDict, Field, JsonValue, ValidationError, model_validator

from qmg_lab.clsf.stream_plan import StreamPlan, hf2_rate
from qmg_lab.config.errors import describe_error, toml_syntax_message
from qmg_lab.instruments import INSTRUMENT_NAMES


class ConfigError(ValueError):
    """A configuration that cannot be used; the message names the field and what is allowed."""


class _Section(BaseModel):
    # strict: a TOML string or boolean is not silently taken for a number ("10", true), nor a number or a string
    # for a boolean (1, "yes"); integers are accepted where a float is expected.
    # allow_inf_nan=False: every float of every section is finite (TOML's inf and nan are refused), one policy for
    # all sections and the keys added later; a key that needs inf would have to say so in its own Field.
    model_config = ConfigDict(extra="forbid", frozen=True, validate_default=True, strict=True, allow_inf_nan=False)


Terminator = Literal["CR", "LF", "CRLF"]
ReplyTerminator = Literal["auto", "CR", "LF", "CRLF"]
PositiveFloat = Annotated[float, Field(gt=0, allow_inf_nan=False)]
HF2Option = Literal["MF", "PLL", "PID", "MOD"]
DEFAULT_HF2_OPTIONS: tuple[HF2Option, ...] = ("MF", "PLL", "PID")
FiniteFloat = Annotated[float, Field(allow_inf_nan=False)]
TimeS = Annotated[float, Field(ge=0.0)]  # an instant of the run, s: never negative (finite by the section policy)


def _limited_by(*keys: str) -> dict[str, JsonValue]:
    """A plan key's bounds are instrument limits set elsewhere in the configuration (one source for each bound):
    two keys, the value lies in [low, high]; one key, |value| <= it (for a list, every item). `Config` checks
    them when it is validated, and the error and docs/configuration.md name the keys (`plan_limit_problems`)."""
    return {"limited_by": list(keys)}


#: the serial ports of the table and the chamber by default, per OS (`sys.platform`): a USB-serial adapter is
#: /dev/ttyUSB<n> on Linux (the kernel's usbserial naming) and COM<n> on Windows, where COM1 and COM2 are
#: usually the board's own ports and the first adapter gets COM3 (Device Manager, "Ports (COM & LPT)").
#: Every other OS takes the POSIX names.
SERIAL_PORT_DEFAULTS: dict[str, dict[str, str]] = {
    "win32": {"table": "COM3", "chamber": "COM4"},
    "posix": {"table": "/dev/ttyUSB0", "chamber": "/dev/ttyUSB1"},
}


def default_serial_port(instrument: Literal["table", "chamber"], platform: str = sys.platform) -> str:
    """The default [table]/[chamber] port on `platform` (SERIAL_PORT_DEFAULTS: the one place of these names)."""
    return SERIAL_PORT_DEFAULTS["win32" if platform == "win32" else "posix"][instrument]


def _per_os_port(instrument: Literal["table", "chamber"]) -> dict[str, JsonValue]:
    """json_schema_extra of a port field: its per-OS defaults, for docs/configuration.md (qmg_lab.config.docs)."""
    return {"default_per_os": {os_name: ports[instrument] for os_name, ports in SERIAL_PORT_DEFAULTS.items()}}


def _transport_on_this_system(value: str) -> str:
    """The twins' pty transport needs POSIX pseudo-terminals (sims/serial_twin.py): refuse it where there are none."""
    if value == "pty" and os.name != "posix":
        raise ValueError('"pty" needs a POSIX system (Linux, macOS): on Windows use "inprocess" or "socket"')
    return value


SimTransport = Annotated[Literal["inprocess", "pty", "socket"], AfterValidator(_transport_on_this_system)]


NOTES_MAX_CHARS = 2000  # [campaign] notes and `run --note`: a paragraph, not a document


class CampaignSection(_Section):
    """What kind of campaign the `[plan]` describes."""

    name: str = Field("campaign", min_length=1, max_length=200, description="free-text name stored in the file")
    kind: Literal["temperature_sweep", "allan", "bandwidth", "linearity"] = Field(
        "temperature_sweep",
        description="temperature_sweep: the paper's Figs. 4-6; allan: Fig. 7; bandwidth/linearity: Figs. 3/2",
    )
    operator: str = Field("", max_length=100, description="who runs the campaign (stored in the file; optional)")
    device_serial: str = Field("", max_length=100, description="serial number of the gyroscope under test (optional)")
    notes: str = Field("", max_length=NOTES_MAX_CHARS, description="why this campaign: free text stored in the file")


class DeviceSection(_Section):
    """Nominal constants of the gyroscope and its front end, used to design the loops (paper eq. 5)."""

    f0_hz: float = Field(2200.0, ge=100.0, le=100e3, description="drive = sense resonance frequency, Hz")
    q_factor: float = Field(1.2e6, ge=1e2, le=1e8, description="quality factor (both modes)")
    angular_gain: float = Field(0.8, gt=0.0, le=1.0, description="Bryan angular gain k (dimensionless)")
    sf_nominal_v_per_dps: float = Field(
        0.06, gt=0.0, le=10.0, description="nominal FTR scale factor, V of rate output per deg/s"
    )
    drive_amplitude_vrms: float = Field(
        0.5, gt=0.0, le=5.0, description="AGC setpoint: drive pickoff amplitude R on the drive demod, Vrms"
    )
    drive_voltage_v: float = Field(
        0.05, gt=0.0, le=10.0, description="drive output amplitude that sustains the nominal drive amplitude, V"
    )
    max_forcer_v: float = Field(10.0, gt=0.0, le=10.0, description="forcer voltage limit, V (paper: 10 V)")

    @property
    def tau_s(self) -> float:
        """Energy decay time tau = 2Q/omega, s."""
        return 2.0 * self.q_factor / (2.0 * math.pi * self.f0_hz)


class LoopsSection(_Section):
    """Closed-loop bandwidths (paper: PLL 15 Hz, AGC 0.5 Hz, rate 2 Hz, quadrature 2 Hz)."""

    pll_bandwidth_hz: float = Field(15.0, gt=0.0, le=500.0)
    pll_damping: float = Field(0.707, gt=0.0, le=5.0, description="PLL damping ratio zeta")
    agc_bandwidth_hz: float = Field(0.5, gt=0.0, le=50.0)
    rate_bandwidth_hz: float = Field(2.0, gt=0.0, le=50.0, description="FTR rate-loop bandwidth, Hz")
    quadrature_bandwidth_hz: float = Field(2.0, gt=0.0, le=50.0)
    sense_pi_design: Literal["critically_damped", "zero_on_pole"] = Field(
        "critically_damped",
        description="the sense axis's two PIs (FTR rate and quadrature): critically_damped puts both closed-loop "
        "poles at -p, p = 2 pi f_bw / sqrt(3 + sqrt 10), -3 dB at the loop's bandwidth, no slow mode left after a "
        "table step (2 % settling 1.1 s at 2 Hz); zero_on_pole cancels the envelope pole 1/tau (first order, "
        "0.31 s settling) and leaves a mismatch's slow mode (tau = 2Q/omega) in the rate output (campaign/loops.py)",
    )
    rate_zero_offset_hz: float = Field(
        0.0,
        ge=0.0,
        le=5.0,
        description="with sense_pi_design = zero_on_pole: the rate PI's zero this far above 1/tau, Hz",
    )
    agc_zero_offset_hz: float = Field(
        0.05,
        ge=0.0,
        le=5.0,
        description="AGC PI zero this far above 1/tau, Hz: on the pole, the drive amplitude (and the SF) would "
        "recover from each table step's Coriolis disturbance with tau = 174 s",
    )
    lock_timeout_s: float = Field(60.0, gt=0.0, le=3600.0, description="how long to wait for PLL lock and settling")
    lock_settle_s: float = Field(10.0, ge=0.0, le=3600.0, description="time all loops must stay locked before the run")


class DitherSection(_Section):
    """The CLSF virtual rate: a square wave from the DS345 added to the FTR command."""

    frequency_hz: float = Field(7.0, gt=0.0, le=100.0, description="dither (virtual-rate) frequency, Hz")
    virtual_rate_dps: float = Field(
        5.0, gt=0.0, le=100.0, description="virtual-rate amplitude (deg/s); DS345 amplitude = 2*this*SF Vpp"
    )


class ClsfSection(_Section):
    """Host-side closed-loop scale factor estimator and gain controller."""

    mode: Literal["observe", "correct", "off"] = Field("observe")
    time_constant_s: float = Field(60.0, gt=0.0, le=1e5, description="correct mode: CLSF loop time constant, s")
    hold_s: float = Field(1.0, ge=0.0, le=60.0, description="hold updates this long around commanded table moves, s")
    reference_periods: int = Field(
        50, ge=1, le=100000, description="dither periods averaged to form the reference level D0 at the start"
    )


class PlanSection(_Section):
    """The steps: chamber program and table rates. Times in s, temperatures in deg C, rates in deg/s."""

    chamber_start_c: float = Field(25.0, json_schema_extra=_limited_by("chamber.min_c", "chamber.max_c"))
    chamber_end_c: float = Field(35.0, json_schema_extra=_limited_by("chamber.min_c", "chamber.max_c"))
    chamber_ramp_c_per_min: float = Field(0.25, gt=0.0, json_schema_extra=_limited_by("chamber.max_ramp_c_per_min"))
    chamber_soak_s: float = Field(300.0, ge=0.0, le=86400.0, description="hold at the start temperature first")
    chamber_end_hold_s: float = Field(
        600.0, ge=0.0, le=86400.0, description="keep stepping this long after the ramp ends (the gyro lags the air)"
    )
    chamber_band_c: float = Field(
        2.0, gt=0.0, le=50.0, description="suspend the campaign while |T - setpoint| exceeds this, deg C"
    )
    table_rate_dps: float = Field(
        5.0,
        ge=0.0,
        json_schema_extra=_limited_by("table.max_rate_dps"),
        description="magnitude of the alternating table rates",
    )
    table_accel_dps2: float = Field(300.0, gt=0.0, json_schema_extra=_limited_by("table.max_accel_dps2"))
    dwell_s: float = Field(60.0, gt=0.0, le=86400.0, description="time at each table rate, settle included")
    settle_s: float = Field(5.0, ge=0.0, le=3600.0, description="start of each dwell excluded from analysis")
    duration_s: float = Field(
        10800.0, gt=0.0, le=30 * 86400.0, description="allan campaign: total logging time at constant temperature"
    )
    table_step_interval_s: float = Field(
        0.0, ge=0.0, le=86400.0, description="allan campaign: a +-rate pair every this many s (0 = table at rest)"
    )
    # characterization
    bandwidth_frequencies_hz: list[PositiveFloat] = Field(
        default_factory=lambda: [0.2, 0.5, 1.0, 1.5, 2.0, 3.0, 5.0],
        description="bandwidth: sinusoidal table-rate frequencies, Hz",
    )
    bandwidth_amplitude_dps: float = Field(5.0, gt=0.0, json_schema_extra=_limited_by("table.max_rate_dps"))
    bandwidth_cycles: int = Field(10, ge=2, le=10000)
    linearity_rates_dps: list[FiniteFloat] = Field(
        default_factory=lambda: [-5.0, -4.0, -3.0, -2.0, -1.0, 0.0, 1.0, 2.0, 3.0, 4.0, 5.0],
        json_schema_extra=_limited_by("table.max_rate_dps"),
    )

    @model_validator(mode="after")
    def _settle_inside_dwell(self) -> PlanSection:
        if self.settle_s >= self.dwell_s:
            raise ValueError(f"plan.settle_s ({self.settle_s}) must be shorter than plan.dwell_s ({self.dwell_s})")
        return self


class LockInSection(_Section):
    """Zurich Instruments HF2LI: data server address, device, demodulator stream and wiring."""

    sim: bool = Field(False, description="use the HF2 twin instead of a data server")
    host: str = Field("localhost", min_length=1)
    port: int = Field(8005, ge=1, le=65535, description="HF2 data server port (HF2: 8005)")
    device: str = Field("dev0", pattern=r"^dev\d+$", description="device id, e.g. dev1234")
    demod_rate_hz: float = Field(
        1800.0,
        ge=200.0,
        le=28800.0,
        description="demodulator streaming rate, Sa/s; the HF2 applies the nearest rate it offers (qmg-lab check "
        "shows it)",
    )
    demod_timeconstant_s: float = Field(
        1e-4,
        gt=0.0,
        le=1e-3,
        description="demodulator filter time constant per stage, s; at most 1 ms so that the filter passes the "
        "dither and adds no more than n tc of lag to the 2 Hz loops",
    )
    demod_order: int = Field(1, ge=1, le=8, description="demodulator filter order (stages of 6 dB/octave)")
    auxin_averaging: int = Field(
        0, ge=0, le=15, description="AuxIn averaging: each AuxIn reading is the mean of 2^n ADC samples"
    )
    poll_interval_s: float = Field(0.5, ge=0.05, le=5.0, description="length of each polled block, s")
    sim_poll_interval_s: float = Field(
        2.0,
        ge=0.05,
        le=10.0,
        description="twin only: block length (the twin needs no real-time buffer; each block costs the host a "
        "fixed overhead, so long blocks run the twins faster, but suspensions and resumes act per block), s",
    )
    drive_sigin: int = Field(0, ge=0, le=1, description="signal input of the drive pickoff (0 = SigIn1)")
    sense_sigin: int = Field(1, ge=0, le=1, description="signal input of the sense pickoff")
    drive_sigout: int = Field(0, ge=0, le=1, description="signal output driving the drive electrodes")
    forcer_sigout: int = Field(1, ge=0, le=1, description="signal output carrying the forcer carrier")
    forcer_carrier_amplitude: float = Field(
        0.5, gt=0.0, le=1.0, description="nominal forcer carrier amplitude (fraction of range) = gain 1.0"
    )
    rate_auxout: int = Field(0, ge=0, le=3, description="AuxOut carrying the rate PID output (cabled to AuxIn1)")
    quadrature_auxout: int = Field(1, ge=0, le=3, description="AuxOut carrying the quadrature PID output")
    rate_auxin: int = Field(0, ge=0, le=1, description="AuxIn recording the rate output")
    dither_auxin: int = Field(1, ge=0, le=1, description="AuxIn recording the DS345 dither")
    output_safe_v: float = Field(0.0, ge=-10.0, le=10.0, description="AuxOut value in the safe state, V")
    drive_mixer_channel: int | None = Field(
        None,
        ge=0,
        le=7,
        description="output mixer channel carrying the drive; unset = from the HF2's options (MF: 0; without MF: "
        "6 on output 1, 7 on output 2)",
    )
    forcer_mixer_channel: int | None = Field(
        None,
        ge=0,
        le=7,
        description="output mixer channel carrying the forcer carrier; unset = from the HF2's options (MF: 1; "
        "without MF: 6 on output 1, 7 on output 2)",
    )
    fixed_channel_oscillators: list[Annotated[int, Field(ge=0, le=5)]] = Field(
        default_factory=lambda: [0, 1],
        min_length=2,
        max_length=2,
        description="oscillator indices (0-based) of output mixer channels 6 and 7, which have no demodulator to "
        "choose one: HF2 user manual, External Reference tutorial (Output 2 runs on oscillator 2); the driver locks "
        "a carrier on an oscillator other than PLL 1's with the PLL that drives it (docs/wiring.md)",
    )
    allow_version_mismatch: bool = Field(
        False,
        description="connect even if the data server's LabOne version differs from the installed zhinst-core "
        "(zhinst-core refuses by default; better: install the matching zhinst-core)",
    )

    @model_validator(mode="after")
    def _distinct_wiring(self) -> LockInSection:
        if self.rate_auxin == self.dither_auxin:
            raise ValueError("lockin.rate_auxin and lockin.dither_auxin must be different AuxIn channels")
        if self.rate_auxout == self.quadrature_auxout:
            raise ValueError("lockin.rate_auxout and lockin.quadrature_auxout must be different AuxOut channels")
        if self.drive_sigin == self.sense_sigin:
            raise ValueError("lockin.drive_sigin and lockin.sense_sigin must be different inputs")
        return self


class GeneratorSection(_Section):
    """SRS DS345 function generator (the dither source), over VISA."""

    sim: bool = Field(False)
    resource: str = Field("GPIB0::19::INSTR", min_length=1, description="VISA resource string")
    visa_backend: str = Field("", description="pyvisa backend: '' default, '@py', or 'file.yaml@sim'")
    timeout_ms: int = Field(2000, ge=10, le=60000)
    max_amplitude_vpp: float = Field(10.0, gt=0.0, le=10.0, description="DS345: 10 Vpp into 50 ohm")


class TableSection(_Section):
    """Ideal Aerosmith 1291BR rate table, over a pyserial URL."""

    sim: bool = Field(False)
    port: str = Field(
        default_factory=lambda: default_serial_port("table"),
        min_length=1,
        description="pyserial URL: COM3, /dev/ttyUSB0, socket://h:p, ...",
        json_schema_extra=_per_os_port("table"),
    )
    baudrate: int = Field(9600, ge=300, le=115200)
    timeout_s: float = Field(1.0, gt=0.0, le=30.0)
    max_rate_dps: float = Field(100.0, gt=0.0, le=1000.0, description="refuse commands above this rate")
    max_accel_dps2: float = Field(500.0, gt=0.0, le=10000.0, description="refuse accelerations above this")
    sim_transport: SimTransport = Field("inprocess", description="twin only: how the driver reaches the twin")
    # framing (unconfirmed for the 1291BR: docs/bench-bringup.md says how to set it from the manual)
    command_terminator: Terminator = Field("CRLF", description="sent after every command: CR, LF or CRLF")
    reply_terminator: ReplyTerminator = Field(
        "auto", description="ends every reply line: auto (CR, LF or CR LF, each accepted), or exactly CR, LF, CRLF"
    )
    prompt: str = Field(
        ">",
        min_length=1,
        max_length=8,
        pattern=r"^[!-~]+$",
        description="the controller's ready prompt after every reply",
    )
    sim_reply_terminator: Terminator = Field("CR", description="twin only: how the twin ends its reply lines")
    servo_enable_command: str = Field(
        "SRV",
        max_length=16,
        pattern=r"^[!-~]*$",
        description="sent once (prompt only) before the first motion of each connection: public Aerosmith code "
        "enables the servo with SRV; '' sends nothing",
    )
    sim_prompt_terminator: Literal["CR", "LF", "CRLF", "none"] = Field(
        "CR", description="twin only: what follows the twin's prompt (none = a bare prompt)"
    )
    # the table's own measure of its motion on the HF2 DIO (assumed wiring: docs/wiring.md, "The table's encoder")
    encoder_on_dio: bool = Field(
        True,
        description="the table's encoder A/B is cabled to the HF2 DIO inputs (false: step windows on host time)",
    )
    encoder_a_dio_bit: int = Field(0, ge=0, le=31, description="HF2 DIO input bit of the encoder's A channel")
    encoder_b_dio_bit: int = Field(1, ge=0, le=31, description="HF2 DIO input bit of the encoder's B channel")
    encoder_lines_per_rev: int = Field(
        3600,
        ge=1,
        le=10**7,
        description="quadrature cycles per table revolution on A/B after the controller's divider (assumed)",
    )

    @model_validator(mode="after")
    def _encoder_bits_differ(self) -> TableSection:
        if self.encoder_a_dio_bit == self.encoder_b_dio_bit:
            raise ValueError("[table] encoder_a_dio_bit and encoder_b_dio_bit must be different DIO bits")
        return self


class ChamberSection(_Section):
    """Thermal chamber controller (Sun Electronic Systems EC1x ASCII protocol), over RS-232 or GPIB."""

    sim: bool = Field(False)
    port: str = Field(
        default_factory=lambda: default_serial_port("chamber"),
        min_length=1,
        description="pyserial URL (COM4, /dev/ttyUSB1, socket://h:p) or, if it contains '::', a VISA resource "
        "(GPIB0::6::INSTR) opened through pyvisa",
        json_schema_extra=_per_os_port("chamber"),
    )
    visa_backend: str = Field("", description="VISA address only: pyvisa backend: '' default, '@py', 'file.yaml@sim'")
    baudrate: int = Field(9600, ge=300, le=115200, description="serial URL only")
    timeout_s: float = Field(1.0, gt=0.0, le=30.0, description="reply timeout, s (also the wait for an OK)")
    setting_ack: Literal["auto", "ok", "none"] = Field(
        "auto",
        description="how settings are acknowledged: auto (an OK if one comes within timeout_s, else confirmed by "
        "reading it back), ok (every setting must answer OK), none (never wait: always read back)",
    )
    min_c: float = Field(-40.0, ge=-100.0, le=200.0, description="lowest setpoint allowed, deg C")
    max_c: float = Field(85.0, ge=-100.0, le=200.0, description="highest setpoint allowed, deg C")
    max_ramp_c_per_min: float = Field(5.0, gt=0.0, le=50.0)
    safe_setpoint_c: float = Field(25.0, ge=-100.0, le=200.0, description="setpoint in the safe state")
    sim_transport: SimTransport = Field("inprocess")
    # framing (unconfirmed for the EC1x: docs/bench-bringup.md says how to set it from the manual)
    command_terminator: Terminator = Field("CRLF", description="sent after every command: CR, LF or CRLF")
    reply_terminator: ReplyTerminator = Field(
        "auto", description="ends every reply line: auto (CR, LF or CR LF, each accepted), or exactly CR, LF, CRLF"
    )
    sim_reply_terminator: Terminator = Field("CRLF", description="twin only: how the twin ends its reply lines")

    @model_validator(mode="after")
    def _limits_ordered(self) -> ChamberSection:
        if self.min_c >= self.max_c:
            raise ValueError(f"chamber.min_c ({self.min_c}) must be below chamber.max_c ({self.max_c})")
        if not self.min_c <= self.safe_setpoint_c <= self.max_c:
            raise ValueError(
                f"chamber.safe_setpoint_c ({self.safe_setpoint_c}) must lie in [{self.min_c}, {self.max_c}]"
            )
        return self


class StorageSection(_Section):
    flush_interval_s: float = Field(1.0, gt=0.0, le=60.0, description="flush the HDF5 file at least this often")
    compression: Literal["auto", "none", "gzip", "lzf"] = Field(
        "auto",
        description="auto = gzip (shuffle + deflate level 1, filters every HDF5 reader has; the compression runs "
        "beside the campaign on the writer thread, on the twins by ISA-L), twins and hardware alike; docs/hdf5.md",
    )

    level: Literal["full", "study"] = Field(
        "full",
        description="full: every stream (/lockin, /truth at the lock-in rate); study: only what `qmg-lab analyze` "
        "needs (/clsf, /steps, /table, /chamber, the per-step /windows and per-period /edges summaries, the raw "
        "stream of the one step the settling time uses), for design studies; docs/hdf5.md",
    )

    def resolved_compression(self, simulated_lockin: bool = False) -> str:
        """The HDF5 filter to use: 'auto' is gzip, on twins and hardware alike (docs/hdf5.md: size and cost)."""
        if self.compression == "auto":
            return "gzip"
        return self.compression


class SimFaultsSection(_Section):
    """Faults the twins inject (reliability testing; docs/reliability.md). Probabilities are per transaction,
    drawn from a generator seeded by sim.seed (the same seed gives the same faults); times are simulated
    seconds of the twins' world clock (a resumed run's world continues where the file ends)."""

    serial_timeout_prob: float = Field(0.0, ge=0.0, le=1.0, description="table/chamber: reply lost (timeout)")
    serial_garble_prob: float = Field(
        0.0, ge=0.0, le=1.0, description="table/chamber: reply garbled (a non-ASCII byte) or truncated (no terminator)"
    )
    visa_timeout_prob: float = Field(0.0, ge=0.0, le=1.0, description="DS345: reply lost (VISA timeout)")
    visa_garble_prob: float = Field(0.0, ge=0.0, le=1.0, description="DS345: reply garbled or truncated")
    disconnect_at_s: list[TimeS] = Field(
        default_factory=list, description="the disconnect_instrument's link drops at these times, s"
    )
    disconnect_duration_s: float = Field(2.0, ge=0.0, le=3600.0, description="how long each drop lasts, s")
    disconnect_instrument: Literal["table", "chamber", "generator"] = Field(
        "table", description="whose link drops (nothing reaches the instrument, nothing comes back)"
    )
    interlock_trip_at_s: float | None = Field(None, ge=0.0, description="the rate table's interlock trips, s")
    chamber_overshoot_at_s: float | None = Field(None, ge=0.0, description="the chamber air overshoots, s")
    chamber_overshoot_c: float = Field(5.0, ge=0.0, le=50.0, description="overshoot peak, deg C")
    chamber_overshoot_decay_s: float = Field(30.0, gt=0.0, le=3600.0, description="overshoot decays as exp(-t/this), s")
    chamber_dropout_at_s: float | None = Field(
        None, ge=0.0, description="the chamber's air sensor drops out (C1? answers ?SENSOR), s"
    )
    chamber_dropout_duration_s: float = Field(5.0, ge=0.0, le=3600.0)
    sample_loss_at_s: list[TimeS] = Field(
        default_factory=list, description="the HF2 stream loses samples in the block at these times, s"
    )
    sample_loss_count: int = Field(100, ge=1, le=100000, description="samples lost at each sample_loss_at_s")
    pll_unlock_at_s: float | None = Field(None, ge=0.0, description="the HF2 PLL is forced open, s")
    pll_unlock_duration_s: float = Field(3.0, ge=0.0, le=3600.0)
    hf2_disconnect_at_s: list[TimeS] = Field(
        default_factory=list,
        description="the HF2's link to the host drops at these times: every data-server call raises zhinst-core's "
        "ConnectionError while the instrument runs on, s",
    )
    hf2_disconnect_duration_s: float = Field(2.0, ge=0.0, le=3600.0, description="how long each HF2 link drop lasts, s")
    hf2_call_timeout_s: float = Field(
        1.0,
        gt=0.0,
        le=60.0,
        description="how long a data-server call on the dropped link takes to fail, s (assumed; a poll: its "
        "recording time)",
    )


class RecoverySection(_Section):
    """What the campaign does when an instrument fails (docs/reliability.md)."""

    reconnect_attempts: int = Field(
        3, ge=0, le=20, description="immediate close/reopen/re-verify attempts before the campaign suspends"
    )
    timeout_s: float = Field(
        30.0,
        ge=0.0,
        le=3600.0,
        description="the campaign keeps logging, suspended, and retries a failed instrument this long, s; then aborts",
    )
    safe_state_timeout_s: float = Field(
        30.0, ge=0.0, le=3600.0, description="on abort, keep retrying an instrument's safe state this long, s"
    )


class SimSection(_Section):
    """Parameters of the simulated test stand (the paper's QMG by default). See docs/simulation.md."""

    seed: int = Field(1, ge=0, le=2**63 - 1)
    f0_hz: float = Field(2200.0, ge=100.0, le=100e3)
    q_factor: float = Field(1.2e6, ge=1e2, le=1e8)
    damping_mismatch: float = Field(0.01, ge=0.0, le=0.5, description="Delta(1/tau)/(1/tau), paper dQ/Q = 1 %")
    damping_axis_deg: float = Field(5.0, ge=-90.0, le=90.0)
    freq_mismatch_hz: float = Field(0.02, ge=0.0, le=10.0, description="mode split at T_ref, Hz (assumed)")
    stiffness_axis_deg: float = Field(20.0, ge=-90.0, le=90.0, description="principal axis of the split (assumed)")
    angular_gain: float = Field(0.8, gt=0.0, le=1.0)
    arw_dps_per_rt_hz: float | None = Field(
        None, ge=0.0, description="override ARW directly in (deg/s)/sqrt(Hz); default from arw_deg_per_rt_h"
    )
    arw_deg_per_rt_h: float = Field(0.02, ge=0.0, le=100.0, description="angle random walk, deg/sqrt(h)")
    bias_instability_deg_per_h: float = Field(0.2, ge=0.0, le=1000.0, description="IEEE 952 B, deg/h")
    pickoff_noise_vrms_per_rt_hz: float = Field(
        2.3e-7,
        ge=0.0,
        le=1e-2,
        description="pickoff voltage noise per demod quadrature, V/sqrt(Hz) (inferred: docs/noise-budget.md)",
    )
    forcer_noise_v_per_rt_hz: float = Field(
        1e-6,
        ge=0.0,
        le=1e-2,
        description="forcer-path voltage noise at the summing node, not recorded by the AuxIns, V/sqrt(Hz) (assumed)",
    )
    auxout_bits: int = Field(16, ge=0, le=32, description="HF2 AuxOut DAC resolution, bits (0 = ideal)")
    auxout_range_v: float = Field(10.0, gt=0.0, le=100.0, description="HF2 AuxOut range, +-V")
    auxin_bits: int = Field(16, ge=0, le=32, description="HF2 AuxIn ADC resolution, bits (0 = ideal)")
    auxin_range_v: float = Field(10.0, gt=0.0, le=100.0, description="HF2 AuxIn range, +-V")
    auxin_noise_v_rms: float = Field(
        1e-4, ge=0.0, le=1.0, description="white noise of one AuxIn reading, V rms (assumed)"
    )
    forcer_tempco_ppm_per_c: float = Field(-1000.0, ge=-1e5, le=1e5, description="forcer gain, what CLSF removes")
    frequency_tempco_ppm_per_c: float = Field(-30.0, ge=-1e4, le=1e4)
    # the pickoff-gain ratio G_py/G_px, what CLSF cannot see, in its physical parts (docs/accuracy-budget.md)
    pickoff_electronics_tempco_ppm_per_c: float = Field(
        40.0,
        ge=-1e4,
        le=1e4,
        description="G_py/G_px drift of the two front ends' gain-setting parts at the front-end board temperature, "
        "ppm/degC (assumed: two class-I C0G capacitors, 0 +- 30 ppm/degC each, bound 60)",
    )
    pickoff_transducer_tempco_ppm_per_c: float = Field(
        20.0,
        ge=-1e4,
        le=1e4,
        description="G_py/G_px drift of the sense and drive electrodes and gaps at the die temperature, ppm/degC "
        "(assumed: the two pickoffs share one die; a residual of asymmetric package stress)",
    )
    pickoff_ratio_tempco2_ppm_per_c2: float = Field(
        0.5,
        ge=-1e3,
        le=1e3,
        description="quadratic part of the G_py/G_px drift at the die temperature, ppm/degC^2 (assumed)",
    )
    frontend_thermal_tau_s: float = Field(
        300.0,
        ge=0.0,
        le=1e5,
        description="the front-end board's first-order lag behind the gyro die temperature, s (assumed: a board "
        "beside the package in the chamber; 0 = at the die temperature)",
    )
    reference_temperature_c: float = Field(25.0, ge=-100.0, le=200.0)
    thermal_lag_s: float = Field(600.0, gt=0.0, le=1e6, description="chamber air -> gyro first-order lag, s")
    chamber_time_constant_s: float = Field(60.0, gt=0.0, le=1e5, description="chamber air -> its setpoint, s")
    initial_temperature_c: float = Field(25.0, ge=-60.0, le=150.0)
    table_rate_scale_error_ppm: float = Field(60.0, ge=-1e4, le=1e4, description="1291BR: 100 ppm rate accuracy")
    # deterministic non-idealities (docs/accuracy-budget.md: origin of each default, what the paper implies)
    table_rate_ripple_ppm: float = Field(
        100.0, ge=0.0, le=1e5, description="1291BR once-per-revolution rate ripple, ppm of the rate (assumed)"
    )
    table_ripple_phase_deg: float = Field(0.0, ge=-360.0, le=360.0, description="table angle of the ripple's peak")
    table_encoder_lines_per_rev: int = Field(
        3600,
        ge=1,
        le=10**7,
        description="the twin table's encoder A/B quadrature cycles per revolution on the DIO (assumed divider)",
    )
    q_tempco_ppm_per_c: float = Field(-2000.0, ge=-1e5, le=1e5, description="dQ/Q per degC (assumed)")
    damping_mismatch_tempco_per_c: float = Field(
        1e-4, ge=-0.01, le=0.01, description="d(Delta(1/tau)/(1/tau))/dT per degC (assumed)"
    )
    freq_mismatch_tempco_hz_per_c: float = Field(
        -0.002, ge=-1.0, le=1.0, description="mode split tempco, Hz/degC (assumed)"
    )
    forcer_bias_v: float = Field(5.0, ge=0.0, le=200.0, description="sense forcer polarization V_p, V (assumed)")
    forcer_gap_um: float = Field(2.0, gt=0.0, le=100.0, description="parallel-plate forcer gap, um (assumed)")
    drive_amplitude_um: float = Field(5.0, gt=0.0, le=100.0, description="physical drive amplitude, um (assumed)")
    forcer_electrode_v_per_v: float = Field(
        1.0, ge=0.0, le=100.0, description="forcer electrode AC amplitude per command volt (paper: 10 V at 150 deg/s)"
    )
    feedthrough_v_per_v: float = Field(
        1e-4, ge=0.0, le=1.0, description="sense pickoff volts per forcer-electrode volt (assumed)"
    )
    feedthrough_phase_deg: float = Field(90.0, ge=-360.0, le=360.0, description="feedthrough phase vs the force")
    hf2_demod_ripple: bool = Field(True, description="carrier model: the demod filter's 2-omega residual")
    loop_delay_us: float = Field(0.0, ge=0.0, le=1e4, description="lock-in loop delay, us")
    ds345_timebase_offset_ppm: float = Field(
        3.0, ge=-1000.0, le=1000.0, description="the DS345's crystal timebase against the HF2's clock, ppm (assumed)"
    )
    ds345_timebase_wander_ppm: float = Field(
        0.5, ge=0.0, le=100.0, description="slow wander of that timebase (sinusoidal amplitude), ppm (assumed)"
    )
    ds345_timebase_wander_period_s: float = Field(3600.0, gt=0.0, le=1e7, description="period of that wander, s")
    ds345_command_latency_s: float = Field(
        0.37e-3, ge=0.0, le=1.0, description="a DS345 setting takes effect this long after the command, s (assumed)"
    )
    hf2_options: list[HF2Option] = Field(
        default_factory=lambda: list(DEFAULT_HF2_OPTIONS),
        description="options of the twin's HF2LI (features/options), any of MF, PLL, PID, MOD; its node tree lists "
        "what such an instrument lists (without MF: 2 oscillators, output mixer channels 6 and 7 only; no plls, "
        "pids, mods branch without PLL, PID, MOD)",
    )
    hf2_timestamp_offset_ticks: int = Field(
        0,
        ge=-1_000_000,
        le=1_000_000,
        description="clockbase ticks the HF2 twin adds to the timestamps of every demodulator but the first (no "
        "source says two HF2 demodulators stamp their samples identically; the driver pairs nearest samples)",
    )
    hf2_rate_set: Literal["hf2", "ticks"] = Field(
        "hf2",
        description="rates the HF2 twin offers: 'hf2' its binary ladder (1800, 3600, ... Sa/s), 'ticks' any "
        "clockbase/integer rate (robustness studies at rates no HF2 offers)",
    )
    drive_voltage_v: float = Field(0.05, gt=0.0, le=10.0, description="true drive voltage at nominal amplitude, V")
    sf_true_v_per_dps: float = Field(0.06, gt=0.0, le=10.0, description="true FTR SF at the reference temperature")
    chamber_status_layout: Literal["ec13", "flags16"] = Field(
        "ec13",
        description="chamber twin's STATUS?: ec13 = 18 Y/N flags + self-test digit (public EC13 driver), flags16",
    )
    chamber_self_test: int = Field(0, ge=0, le=9, description="chamber twin's self-test digit (ec13 layout)")
    chamber_acknowledges_settings: bool = Field(
        True, description="chamber twin answers OK to settings (false: it answers nothing, as an EC13 on GPIB)"
    )
    chamber_powered_at_start: bool = Field(
        True, description="chamber twin's power at start (false: off, the usual morning state, until ON)"
    )
    chamber_set_query_while_off: Literal["held", "target"] = Field(
        "held",
        description="chamber twin's SET? while the power is off: held = the ramping setpoint where it stopped "
        "(it does not ramp without power), target = the last SET= value",
    )
    chamber_silent_commands: int = Field(
        0, ge=0, le=100, description="chamber twin ignores its first N command lines (a controller starting up)"
    )
    table_servo_on_at_start: bool = Field(
        True, description="table twin's servo at power-up (false: JOG/SGO refused, E06, until the servo command)"
    )
    faults: SimFaultsSection = Field(default_factory=SimFaultsSection)

    @model_validator(mode="before")
    @classmethod
    def _retired_pickoff_key(cls, data: Any) -> Any:
        """The single pickoff-ratio coefficient is split into its physical parts; a file that still sets it gets
        a message naming them (a silent mapping would have to guess the split, and the lag depends on it)."""
        if isinstance(data, dict) and "pickoff_ratio_tempco_ppm_per_c" in data:
            raise ValueError(
                "pickoff_ratio_tempco_ppm_per_c is retired: set pickoff_electronics_tempco_ppm_per_c (front-end "
                "board, lagging the die by frontend_thermal_tau_s) and pickoff_transducer_tempco_ppm_per_c (die); "
                "their sum is the old coefficient; pickoff_ratio_tempco2_ppm_per_c2 adds a quadratic part"
            )
        return data

    @model_validator(mode="after")
    def _averaged_model(self) -> SimSection:
        """The twin's averaged model holds for a mode split well below the resonance (docs/physics.md)."""
        if self.freq_mismatch_hz >= 0.1 * self.f0_hz:
            raise ValueError(
                f"freq_mismatch_hz = {self.freq_mismatch_hz:g} must be below 0.1 f0_hz = {0.1 * self.f0_hz:g} Hz "
                "(the averaged model needs the mode split well below the resonance)"
            )
        return self


class Config(_Section):
    """A whole campaign configuration."""

    campaign: CampaignSection = Field(default_factory=CampaignSection)
    device: DeviceSection = Field(default_factory=DeviceSection)
    loops: LoopsSection = Field(default_factory=LoopsSection)
    dither: DitherSection = Field(default_factory=DitherSection)
    clsf: ClsfSection = Field(default_factory=ClsfSection)
    plan: PlanSection = Field(default_factory=PlanSection)
    lockin: LockInSection = Field(default_factory=LockInSection)
    generator: GeneratorSection = Field(default_factory=GeneratorSection)
    table: TableSection = Field(default_factory=TableSection)
    chamber: ChamberSection = Field(default_factory=ChamberSection)
    storage: StorageSection = Field(default_factory=StorageSection)
    recovery: RecoverySection = Field(default_factory=RecoverySection)
    sim: SimSection = Field(default_factory=SimSection)

    @model_validator(mode="after")
    def _cross_checks(self) -> Config:
        problems = plan_limit_problems(self)
        if problems:
            raise ValueError("\n  ".join(problems))
        too_long = plan_size_problem(self)
        if too_long:
            raise ValueError(too_long)
        if self.dither.frequency_hz > self.lockin.demod_rate_hz / 20:
            raise ValueError(
                f"dither.frequency_hz ({self.dither.frequency_hz}) needs at least 20 demod samples per period: "
                f"at most lockin.demod_rate_hz/20 = {self.lockin.demod_rate_hz / 20:g} Hz"
            )
        if self.storage.level == "study" and self.campaign.kind == "bandwidth":
            raise ValueError(
                'storage.level = "study" keeps no raw lock-in stream, which the bandwidth campaign\'s Bode fits '
                'need: use storage.level = "full" for campaign.kind = "bandwidth"'
            )
        if self.loops.rate_zero_offset_hz != 0.0 and self.loops.sense_pi_design != "zero_on_pole":
            raise ValueError(
                f"loops.rate_zero_offset_hz ({self.loops.rate_zero_offset_hz}) places the zero of the "
                'sense_pi_design = "zero_on_pole" PI; the critically damped design (the default) places its own: '
                'set loops.sense_pi_design = "zero_on_pole" or drop rate_zero_offset_hz'
            )
        if self.loops.rate_bandwidth_hz >= self.dither.frequency_hz:
            raise ValueError(
                f"loops.rate_bandwidth_hz ({self.loops.rate_bandwidth_hz}) must be below dither.frequency_hz "
                f"({self.dither.frequency_hz}): the dither has to lie outside the rate-loop bandwidth"
            )
        return self

    def with_all_sim(self, sim: bool = True) -> Config:
        """The same configuration with every instrument set to its twin (the CLI's --sim)."""
        update = {name: getattr(self, name).model_copy(update={"sim": sim}) for name in INSTRUMENT_NAMES}
        return self.model_copy(update=update)

    @property
    def any_sim(self) -> bool:
        return any(getattr(self, n).sim for n in INSTRUMENT_NAMES)

    @property
    def all_sim(self) -> bool:
        return all(getattr(self, n).sim for n in INSTRUMENT_NAMES)

    def instrument_modes(self) -> dict[str, str]:
        """ "twin" | "hardware" per instrument, as the configuration (after --sim) sets them: the one place that
        decides it for the CLI, the study task and the run file's instrument_modes attribute."""
        return {n: ("twin" if getattr(self, n).sim else "hardware") for n in INSTRUMENT_NAMES}


def dither_amplitude_vpp(cfg: Config) -> float:
    """DS345 peak-to-peak amplitude for the virtual rate: Vpp = 2 Omega_v SF (the dither adds to the FTR command)."""
    return 2.0 * cfg.dither.virtual_rate_dps * cfg.device.sf_nominal_v_per_dps


def plan_limit_problems(cfg: Config) -> list[str]:
    """Every [plan] value outside the instrument limit its field names (`_limited_by`), in words."""
    problems = []
    for key, info in PlanSection.model_fields.items():
        extra = info.json_schema_extra
        keys = extra.get("limited_by") if isinstance(extra, dict) else None
        if not isinstance(keys, list):
            continue
        limits = [_value_at(cfg, str(k)) for k in keys]
        low, high = (limits[0], limits[1]) if len(limits) == 2 else (-limits[0], limits[0])
        value = getattr(cfg.plan, key)
        bad = [v for v in (value if isinstance(value, list) else [value]) if not low <= v <= high]
        if not bad:
            continue
        if len(keys) == 2:
            limit = f"outside [{low:g}, {high:g}] ({keys[0]}, {keys[1]})"
        else:
            limit = f"above {keys[0]} = {high:g} in magnitude"
        problems.append(
            f"plan.{key} = {bad[0]:g} is {limit}: change it, or the limit if the instrument allows more "
            "(qmg-lab check shows every limit)"
        )
    return problems


MAX_PLAN_STEPS = 100_000  # a 30-day Allan campaign in 600 s segments has 4320 steps; the paper's sweep 50
ALLAN_SEGMENT_S = 600.0  # checkpoint granularity of a long constant-temperature hold (qmg_lab/campaign/plan.py)


def plan_step_bound(cfg: Config) -> float:
    """An upper bound of the number of steps qmg_lab/campaign/plan.py's build_plan makes, formed without building
    them (a float: inf for absurd values): lock, dither, soak and return, plus per kind
    temperature_sweep 2 ceil((ramp time + end hold) / (2 dwell)); allan, per hold segment or step interval (each
    at least max(interval, 2 dwell) long), a hold, two rate steps and a return; bandwidth 2 + one per frequency;
    linearity one per rate."""
    p, kind = cfg.plan, cfg.campaign.kind
    fixed = 4.0
    if kind == "temperature_sweep":
        ramp_s = abs(p.chamber_end_c - p.chamber_start_c) / p.chamber_ramp_c_per_min * 60.0
        return fixed + 2.0 * ((ramp_s + p.chamber_end_hold_s) / (2.0 * p.dwell_s) + 1.0)
    if kind == "allan":
        if p.table_step_interval_s > 0:
            return fixed + 4.0 * (p.duration_s / max(p.table_step_interval_s, 2.0 * p.dwell_s) + 1.0)
        return fixed + p.duration_s / ALLAN_SEGMENT_S + 1.0
    if kind == "bandwidth":
        return fixed + 2.0 + len(p.bandwidth_frequencies_hz)
    return fixed + len(p.linearity_rates_dps)


def plan_size_problem(cfg: Config) -> str:
    """Why the plan would have more than MAX_PLAN_STEPS steps ("" if it would not): a ramp of 1e-9 degC/min or a
    dwell of a microsecond would otherwise make `check` and `run` build billions of steps, silently."""
    steps = plan_step_bound(cfg)
    if steps <= MAX_PLAN_STEPS:
        return ""
    keys = {
        "temperature_sweep": "plan.chamber_ramp_c_per_min (degC/min), plan.dwell_s (s)",
        "allan": "plan.table_step_interval_s (s), plan.dwell_s (s)",
    }.get(cfg.campaign.kind, "the plan's lists")
    return f"the plan would have up to {steps:.3g} steps, more than {MAX_PLAN_STEPS}: check {keys}"


def _value_at(cfg: Config, dotted: str) -> float:
    section, key = dotted.split(".")
    return float(getattr(getattr(cfg, section), key))


def parse_config(text: str, source: str = "<string>") -> Config:
    """Validate TOML text into a Config; raise ConfigError naming every bad field and its allowed range."""
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{source}: not valid TOML: {toml_syntax_message(text, exc)}") from None
    try:
        return Config.model_validate(data)
    except ValidationError as exc:
        lines = [describe_error(e, Config) for e in exc.errors(include_url=False)]
        raise ConfigError(f"{source}: invalid configuration:\n  " + "\n  ".join(lines)) from None


#: the largest configuration file read, bytes: a campaign's TOML is a few kB; anything larger is not one
CONFIG_MAX_BYTES = 1 << 20


def load_config(path: str | Path) -> tuple[Config, str]:
    """Read and validate a configuration file. Returns the model and the file's text (stored in run files)."""
    p = Path(path)
    try:
        info = p.stat()  # before any open: opening a FIFO waits for a writer, a device may never end
        if stat.S_ISDIR(info.st_mode):
            raise ConfigError(f"{p}: is a directory, not a configuration file")
        if not stat.S_ISREG(info.st_mode):
            raise ConfigError(f"{p}: is not a regular file (a pipe, a device or a socket); give a TOML file")
        if info.st_size > CONFIG_MAX_BYTES:
            raise ConfigError(
                f"{p}: {info.st_size} bytes is not a configuration (at most {CONFIG_MAX_BYTES} bytes); "
                "give the campaign's TOML file"
            )
        with open(p, "rb") as f:
            text = f.read(CONFIG_MAX_BYTES + 1).decode("utf-8")  # no newline translation: TOML allows LF and CRLF
    except FileNotFoundError:
        raise ConfigError(f"{p}: configuration file not found") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"{p}: cannot read configuration: {exc}") from None
    if len(text) > CONFIG_MAX_BYTES:
        raise ConfigError(f"{p}: grew past {CONFIG_MAX_BYTES} bytes while it was read; give the campaign's TOML file")
    return parse_config(text, str(p)), text


def config_fingerprint(text: str) -> str:
    """SHA-256 of the configuration text, hex: the identity `--resume` checks."""
    return hashlib.sha256(text.encode("utf-8")).hexdigest()


def stream_timing_problem(cfg: Config) -> str | None:
    """Why a campaign configuration cannot stream a trustworthy CLSF, or None (qmg_lab/clsf/stream_plan.py).

    The lock-in rate must be one the HF2 offers (unless the twin is told to offer any), and the dither's edges must
    not lock to the sample grid. Checked before a campaign runs (`run`, `check`, `characterize`), not when a
    stored configuration is read back for analysis: files written under other rules stay readable."""
    rate = cfg.lockin.demod_rate_hz
    if not (cfg.lockin.sim and cfg.sim.hf2_rate_set == "ticks"):
        applied = hf2_rate(rate)
        if abs(applied - rate) > 1e-6 * rate:
            rungs = ", ".join(f"{hf2_rate(r):g}" for r in (450, 900, 1800, 3600, 7200))
            return (
                f"lockin.demod_rate_hz = {rate:g} Sa/s is not a rate the HF2 offers (it would stream at "
                f"{applied:g} Sa/s); use one of {rungs} ... Sa/s"
            )
    if cfg.clsf.mode != "off":
        return StreamPlan(
            rate, cfg.dither.frequency_hz, cfg.lockin.demod_order, cfg.lockin.demod_timeconstant_s
        ).problem()
    return None
