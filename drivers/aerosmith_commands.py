"""The Ideal Aerosmith 1291BR remote command table, kept as data.

The 1291BR manual is not public. Everything below follows the 3-letter mnemonic set that independent open-source
drivers for Ideal Aerosmith tables use (docs/instruments.md) plus the assumptions written in each
entry's `assumption` and in docs/instruments.md. To correct the protocol from the real manual, edit this module
only: the driver (drivers/aerosmith.py) takes mnemonics, number formats, reply parsers and status bits from here.

Framing (assumed; the defaults of FRAMING, each settable in [table] of the configuration):

* host -> table: ``<MNE><value>`` + CR LF, the value written right after the mnemonic, no space,
  e.g. ``b"JOG5.000000\\r\\n"``.
* table -> host: zero or one reply line (``b"5.000300\\r"``), then the prompt ``>``. Settings and actions answer
  the prompt only; queries answer their value line, then the prompt. The reply terminator is read tolerantly
  (CR, LF or CR LF; the prompt with or without its terminator; blanks around the content): see
  drivers/serial_link.py.
* A command the controller refuses answers an error line ``E<nn> <text>`` (two decimal digits, a space, free
  text) ending CR, then the prompt. Error codes: see ERROR_CODES.
"""

from __future__ import annotations

import enum
import math
import re
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from drivers.serial_link import Framing

COMMAND_TERMINATOR = b"\r\n"
PROMPT = ">"
#: the assumed framing: commands end CR LF, replies are read tolerantly, the prompt is ">"
FRAMING = Framing(command_terminator="CRLF", reply_terminator="auto", prompt=PROMPT)
MAX_REPLY_BYTES = 64

ERROR_LINE = re.compile(r"^E(\d{2}) (.*)$")
ERROR_CODES: dict[int, str] = {
    1: "unknown command",
    2: "bad or missing argument",
    3: "argument outside the controller's range",
    4: "interlock tripped: motion refused until reset",
    5: "framing: command not terminated by CR LF",
    6: "servo off: motion refused until the servo is enabled ([table] servo_enable_command)",
}
ERROR_INTERLOCK = 4

_FLOAT = re.compile(r"^[+-]?\d+(\.\d+)?([eE][+-]?\d+)?$")
_INT = re.compile(r"^\d{1,10}$")


class TableStatus(enum.IntFlag):
    """Bits of the STA status integer (assumed; the twin implements the same definition on its own).

    MOVING: |rate| > 0.  AT_RATE: rate mode and the acceleration ramp has reached the commanded rate.
    INTERLOCK: the interlock tripped (the table braked to rest and refuses motion).  SERVO_ON: the axis servo is
    enabled.  SINE: a sinusoidal rate profile (SGO) is running.
    """

    MOVING = 1
    AT_RATE = 2
    INTERLOCK = 4
    SERVO_ON = 8
    SINE = 16


def parse_float(text: str) -> float:
    """A decimal number: optional sign, digits, optional fraction and exponent; nothing else."""
    if not _FLOAT.match(text):
        raise ValueError(f"not a decimal number: {text!r}")
    return float(text)


def parse_status(text: str) -> int:
    """STA reply: an unsigned decimal integer, at most 10 digits."""
    if not _INT.match(text):
        raise ValueError(f"not a status integer: {text!r}")
    return int(text)


def parse_flag(text: str) -> bool:
    """MCO reply: '1' (motion complete) or '0'."""
    if text not in ("0", "1"):
        raise ValueError(f"not a 0/1 flag: {text!r}")
    return text == "1"


@dataclass(frozen=True)
class TableCommand:
    """One remote command: `mnemonic` + the value formatted with `arg_format` (None = no value).

    `reply` parses the reply line (None = the command answers the prompt only). `unit` is the unit of the
    value or of the reply.
    """

    key: str
    mnemonic: str
    arg_format: str | None
    reply: Callable[[str], Any] | None
    unit: str
    assumption: str

    def quantize(self, value: float) -> float:
        """The value the table receives: `value` rounded as `arg_format` writes it (limits are checked on it)."""
        if self.arg_format is None:
            raise ValueError(f"{self.mnemonic} takes no value")
        return float(self.arg_format.format(value)) if math.isfinite(value) else value

    def encode(self, value: float | None = None, terminator: bytes = COMMAND_TERMINATOR) -> bytes:
        """The bytes sent: mnemonic, formatted value, the command terminator (CR LF by default)."""
        if self.arg_format is None:
            if value is not None:
                raise ValueError(f"{self.mnemonic} takes no value")
            return self.mnemonic.encode("ascii") + terminator
        if value is None:
            raise ValueError(f"{self.mnemonic} needs a value ({self.unit})")
        return (self.mnemonic + self.arg_format.format(value)).encode("ascii") + terminator


_TABLE = (
    TableCommand(
        "accel",
        "ACL",
        "{:.3f}",
        None,
        "deg/s^2",
        "acceleration used by the next JOG/STO; positive; answers the prompt only",
    ),
    TableCommand(
        "jog",
        "JOG",
        "{:.6f}",
        None,
        "deg/s",
        "rate mode: ramp to this rate at the ACL acceleration; sign = direction; prompt only",
    ),
    TableCommand(
        "stop",
        "STO",
        None,
        None,
        "",
        "decelerate to rest at the ACL acceleration; accepted while the interlock is tripped",
    ),
    TableCommand("position", "PPO", None, parse_float, "deg", "axis position, wrapped to [0, 360)"),
    TableCommand("velocity", "PVE", None, parse_float, "deg/s", "measured (delivered) axis rate"),
    TableCommand(
        "status",
        "STA",
        None,
        parse_status,
        "",
        "status integer, bits in TableStatus; also the resync query sent after JOG",
    ),
    TableCommand(
        "motion_complete",
        "MCO",
        "{:.3f}",
        parse_flag,
        "deg/s",
        "rate mode: '1' when |rate - command| <= tolerance, '0' otherwise (always '0' in sine mode)",
    ),
    TableCommand(
        "sine_amplitude",
        "AMP",
        "{:.6f}",
        None,
        "deg/s",
        "peak rate of the sinusoid started by SGO (a rate amplitude, not an angle)",
    ),
    TableCommand("sine_frequency", "FRQ", "{:.6f}", None, "Hz", "frequency of the sinusoid started by SGO"),
    TableCommand(
        "sine_go",
        "SGO",
        None,
        None,
        "",
        "start rate(t) = AMP sin(2 pi FRQ t) from now; refused (E03) if AMP*2*pi*FRQ > ACL",
    ),
    TableCommand(
        "identify",
        "STA",
        None,
        parse_status,
        "",
        "no identity query is public: STA is used as the identify/liveness query",
    ),
)

COMMANDS: dict[str, TableCommand] = {c.key: c for c in _TABLE}
