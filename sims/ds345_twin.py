"""Message-level twin of the SRS DS345 function generator, writing its output into the shared World.

The twin parses what the real unit parses (docs/instruments.md, DS345 section): messages end with LF (a
CR before it is ignored), several commands per message separated by ';', each a 4-letter mnemonic (or a
'*' common command), an optional '?', then an argument. Mnemonics are case-insensitive.

    FUNC i | FUNC?       0 sine, 1 square, 2 triangle, 3 ramp, 4 noise, 5 arbitrary
    FREQ x | FREQ?       Hz; 1 uHz..30.2 MHz for sine/square, ..100 kHz for triangle/ramp
    AMPL xU | AMPL? [U]  U = VP (Vpp), VR (Vrms), DB (dBm into 50 ohm); the reply carries the unit, "0.6VP".
                         0 (mute) or 10 mVpp..10 Vpp; |AC peak| + |DC| <= 5 V into 50 ohm
    OFFS x | OFFS?       |x| <= 5 V and Vpp/2 + |x| <= 5 V
    PHSE x | PHSE?       0..7199.999 deg;  PCLR: the present phase becomes phase 0 (output unchanged)
    INVT i | INVT?       0/1: output inverted (shown to the World as +180 deg of phase)
    *IDN? *RST *CLS *ESR? [bit] *ESE [x] *ESE? *STB? [bit]

Standard event status register (*ESR? reads and clears it; *ESR? i reads and clears bit i):
bit 2 (4) query error: a read found no reply waiting; bit 4 (16) execution error: a value out of range or
not allowed in the present state (the setting is then ignored); bit 5 (32) command error: unknown mnemonic,
missing or malformed argument; bit 7 (128) power on, set when the twin is created.
Status byte (*STB?): bit 4 MAV (a reply waits), bit 5 ESB ((ESR & ESE) != 0), bit 7 set (no command pending).

Amplitude conversion to Vpp: Vpp = c Vrms with the crest factor c = 2 sqrt 2 (sine), 2 (square), 2 sqrt 3
(triangle, ramp); DB is dBm into 50 ohm: Vrms = sqrt(50 ohm * 1 mW * 10^(dBm/10)). Noise and arbitrary
accept VP only.

The World receives every accepted change through world.set_dither(function, frequency_hz, amplitude_vpp,
offset_v, phase_deg). Noise and arbitrary waveforms are not simulated: the World then sees amplitude 0
(offset only). Levels are those the DS345 programs (into 50 ohm); the World gets them unchanged.

Power-on: the real DS345 recalls its last settings; the twin takes them from the World's dither state, so
creating a twin does not change what the World outputs. *RST gives the factory defaults: sine, 1 kHz, 1 Vpp,
0 V offset, 0 deg, not inverted.

Fault hook: `reply_hook(framed_reply) -> bytes | None` sees every reply with its LF before it is queued;
return it unchanged, altered (garbled, truncated: a reply without its LF makes the reader time out) or None
(dropped: the read times out). This is where fault injection plugs in.
"""

from __future__ import annotations

import math
import re
import threading
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import ClassVar

import pyvisa.constants
import pyvisa.errors

from sims.visa_resource import VisaLikeResource
from sims.world import World

ESR_QUERY = 1 << 2
ESR_EXECUTION = 1 << 4
ESR_COMMAND = 1 << 5
ESR_POWER_ON = 1 << 7
STB_MAV = 1 << 4
STB_ESB = 1 << 5
STB_IDLE = 1 << 7

FREQ_MIN_HZ = 1e-6
FREQ_MAX_HZ = {0: 30.2e6, 1: 30.2e6, 2: 100e3, 3: 100e3, 4: 30.2e6, 5: 30.2e6}
AMPL_MIN_VPP = 0.01
AMPL_MAX_VPP = 10.0
OFFS_MAX_V = 5.0
PEAK_MAX_V = 5.0
PHASE_MAX_DEG = 7199.999
CREST = {0: 2.0 * math.sqrt(2.0), 1: 2.0, 2: 2.0 * math.sqrt(3.0), 3: 2.0 * math.sqrt(3.0)}
_EPS = 1e-9

_COMMAND_RE = re.compile(r"^(\*?[A-Z]{3,4})(\?)?\s*(.*)$")
_NUMBER_RE = re.compile(r"^[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?$")
_AMPL_RE = re.compile(r"^([-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?)\s*(VP|VR|DB)$")


class CommandError(Exception):
    """Syntax: unknown command, wrong form, missing or malformed argument (ESR bit 5)."""


class ExecutionError(Exception):
    """Value out of range or not allowed now (ESR bit 4)."""


@dataclass
class DS345Settings:
    function: int = 0
    frequency_hz: float = 1000.0
    amplitude_vpp: float = 1.0
    amplitude_unit: str = "VP"
    offset_v: float = 0.0
    phase_deg: float = 0.0  # displayed phase
    phase_ref_deg: float = 0.0  # World phase of displayed phase 0 (moved by PCLR)
    invert: int = 0


def _number(arg: str) -> float:
    if not _NUMBER_RE.match(arg):
        raise CommandError(f"not a number: {arg!r}")
    return float(arg)


def _integer(arg: str) -> int:
    if not re.fullmatch(r"[-+]?\d+", arg):
        raise CommandError(f"not an integer: {arg!r}")
    return int(arg)


def _fmt(value: float) -> str:
    """Reply number format: up to 10 significant digits, no trailing zeros ("7", "0.6", "1e-06")."""
    text = f"{value:.10g}"
    return "0" if text == "-0" else text


class DS345Twin:
    """The instrument: state, standard event register, reply queue and the coupling to the World."""

    def __init__(self, world: World, serial: str = "00345", firmware: str = "1.04") -> None:
        self.world = world
        self.identity = f"StanfordResearchSystems,DS345,{serial},{firmware}"
        self.lock = threading.RLock()
        d = world.dither
        self.settings = DS345Settings(
            function=d.function if d.function in FREQ_MAX_HZ else 0,
            frequency_hz=d.frequency_hz,
            amplitude_vpp=d.amplitude_vpp,
            offset_v=d.offset_v,
            phase_deg=d.phase_deg,
        )
        self.esr = ESR_POWER_ON
        self.ese = 0
        self.reply_hook: Callable[[bytes], bytes | None] | None = None
        self.log: list[bytes] = []  # every message received (for inspection)
        self._input = bytearray()
        self._output: deque[bytes] = deque()

    # ---------------------------------------------------------------- bytes in / out
    def write_bytes(self, data: bytes) -> None:
        """Receive bytes; every complete LF-terminated message is executed."""
        with self.lock:
            self._input.extend(data)
            while b"\n" in self._input:
                line, _, rest = bytes(self._input).partition(b"\n")
                self._input = bytearray(rest)
                self.log.append(line + b"\n")
                self._execute_line(line)

    def read_message(self) -> bytes | None:
        """The next queued reply (with its LF), or None if none waits (that sets the query-error bit)."""
        with self.lock:
            if not self._output:
                self.esr |= ESR_QUERY
                return None
            return self._output.popleft()

    def clear(self) -> None:
        """Device clear: drop the input and output buffers (settings and registers are kept)."""
        with self.lock:
            self._input.clear()
            self._output.clear()

    def resource(self, resource_name: str = "GPIB0::19::INSTR", reply_end: bytes = b"\n") -> VisaTwinResource:
        """A new VISA-like resource connected to this twin (call again to 'reopen' after close); `reply_end`
        ends every reply on it (LF on GPIB; CR, LF or CR LF to play an RS-232 unit)."""
        return VisaTwinResource(self, resource_name, reply_end)

    def _reply(self, text: str) -> None:
        framed = text.encode("ascii") + b"\n"
        if self.reply_hook is not None:
            hooked = self.reply_hook(framed)
            if hooked is None:
                return
            framed = hooked
        self._output.append(framed)

    # ---------------------------------------------------------------- parsing
    def _execute_line(self, line: bytes) -> None:
        try:
            text = line.decode("ascii")
        except UnicodeDecodeError:
            self.esr |= ESR_COMMAND
            return
        for raw_part in text.split(";"):
            part = raw_part.strip()
            if not part:
                continue
            match = _COMMAND_RE.match(part.upper())
            try:
                if match is None:
                    raise CommandError(f"unparsable command {part!r}")
                mnemonic, query, arg = match.group(1), match.group(2) == "?", match.group(3).strip()
                handler = self._HANDLERS.get(mnemonic)
                if handler is None:
                    raise CommandError(f"unknown command {mnemonic!r}")
                handler(self, query, arg)
            except CommandError:
                self.esr |= ESR_COMMAND
            except ExecutionError:
                self.esr |= ESR_EXECUTION

    @staticmethod
    def _no_arg(arg: str) -> None:
        if arg:
            raise CommandError(f"unexpected argument {arg!r}")

    # ---------------------------------------------------------------- World coupling
    def _push(self) -> None:
        s = self.settings
        simulated = s.function in CREST
        phase = s.phase_ref_deg + s.phase_deg + (180.0 if s.invert else 0.0)
        self.world.set_dither(
            function=s.function,
            frequency_hz=s.frequency_hz,
            amplitude_vpp=s.amplitude_vpp if simulated else 0.0,
            offset_v=s.offset_v,
            phase_deg=phase % 360.0,
        )

    # ---------------------------------------------------------------- commands
    def _func(self, query: bool, arg: str) -> None:
        if query:
            self._no_arg(arg)
            self._reply(str(self.settings.function))
            return
        code = _integer(arg)
        if code not in FREQ_MAX_HZ:
            raise ExecutionError(f"FUNC {code}")
        if self.settings.frequency_hz > FREQ_MAX_HZ[code] * (1 + _EPS):
            raise ExecutionError(f"FUNC {code} at {self.settings.frequency_hz} Hz")
        self.settings.function = code
        self._push()

    def _freq(self, query: bool, arg: str) -> None:
        if query:
            self._no_arg(arg)
            self._reply(_fmt(self.settings.frequency_hz))
            return
        f = _number(arg)
        if not FREQ_MIN_HZ * (1 - _EPS) <= f <= FREQ_MAX_HZ[self.settings.function] * (1 + _EPS):
            raise ExecutionError(f"FREQ {f}")
        self.settings.frequency_hz = f
        self._push()

    def _vpp_per_unit(self, unit: str, value: float) -> float:
        """Vpp for an amplitude in `unit` (VP, VR, DB) under the present function."""
        if unit == "VP":
            return value
        crest = CREST.get(self.settings.function)
        if crest is None:
            raise ExecutionError(f"{unit} amplitude for function {self.settings.function}")
        vrms = value if unit == "VR" else math.sqrt(50.0 * 1e-3 * 10.0 ** (value / 10.0))
        return crest * vrms

    def _in_unit(self, unit: str) -> float:
        vpp = self.settings.amplitude_vpp
        if unit == "VP":
            return vpp
        crest = CREST.get(self.settings.function)
        if crest is None:
            raise ExecutionError(f"AMPL? {unit} for function {self.settings.function}")
        vrms = vpp / crest
        if unit == "VR":
            return vrms
        if vrms <= 0.0:
            raise ExecutionError("AMPL? DB of a muted output")
        return 10.0 * math.log10(vrms * vrms / (50.0 * 1e-3))

    def _ampl(self, query: bool, arg: str) -> None:
        s = self.settings
        if query:
            unit = arg or s.amplitude_unit
            if unit not in ("VP", "VR", "DB"):
                raise CommandError(f"AMPL? {arg!r}")
            self._reply(_fmt(round(self._in_unit(unit), 6)) + unit)
            return
        m = _AMPL_RE.match(arg)
        if m is None:
            raise CommandError(f"AMPL {arg!r}: a number and a unit VP, VR or DB")
        value, unit = float(m.group(1)), m.group(2)
        if unit == "DB" and value < -300:
            raise ExecutionError("AMPL dBm too low")
        vpp = self._vpp_per_unit(unit, value)
        if vpp != 0.0 and not AMPL_MIN_VPP * (1 - _EPS) <= vpp <= AMPL_MAX_VPP * (1 + _EPS):
            raise ExecutionError(f"AMPL {vpp} Vpp")
        if vpp / 2.0 + abs(s.offset_v) > PEAK_MAX_V + _EPS:
            raise ExecutionError(f"AMPL {vpp} Vpp with offset {s.offset_v} V")
        s.amplitude_vpp, s.amplitude_unit = vpp, unit
        self._push()

    def _offs(self, query: bool, arg: str) -> None:
        s = self.settings
        if query:
            self._no_arg(arg)
            self._reply(_fmt(s.offset_v))
            return
        v = _number(arg)
        if abs(v) > OFFS_MAX_V + _EPS or s.amplitude_vpp / 2.0 + abs(v) > PEAK_MAX_V + _EPS:
            raise ExecutionError(f"OFFS {v}")
        s.offset_v = v
        self._push()

    def _phse(self, query: bool, arg: str) -> None:
        s = self.settings
        if query:
            self._no_arg(arg)
            self._reply(_fmt(round(s.phase_deg, 3)))
            return
        p = _number(arg)
        if not 0.0 <= p <= PHASE_MAX_DEG + _EPS:
            raise ExecutionError(f"PHSE {p}")
        s.phase_deg = p
        self._push()

    def _pclr(self, query: bool, arg: str) -> None:
        if query:
            raise CommandError("PCLR has no query form")
        self._no_arg(arg)
        s = self.settings
        s.phase_ref_deg = (s.phase_ref_deg + s.phase_deg) % 360.0
        s.phase_deg = 0.0  # output unchanged: nothing to push

    def _invt(self, query: bool, arg: str) -> None:
        if query:
            self._no_arg(arg)
            self._reply(str(self.settings.invert))
            return
        i = _integer(arg)
        if i not in (0, 1):
            raise ExecutionError(f"INVT {i}")
        self.settings.invert = i
        self._push()

    def _idn(self, query: bool, arg: str) -> None:
        if not query:
            raise CommandError("*IDN has only a query form")
        self._no_arg(arg)
        self._reply(self.identity)

    def _rst(self, query: bool, arg: str) -> None:
        if query:
            raise CommandError("*RST has no query form")
        self._no_arg(arg)
        self.settings = DS345Settings()
        self._push()

    def _cls(self, query: bool, arg: str) -> None:
        if query:
            raise CommandError("*CLS has no query form")
        self._no_arg(arg)
        self.esr = 0

    def _bit_arg(self, arg: str) -> int | None:
        if not arg:
            return None
        bit = _integer(arg)
        if not 0 <= bit <= 7:
            raise ExecutionError(f"bit {bit}")
        return bit

    def _esr(self, query: bool, arg: str) -> None:
        if not query:
            raise CommandError("*ESR has only a query form")
        bit = self._bit_arg(arg)
        if bit is None:
            value, self.esr = self.esr, 0
        else:
            value = (self.esr >> bit) & 1
            self.esr &= ~(1 << bit)
        self._reply(str(value))

    def _ese(self, query: bool, arg: str) -> None:
        if query:
            self._no_arg(arg)
            self._reply(str(self.ese))
            return
        value = _integer(arg)
        if not 0 <= value <= 255:
            raise ExecutionError(f"*ESE {value}")
        self.ese = value

    def _stb(self, query: bool, arg: str) -> None:
        if not query:
            raise CommandError("*STB has only a query form")
        bit = self._bit_arg(arg)
        stb = STB_IDLE | (STB_MAV if self._output else 0) | (STB_ESB if self.esr & self.ese else 0)
        self._reply(str(stb if bit is None else (stb >> bit) & 1))

    _HANDLERS: ClassVar[dict[str, Callable[[DS345Twin, bool, str], None]]] = {
        "FUNC": _func,
        "FREQ": _freq,
        "AMPL": _ampl,
        "OFFS": _offs,
        "PHSE": _phse,
        "PCLR": _pclr,
        "INVT": _invt,
        "*IDN": _idn,
        "*RST": _rst,
        "*CLS": _cls,
        "*ESR": _esr,
        "*ESE": _ese,
        "*STB": _stb,
    }


class VisaTwinResource(VisaLikeResource):
    """A VISA-like resource wired to a DS345Twin: what pyvisa's MessageBasedResource offers a driver.

    write(msg) sends msg + write_termination as ASCII. Every reply reaches the resource with `reply_end` in
    place of the twin's LF (LF by default, as on GPIB; CR or CR LF plays a unit on RS-232). read() returns the
    next reply up to read_termination (removed); with an empty read_termination, one whole reply message.
    read_bytes(n) returns the next n bytes of the reply stream. No reply, or a reply that never reaches the
    terminator, raises pyvisa's VisaIOError(VI_ERROR_TMO) at once: the clock is virtual, the timeout (ms) is
    only recorded. A partial reply stays in the receive buffer, as on a real link, until clear(). A reply that
    is not ASCII raises UnicodeDecodeError, as pyvisa's read does. A closed resource raises pyvisa's
    InvalidSession.
    """

    def __init__(self, twin: DS345Twin, resource_name: str = "GPIB0::19::INSTR", reply_end: bytes = b"\n") -> None:
        if reply_end not in (b"\r", b"\n", b"\r\n"):
            raise ValueError("reply_end must be CR, LF or CR LF")
        super().__init__(resource_name)
        self.twin = twin
        self.reply_end = reply_end

    def write(self, message: str) -> int:
        self._check_open()
        data = (message + (self.write_termination or "")).encode("ascii")
        self.twin.write_bytes(data)
        return len(data)

    def _more(self) -> bool:
        self._rx.extend(self._next_message())
        return True

    def _next_message(self) -> bytes:
        """The twin's next reply as it goes on this wire (its LF replaced by reply_end); timeout if none."""
        message = self.twin.read_message()
        if message is None:
            raise pyvisa.errors.VisaIOError(pyvisa.constants.StatusCode.error_timeout)
        if message.endswith(b"\n"):
            message = message[:-1] + self.reply_end
        return message

    def read(self) -> str:
        self._check_open()
        term = (self.read_termination or "").encode("ascii")
        while True:
            if term and term in self._rx:
                head, _, rest = bytes(self._rx).partition(term)
                self._rx = bytearray(rest)
                return head.decode("ascii")  # like pyvisa: non-ASCII raises UnicodeDecodeError
            message = self._next_message()
            if not term:
                return message.decode("ascii")
            self._rx.extend(message)

    def clear(self) -> None:
        super().clear()
        self.twin.clear()
