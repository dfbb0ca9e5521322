"""Driver for a Sun Electronic Systems EC1x thermal-chamber controller (ASCII protocol) over a pyserial-like port.

Protocol (commands from the public EC1x command set; framing and replies assumed, see docs/instruments.md):

* host -> controller: the command text + CR LF, e.g. ``b"SET=30.00\\r\\n"``, ``b"C1?\\r\\n"``.
* controller -> host: exactly one line per command, assumed to end CR LF; read tolerantly (CR, LF or CR LF,
  blanks around the content) by drivers/serial_link.py, terminators settable through `Framing`. Queries answer
  their value (``b"27.00\\r\\n"``); settings and actions (SET=, RATE=, ON, OFF, LTL=, UTL=) answer ``b"OK\\r\\n"``;
  a refused command answers ``?`` + a reason (``b"?LIMIT\\r\\n"``).
* STATUS? answers at least 9 Y/N flags: char 0 = power (chamber on), char 8 = ramping.
* SET? answers the controller's current setpoint (the ramping one), not the final target.

Sequences: set_setpoint(c, r) = RATE=r, SET=c, ON. read() = C1?, SET?, STATUS?. safe_state() = SET=safe, ON
(the chamber stays on so that it actively goes to the safe setpoint). write_limits() = LTL=min, UTL=max (the
controller's own protection; the station calls it once after identify()).
"""

from __future__ import annotations

import logging
import math
import re
from collections.abc import Callable
from typing import Any, TypeVar

from drivers.serial_link import Framing, SerialLink, SerialPort
from qmg_lab.instruments import ChamberReading, InstrumentError, LimitError, ThermalChamber, check_limit

T = TypeVar("T")

#: the assumed framing: commands end CR LF, replies are read tolerantly (CR, LF or CR LF), no prompt
FRAMING = Framing(command_terminator="CRLF", reply_terminator="auto", prompt="")
ACK = "OK"
ERROR_PREFIX = "?"
SETPOINT_FORMAT = "SET={:.2f}"  # deg C
RATE_FORMAT = "RATE={:.3f}"  # deg C per minute
LOWER_LIMIT_FORMAT = "LTL={:.2f}"  # deg C
UPPER_LIMIT_FORMAT = "UTL={:.2f}"  # deg C
STATUS_POWER_CHAR = 0
STATUS_RAMPING_CHAR = 8
IDENTIFY_QUERY = "STATUS?"  # no identity query is public; STATUS? checks the controller answers in EC1x form

_FLOAT = re.compile(r"^[+-]?\d+(\.\d+)?$")
_FLAGS = re.compile(r"^[YN]{9,32}$")

log = logging.getLogger(__name__)


def parse_temperature(text: str) -> float:
    """C1?/SET?/RATE? reply: a signed decimal number, nothing else."""
    if not _FLOAT.match(text):
        raise ValueError(f"not a decimal number: {text!r}")
    return float(text)


def parse_status(text: str) -> str:
    """STATUS? reply: 9 to 32 characters, each Y or N."""
    if not _FLAGS.match(text):
        raise ValueError(f"not a Y/N status string of at least 9 flags: {text!r}")
    return text


def _as_sent(fmt: str, value: float) -> float:
    """`value` rounded as the command format `fmt` ("NAME={:.Nf}") writes it; non-finite values pass through
    (check_limit names them)."""
    try:
        v = float(value)
    except (TypeError, ValueError) as exc:
        raise LimitError(f"{fmt.split('=', maxsplit=1)[0]} value {value!r} is not a number") from exc
    return float(fmt.format(v).split("=", 1)[1]) if math.isfinite(v) else v


class SunEC1xChamber(ThermalChamber):
    """The thermal chamber.

    port: an open pyserial-like port. min_c/max_c: setpoint limits (deg C); max_ramp_c_per_min: ramp limit;
    safe_setpoint_c: where safe_state() sends the chamber. port_factory: opens a new port for reconnect().
    framing: terminators (default FRAMING).
    """

    NAME = "EC1x chamber"

    def __init__(
        self,
        port: SerialPort,
        *,
        min_c: float,
        max_c: float,
        max_ramp_c_per_min: float,
        safe_setpoint_c: float,
        port_factory: Callable[[], SerialPort] | None = None,
        framing: Framing | None = None,
    ) -> None:
        for name, v in (
            ("min_c", min_c),
            ("max_c", max_c),
            ("max_ramp_c_per_min", max_ramp_c_per_min),
            ("safe_setpoint_c", safe_setpoint_c),
        ):
            if not math.isfinite(v):
                raise ValueError(f"{name} must be a finite number, got {v!r}")
        if min_c >= max_c:
            raise ValueError(f"min_c ({min_c}) must be below max_c ({max_c})")
        if max_ramp_c_per_min <= 0:
            raise ValueError(f"max_ramp_c_per_min must be positive, got {max_ramp_c_per_min}")
        if not min_c <= safe_setpoint_c <= max_c:
            raise ValueError(f"safe_setpoint_c ({safe_setpoint_c}) must lie in [{min_c}, {max_c}]")
        self.min_c, self.max_c = float(min_c), float(max_c)
        self.max_ramp_c_per_min = float(max_ramp_c_per_min)
        self.safe_setpoint_c = float(safe_setpoint_c)
        self.framing = framing or FRAMING
        self._link = SerialLink(port, name=self.NAME, framing=self.framing)
        self._command_end = self.framing.command_end  # the framing is fixed for the driver's life
        self._factory = port_factory
        self._target_c: float | None = None
        self._ramp_c_per_min: float | None = None

    # ------------------------------------------------------------------ transactions
    def _transact(self, text: str) -> str:
        raw = text.encode("ascii") + self._command_end
        self._link.send(raw)
        line = self._link.read_line(raw)
        if line.startswith(ERROR_PREFIX):
            raise InstrumentError(f"{self.NAME}: {text!r} refused: {line!r}")
        return line

    def _command(self, text: str) -> None:
        """A setting or action: the reply must be exactly OK."""
        line = self._transact(text)
        if line != ACK:
            raise InstrumentError(f"{self.NAME}: garbled reply to {text!r}: received {line!r} instead of {ACK!r}")

    def _query(self, text: str, parser: Callable[[str], T]) -> T:
        line = self._transact(text)
        try:
            return parser(line)
        except ValueError as exc:
            raise InstrumentError(f"{self.NAME}: garbled reply to {text!r}: received {line!r} ({exc})") from exc

    # ------------------------------------------------------------------ ThermalChamber
    def set_setpoint(self, setpoint_c: float, ramp_c_per_min: float) -> None:
        """RATE=ramp, SET=setpoint, ON. min_c <= setpoint <= max_c, 0 < ramp <= max_ramp_c_per_min, checked on
        the values as sent (SET= 2 decimals, RATE= 3 decimals)."""
        setpoint_c, ramp_c_per_min = _as_sent(SETPOINT_FORMAT, setpoint_c), _as_sent(RATE_FORMAT, ramp_c_per_min)
        check_limit("chamber setpoint", setpoint_c, self.min_c, self.max_c, "deg C")
        self._check_ramp(ramp_c_per_min)
        self._command(RATE_FORMAT.format(ramp_c_per_min))
        self._command(SETPOINT_FORMAT.format(setpoint_c))
        self._command("ON")
        self._target_c, self._ramp_c_per_min = float(setpoint_c), float(ramp_c_per_min)

    def read(self) -> ChamberReading:
        """C1? (air, deg C), SET? (current ramping setpoint, deg C), STATUS? (char 8 = ramping)."""
        temperature = self._query("C1?", parse_temperature)
        setpoint = self._query("SET?", parse_temperature)
        flags = self._query("STATUS?", parse_status)
        return ChamberReading(temperature_c=temperature, setpoint_c=setpoint, ramping=flags[STATUS_RAMPING_CHAR] == "Y")

    def ramp_rate(self) -> float:
        """RATE?: the controller's ramp rate, deg C/min."""
        return float(self._query("RATE?", parse_temperature))

    def power_on(self) -> bool:
        """STATUS? char 0."""
        return self._query("STATUS?", parse_status)[STATUS_POWER_CHAR] == "Y"

    def write_limits(self) -> None:
        """LTL=min_c, UTL=max_c: the controller refuses setpoints outside them on its own."""
        self._command(LOWER_LIMIT_FORMAT.format(self.min_c))
        self._command(UPPER_LIMIT_FORMAT.format(self.max_c))

    def power_off(self) -> None:
        """OFF: heating and cooling off (the chamber drifts to ambient). Not the safe state."""
        self._command("OFF")

    # ------------------------------------------------------------------ Instrument
    def identify(self) -> str:
        flags = self._query(IDENTIFY_QUERY, parse_status)
        return f"Sun Electronic Systems EC1x (ASCII protocol; STATUS={flags})"

    def state(self) -> dict[str, Any]:
        reading = self.read()
        return {
            "temperature_c": reading.temperature_c,
            "setpoint_c": reading.setpoint_c,
            "ramping": reading.ramping,
            "target_c": self._target_c,
            "ramp_c_per_min": self._ramp_c_per_min,
            "min_c": self.min_c,
            "max_c": self.max_c,
            "safe_setpoint_c": self.safe_setpoint_c,
        }

    def snapshot(self) -> dict[str, Any]:
        """Identity (STATUS? liveness), settings (limits, ramp rate, framing) and state()."""
        return {
            "identity": self.identify(),
            "firmware": None,  # no public EC1x identity query (docs/bench-bringup.md)
            "settings": {
                "min_c": self.min_c,
                "max_c": self.max_c,
                "max_ramp_c_per_min": self.max_ramp_c_per_min,
                "safe_setpoint_c": self.safe_setpoint_c,
                "ramp_c_per_min": self.ramp_rate(),
                "power_on": self.power_on(),
                "framing": {
                    "command_terminator": self.framing.command_terminator,
                    "reply_terminator": self.framing.reply_terminator,
                },
            },
            "state": self.state(),
        }

    def safe_state(self) -> None:
        """SET=safe_setpoint_c, ON: the chamber goes actively to its safe setpoint at the last ramp rate."""
        self._command(SETPOINT_FORMAT.format(self.safe_setpoint_c))
        self._command("ON")
        self._target_c = self.safe_setpoint_c

    def close(self) -> None:
        self._link.close()

    def reconnect(self) -> None:
        """Close, reopen with the factory, identify, write the limits again (LTL=, UTL=: a controller that was
        power-cycled may have lost them), and re-send the last setpoint and ramp (harmless: the controller holds
        them anyway)."""
        log.info("%s: reconnecting", self.NAME)
        self._link.reopen(self._factory)
        self.identify()
        self.write_limits()
        if self._target_c is not None and self._ramp_c_per_min is not None:
            self.set_setpoint(self._target_c, self._ramp_c_per_min)

    def _check_ramp(self, ramp_c_per_min: float) -> None:
        check_limit("chamber ramp", ramp_c_per_min, 0.0, self.max_ramp_c_per_min, "deg C/min")
        if ramp_c_per_min <= 0.0:
            raise LimitError(f"chamber ramp = {ramp_c_per_min:g} deg C/min must be positive")
