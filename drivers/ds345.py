"""SRS DS345 function generator over a VISA message-based resource (the CLSF dither source).

Protocol (docs/instruments.md, DS345 section): 4-letter mnemonics, an optional `?`, arguments; every
message ends with LF. The driver sends one setting per message and follows every setting with `*ESR?`:

    set_square(7, 0.6)  ->  "FUNC 1\\n" "*ESR?\\n" "FREQ 7\\n" "*ESR?\\n"
                            "AMPL 0.6VP\\n" "*ESR?\\n" "OFFS 0\\n" "*ESR?\\n"
    (preceded by one "OFFS?\\n" query while the driver does not yet know the offset, see below)

so a rejected setting is tied to the one command that caused it. Standard event register bits checked:
bit 2 (4) query error, bit 4 (16) execution/range error, bit 5 (32) command error; any of them raises
`InstrumentError` naming the command and the bit. Bit 7 (128, power on) is ignored.

Number formatting (byte for byte, `format_number`): fixed point with a per-quantity number of decimals,
then trailing zeros and a trailing '.' stripped, never an exponent, never "-0":
    FREQ: 6 decimals (1 uHz resolution)   7 -> "7", 7.25 -> "7.25", 1e-6 -> "0.000001", 30.2e6 -> "30200000"
    AMPL: 4 decimals + "VP" (0.1 mVpp)     0.6 -> "0.6VP", 0 -> "0VP", 0.01 -> "0.01VP"
    OFFS: 4 decimals (0.1 mV)              0 -> "0", -1.25 -> "-1.25"
    PHSE: 3 decimals (0.001 deg)
Values are rounded to that resolution first; the limits are checked on the rounded values, i.e. on exactly
what would be sent, and BEFORE anything is sent:
    frequency  1 uHz <= f <= 30.2 MHz (sine and square)
    amplitude  A = 0 (mute, the documented "AMPL 0VP" idiom) or 10 mVpp <= A <= max_amplitude_vpp (<= 10 Vpp)
    offset     |offset| <= 5 V
    |AC peak| + |DC| = A/2 + |offset| <= 5 V          (all levels into 50 ohm, as the DS345 programs them)

Ordering of AMPL and OFFS: the instrument checks A/2 + |offset| <= 5 V after each command, so the driver
orders the two so that every intermediate state is legal: AMPL first if A_new/2 + |offset_old| <= 5 V, else
OFFS first. The driver remembers the offset it set; when it does not know it (first setting after
construction or reconnect, or after a failed OFFS) it first asks "OFFS?" once:
    fresh set_square(7, 0.6) -> "OFFS?\n" (reply), then the eight messages above.
One of the two orders always works: if both failed, A_new/2 + |o_old| + A_old/2 + |o_new| > 10 V, yet the
old and the new state each sum to <= 5 V.

Reply framing. GPIB: every reply ends with LF (and END); pyvisa reads up to LF, as before. RS-232 (an ASRL
resource): the public serial DS345 driver of the Qacam project (DS345.py on its QSerialDevice base, whose
end-of-line is CR) reads RS-232 replies up to CR, while PLACE's serial DS345 driver (automate/SRS/DS345_driver.py)
reads lines to LF and strips the rest; the commands end with LF in both. A driver that waited for LF alone
timed out on every query of a CR-terminated unit, so on a serial resource the driver reads each reply byte by
byte up to the first CR or LF (drivers/line_transport.py, `read_any_line`): replies ending CR, LF or CR LF are
all read (the LF of a CR LF reply is skipped before the next reply). The resource's own read termination is
set to CR there (for the raw console, `qmg-lab generator raw`).
Replies are parsed strictly after stripping surrounding whitespace: FUNC? one digit 0-5; FREQ?/OFFS? a decimal
number; AMPL? a number followed by VP, VR or DB; *ESR? an integer 0-255; *IDN? four comma-separated fields,
the second "DS345".
A reply that does not match raises `InstrumentError` with the command and the bytes received; a VISA timeout
(or any I/O error) raises `InstrumentError` naming the command.

AMPL? in VR (Vrms) or DB (dBm into 50 ohm) is converted to Vpp by the waveform's crest factor:
Vpp = k Vrms with k = 2 sqrt(2) (sine), 2 (square), 2 sqrt(3) (triangle, ramp); dBm: Vrms = sqrt(50 ohm *
1 mW * 10^(dBm/10)). Noise and arbitrary waveforms have no such factor: amplitude_vpp is then None.
"""

from __future__ import annotations

import contextlib
import logging
import math
import numbers
import re
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

from pyvisa.constants import Parity, StatusCode, StopBits
from pyvisa.errors import VisaIOError
from pyvisa.resources import SerialInstrument

from drivers.line_transport import is_serial_resource, read_any_line
from qmg_lab.instruments import FunctionGenerator, InstrumentError, LimitError, check_limit

log = logging.getLogger(__name__)

# ------------------------------------------------------------------------------------------------ protocol data

FUNCTIONS: dict[int, str] = {0: "sine", 1: "square", 2: "triangle", 3: "ramp", 4: "noise", 5: "arbitrary"}
FUNC_SINE = 0
FUNC_SQUARE = 1

ESR_QUERY_ERROR = 2  # bit numbers of the standard event status register
ESR_EXECUTION_ERROR = 4
ESR_COMMAND_ERROR = 5
ESR_ERROR_BITS: dict[int, str] = {
    ESR_QUERY_ERROR: "query error",
    ESR_EXECUTION_ERROR: "execution/range error",
    ESR_COMMAND_ERROR: "command error",
}

FREQ_MIN_HZ = 1e-6
FREQ_MAX_HZ = 30.2e6  # sine and square
AMPL_MIN_VPP = 0.01  # smallest non-zero amplitude; 0 exactly is the mute
AMPL_MAX_VPP = 10.0
OFFSET_MAX_V = 5.0
PEAK_PLUS_OFFSET_MAX_V = 5.0

FREQ_DECIMALS = 6
AMPL_DECIMALS = 4
OFFS_DECIMALS = 4
PHSE_DECIMALS = 3

TERMINATION = "\n"
SERIAL_REPLY_TERMINATION = "\r"  # RS-232 replies (public serial DS345 code reads to CR); any line end is read

_NUMBER = r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?"
_NUMBER_RE = re.compile(rf"^{_NUMBER}$")
_AMPL_RE = re.compile(rf"^({_NUMBER})(VP|VR|DB)$")
_FUNC_RE = re.compile(r"^[0-5]$")
_ESR_RE = re.compile(r"^\d{1,3}$")

_CREST_VPP_PER_VRMS: dict[int, float] = {
    0: 2.0 * math.sqrt(2.0),
    1: 2.0,
    2: 2.0 * math.sqrt(3.0),
    3: 2.0 * math.sqrt(3.0),
}


class VisaLikeResource(Protocol):
    """What the driver needs of a transport: pyvisa's MessageBasedResource, or the twin's resource."""

    timeout: Any
    write_termination: str
    read_termination: str

    def write(self, message: str) -> Any: ...

    def read(self) -> str: ...

    def read_bytes(self, count: int) -> bytes: ...

    def query(self, message: str) -> str: ...

    def close(self) -> None: ...


def format_number(value: float, decimals: int) -> str:
    """Fixed-point text with `decimals` decimals, trailing zeros and '.' stripped, no exponent, no "-0"."""
    text = f"{round(value, decimals):.{decimals}f}"
    if "." in text:
        text = text.rstrip("0").rstrip(".")
    if text in ("-0", ""):
        text = "0"
    return text


def amplitude_to_vpp(value: float, unit: str, function: int) -> float | None:
    """AMPL? reading in VP, VR (Vrms) or DB (dBm into 50 ohm) -> Vpp for the given FUNC (None: no crest factor)."""
    if unit == "VP":
        return value
    crest = _CREST_VPP_PER_VRMS.get(function)
    if crest is None:
        return None
    if unit == "VR":
        return crest * value
    vrms = math.sqrt(50.0 * 1e-3 * 10.0 ** (value / 10.0))
    return crest * vrms


@dataclass(frozen=True)
class Waveform:
    """A complete setting of the generator as the driver last applied it (re-applied after reconnect)."""

    function: int
    frequency_hz: float
    amplitude_vpp: float
    offset_v: float


# ------------------------------------------------------------------------------------------------ driver


class DS345(FunctionGenerator):
    """SRS DS345 on an open VISA-like resource.

    resource: anything with write/read/query/close/timeout (pyvisa MessageBasedResource or the twin's).
    max_amplitude_vpp: the bench's amplitude limit (<= 10 Vpp, the DS345's own maximum into 50 ohm).
    reopen: a callable returning a freshly opened resource, used by `reconnect` (None: cannot reconnect).
    The constructor only sets the resource's terminations (commands LF; replies LF on GPIB, CR on RS-232: see
    the module docstring) and, on a serial resource, the framing (8N2); it sends nothing.
    """

    def __init__(
        self,
        resource: VisaLikeResource,
        max_amplitude_vpp: float = AMPL_MAX_VPP,
        reopen: Callable[[], VisaLikeResource] | None = None,
    ) -> None:
        if not (
            isinstance(max_amplitude_vpp, numbers.Real)
            and math.isfinite(max_amplitude_vpp)
            and AMPL_MIN_VPP <= max_amplitude_vpp <= AMPL_MAX_VPP
        ):
            raise ValueError(
                f"max_amplitude_vpp = {max_amplitude_vpp!r} must lie in "
                f"[{AMPL_MIN_VPP}, {AMPL_MAX_VPP}] Vpp (the DS345's range into 50 ohm)"
            )
        self.max_amplitude_vpp: float = float(max_amplitude_vpp)
        self._reopen: Callable[[], VisaLikeResource] | None = reopen
        self._resource: VisaLikeResource | None = None
        self._attach(resource)
        self._last: Waveform | None = None  # what the instrument was last told (None: nothing yet)
        self._offset_v: float | None = None  # offset last set (None: unknown -> read with OFFS? first)
        self._identity: str | None = None

    # ---------------------------------------------------------------- transport
    def _attach(self, resource: VisaLikeResource) -> None:
        """LF terminations (GPIB); on RS-232 the reply termination CR and the DS345's framing: 8 data bits, no
        parity, 2 stop bits (the baud rate, 300-19200, default 9600, is the resource's: it must match the
        front-panel setting)."""
        resource.write_termination = TERMINATION
        self._serial = is_serial_resource(resource)
        resource.read_termination = SERIAL_REPLY_TERMINATION if self._serial else TERMINATION
        if isinstance(resource, SerialInstrument):
            resource.data_bits = 8
            resource.parity = Parity.none
            resource.stop_bits = StopBits.two
        self._resource = resource

    @property
    def resource(self) -> VisaLikeResource:
        if self._resource is None:
            raise InstrumentError("DS345: the resource is closed")
        return self._resource

    def _write(self, command: str) -> None:
        try:
            self.resource.write(command)
        except InstrumentError:
            raise
        except Exception as exc:  # pyvisa.VisaIOError, OSError, serial errors: all are link faults
            raise InstrumentError(f"DS345: writing {command!r} failed: {exc}") from exc

    def _query(self, command: str) -> str:
        try:
            if self._serial:  # CR, LF or CR LF: read up to the first line end, whatever it is
                self.resource.write(command)
                reply = read_any_line(self.resource)
            else:
                reply = self.resource.query(command)
        except InstrumentError:
            raise
        except UnicodeDecodeError as exc:  # pyvisa decodes replies as ASCII
            raise InstrumentError(f"DS345: garbled reply to {command!r}: {exc.object!r} (not ASCII)") from exc
        except VisaIOError as exc:
            if exc.error_code == StatusCode.error_timeout:
                raise InstrumentError(f"DS345: no reply to {command!r} within the timeout") from exc
            raise InstrumentError(f"DS345: I/O error on {command!r}: {exc}") from exc
        except Exception as exc:  # OSError, serial errors, closed sessions: all are link faults
            raise InstrumentError(f"DS345: I/O error on {command!r} ({type(exc).__name__}: {exc})") from exc
        if not isinstance(reply, str):
            raise InstrumentError(f"DS345: reply to {command!r} is not text: {reply!r}")
        return reply.strip()

    @staticmethod
    def _garbled(command: str, reply: str, expected: str) -> InstrumentError:
        return InstrumentError(
            f"DS345: garbled reply to {command!r}: {reply.encode(errors='replace')!r} (expected {expected})"
        )

    # ---------------------------------------------------------------- status
    def read_esr(self) -> int:
        """*ESR?: the standard event status register (reading clears it on the instrument)."""
        reply = self._query("*ESR?")
        if not _ESR_RE.match(reply) or int(reply) > 255:
            raise self._garbled("*ESR?", reply, "an integer 0-255")
        return int(reply)

    def _command(self, command: str) -> None:
        """Send one setting, then *ESR?; raise InstrumentError naming the command and every error bit set."""
        self._write(command)
        esr = self.read_esr()
        bad = [f"bit {bit} ({name})" for bit, name in ESR_ERROR_BITS.items() if esr & (1 << bit)]
        if bad:
            raise InstrumentError(f"DS345 rejected {command!r}: *ESR? = {esr}, " + ", ".join(bad))

    # ---------------------------------------------------------------- Instrument
    def identify(self) -> str:
        """*IDN? -> "StanfordResearchSystems,DS345,<serial>,<firmware>"; anything else is an error."""
        reply = self._query("*IDN?")
        fields = reply.split(",")
        if len(fields) != 4 or not all(f.strip() for f in fields):
            raise self._garbled("*IDN?", reply, "four comma-separated fields")
        if fields[1].strip() != "DS345":
            raise InstrumentError(f"DS345: *IDN? names model {fields[1].strip()!r}, not DS345 ({reply!r})")
        self._identity = reply
        return reply

    def state(self) -> dict[str, Any]:
        """FUNC?, FREQ?, AMPL?, OFFS? -> {function, function_code, frequency_hz, amplitude, amplitude_unit,
        amplitude_vpp, offset_v}."""
        func_reply = self._query("FUNC?")
        if not _FUNC_RE.match(func_reply):
            raise self._garbled("FUNC?", func_reply, "one digit 0-5")
        function = int(func_reply)
        frequency = self._query_number("FREQ?")
        ampl_reply = self._query("AMPL?")
        m = _AMPL_RE.match(ampl_reply)
        if not m:
            raise self._garbled("AMPL?", ampl_reply, "a number followed by VP, VR or DB")
        amplitude, unit = float(m.group(1)), m.group(2)
        offset = self._query_number("OFFS?")
        return {
            "function": FUNCTIONS[function],
            "function_code": function,
            "frequency_hz": frequency,
            "amplitude": amplitude,
            "amplitude_unit": unit,
            "amplitude_vpp": amplitude_to_vpp(amplitude, unit, function),
            "offset_v": offset,
        }

    def _query_number(self, command: str) -> float:
        reply = self._query(command)
        if not _NUMBER_RE.match(reply):
            raise self._garbled(command, reply, "a decimal number")
        return float(reply)

    def safe_state(self) -> None:
        """The safe state is the mute (AMPL 0VP): idempotent, sends the same two messages every time."""
        self.mute()

    def close(self) -> None:
        """Close the resource (idempotent)."""
        resource, self._resource = self._resource, None
        if resource is not None:
            try:
                resource.close()
            except Exception as exc:
                raise InstrumentError(f"DS345: closing the resource failed: {exc}") from exc

    def reconnect(self) -> None:
        """Close, reopen through the factory, check *IDN? names a DS345 (and the same serial number as
        before, if it was read), clear the status (*CLS), then re-apply the last settings."""
        if self._reopen is None:
            raise InstrumentError("DS345 cannot reconnect: no reopen factory was given")
        log.info("DS345: reconnecting")
        with contextlib.suppress(InstrumentError):  # the old link is gone anyway
            self.close()
        try:
            resource = self._reopen()
        except Exception as exc:
            raise InstrumentError(f"DS345: reopening the resource failed: {exc}") from exc
        self._attach(resource)
        previous = self._identity
        identity = self.identify()
        if previous is not None and previous.split(",")[2].strip() != identity.split(",")[2].strip():
            raise InstrumentError(f"DS345: reconnected to a different unit: {identity!r} (was {previous!r})")
        self._write("*CLS")  # stale error bits (e.g. the query error of a timed-out read) are not news
        self._offset_v = None
        if self._last is not None:
            self._apply(self._last)

    # ---------------------------------------------------------------- FunctionGenerator
    def set_square(self, frequency_hz: float, amplitude_vpp: float, offset_v: float = 0.0) -> None:
        """FUNC 1, FREQ, AMPL ..VP, OFFS (each followed by *ESR?); LimitError before anything is sent."""
        self._apply(self._checked(FUNC_SQUARE, frequency_hz, amplitude_vpp, offset_v))

    def set_sine(self, frequency_hz: float, amplitude_vpp: float, offset_v: float = 0.0) -> None:
        """FUNC 0, FREQ, AMPL ..VP, OFFS (each followed by *ESR?); LimitError before anything is sent."""
        self._apply(self._checked(FUNC_SINE, frequency_hz, amplitude_vpp, offset_v))

    def mute(self) -> None:
        """AMPL 0VP then *ESR? (the DS345 has no output switch). The offset is left as it is."""
        self._command("AMPL 0VP")
        if self._last is not None:
            self._last = Waveform(self._last.function, self._last.frequency_hz, 0.0, self._last.offset_v)

    def set_phase(self, phase_deg: float) -> None:
        """PHSE x (0 <= x <= 7199.999 deg, 0.001 deg resolution) then *ESR?."""
        if not isinstance(phase_deg, numbers.Real) or not math.isfinite(phase_deg):
            raise LimitError(f"DS345 phase = {phase_deg!r} is not a finite number")
        phase = round(float(phase_deg), PHSE_DECIMALS)
        check_limit("DS345 phase", phase, 0.0, 7199.999, "deg")
        self._command(f"PHSE {format_number(phase, PHSE_DECIMALS)}")

    # ---------------------------------------------------------------- internals
    def _checked(self, function: int, frequency_hz: float, amplitude_vpp: float, offset_v: float) -> Waveform:
        """Round to the wire resolution, then check every limit (LimitError names the first one violated)."""
        for name, value in (("frequency", frequency_hz), ("amplitude", amplitude_vpp), ("offset", offset_v)):
            if not isinstance(value, numbers.Real) or not math.isfinite(value):
                raise LimitError(f"DS345 {name} = {value!r} is not a finite number")
        freq = round(float(frequency_hz), FREQ_DECIMALS)
        ampl = round(float(amplitude_vpp), AMPL_DECIMALS)
        offs = round(float(offset_v), OFFS_DECIMALS)
        check_limit("DS345 frequency", freq, FREQ_MIN_HZ, FREQ_MAX_HZ, "Hz")
        if ampl != 0.0:
            check_limit("DS345 amplitude", ampl, AMPL_MIN_VPP, self.max_amplitude_vpp, "Vpp")
        check_limit("DS345 offset", offs, -OFFSET_MAX_V, OFFSET_MAX_V, "V")
        peak = ampl / 2.0 + abs(offs)
        if peak > PEAK_PLUS_OFFSET_MAX_V + 1e-12:
            raise LimitError(
                f"DS345 |AC peak| + |DC| = {ampl / 2:g} + {abs(offs):g} = {peak:g} V exceeds the "
                f"{PEAK_PLUS_OFFSET_MAX_V:g} V limit into 50 ohm"
            )
        return Waveform(function, freq, ampl, offs)

    def _apply(self, w: Waveform) -> None:
        """FUNC, FREQ, then AMPL/OFFS in the order that keeps every intermediate state legal."""
        if self._offset_v is None:
            self._offset_v = self._query_number("OFFS?")
        self._command(f"FUNC {w.function}")
        self._command(f"FREQ {format_number(w.frequency_hz, FREQ_DECIMALS)}")
        ampl_cmd = f"AMPL {format_number(w.amplitude_vpp, AMPL_DECIMALS)}VP"
        offs_cmd = f"OFFS {format_number(w.offset_v, OFFS_DECIMALS)}"
        ampl_first = w.amplitude_vpp / 2 + abs(self._offset_v) <= PEAK_PLUS_OFFSET_MAX_V
        order = (ampl_cmd, offs_cmd) if ampl_first else (offs_cmd, ampl_cmd)
        self._last = w
        for cmd in order:
            try:
                self._command(cmd)
            except InstrumentError:
                if cmd is offs_cmd:
                    self._offset_v = None  # unknown after a failed OFFS
                raise
            if cmd is offs_cmd:
                self._offset_v = w.offset_v
