"""Driver for a Sun Electronic Systems EC1x thermal-chamber controller (ASCII protocol), over RS-232 or GPIB.

Sources. The command set (SET=, SET?, RATE=, RATE?, C1?, ON, OFF, LTL=, UTL=, STATUS?) is the public EC1x set;
what a real EC13 answers is taken from the public Sun EC13 driver in achim1/skippylab
(skippylab/instruments/climate_chambers.py), which talks to its chamber over GPIB (a Prologix or NI adapter):

* STATUS? answers 18 Y/N flags followed by one self-test digit, e.g. ``YNNNYYYNNNNNNNNNNN0``. Flags (0-based):
  0 power on, 1 last command error, 2 time-out LED, 3 waiting for time-out, 4 heat enabled, 5 cool enabled,
  6 valid set temperature, 7 deviation limit exceeded, 8 ramping, 9 below the lower limit, 10 above the upper
  limit, 11-17 program (LP) and GPIB states. Self-test digit: 0 ok, 1 battery RAM error, 2 EE RAM error
  (check default settings), 3 ROM error (call factory).
* That driver writes settings (SET=, RATE=, ON, OFF, HON, ...) without reading any reply.

Assumed (not confirmed by a public source; each settable, docs/bench-bringup.md "where to correct it"):
commands end CR LF (`[chamber] command_terminator`); replies are one line (`reply_terminator`, read tolerantly:
CR, LF or CR LF); a refused command answers ``?`` + a reason; a controller that does acknowledge answers
``OK``; SET? answers the current (ramping) setpoint; shorter STATUS? layouts of 9 to 32 flags (the first
controllers this driver was written for) keep the same meaning of chars 0 and 8.

Transport: the driver speaks through a `LineTransport` (drivers/line_transport.py): a pyserial port
(`SerialLineTransport`) or a VISA resource such as ``GPIB0::6::INSTR`` (`VisaLineTransport`); a pyserial-like
port passed directly is wrapped in a SerialLineTransport with `framing` and `port_factory`.

Settings and their acknowledgement (`ack`, `[chamber] setting_ack`):

* ``"auto"`` (default): after a setting the driver reads one reply line: ``OK`` is the acknowledgement, ``?…``
  a refusal (InstrumentError), anything else garbled (InstrumentError). If nothing comes within the link's
  timeout the controller does not acknowledge settings (as the EC13 above): that is no fault, and the setting
  is confirmed by reading it back (below). Each unacknowledged setting costs one timeout; set ``"none"`` once
  the bench is known not to answer.
* ``"ok"``: every setting must answer OK (a silent controller is a fault).
* ``"none"``: no reply is read; every setting is confirmed by reading it back.

Read-back confirmation: RATE=r -> RATE? equals r (to the 3 decimals sent); LTL=x / UTL=x -> LTL? / UTL?
equal x (2 decimals); ON / OFF -> STATUS? char 0 is Y / N; SET=x -> SET? equals x, or, since SET? reports
the ramping setpoint, STATUS? says ramping (char 8 Y: the controller is on its way to a new target). A
read-back that disagrees raises InstrumentError ("not taken"): a refused setting is still an error, even from a
controller that never answers one. A SET= confirmed only by the ramping flag is watched afterwards: while the
controller ramps toward x, |SET? - x| shrinks at each read(); if it grows by more than two steps of the
setpoint's resolution (0.01 deg C) before the ramp ends at x, the controller is ramping to some earlier target
and read() raises InstrumentError "not taken" (the station's recovery then reconnects and sends the setpoint
again). The watch ends when STATUS? says not ramping with SET? at x.

Self-test digit (STATUS?, when present): 0 passes. 1 and 2 (battery / EE RAM error: the controller's stored
settings may be back at their defaults) are reported, not refused: identify() logs a warning and state() and
the snapshot carry ``self_test`` with its meaning, because every setting qmg-lab relies on (LTL=, UTL=, RATE=,
SET=, ON) is written again by the driver at connect and at each setpoint. 3 (ROM error) and any undocumented
digit are faults (InstrumentError at identify): a controller whose program memory fails its own test cannot be
trusted with the chamber.

Power before setpoint. SET? answers the ramping setpoint, and a controller whose power is off does not ramp: a
SET= sent while the power is off (the usual state of a chamber in the morning) cannot show in SET? nor in the
ramping flag, so it could not be confirmed. The sequences therefore switch the power on first:
set_setpoint(c, r) = RATE=r, ON, SET=c; safe_state() = ON, SET=safe (the chamber stays on so that it actively
goes to the safe setpoint). A SET= read back while STATUS? says the power is off is refused with a message that
says so. Between ON and SET= the controller heads for its stored setpoint for one transaction (milliseconds).
read() = C1?, SET?, STATUS?. write_limits() = LTL=min, UTL=max (the controller's own protection; the station
calls it once after identify()).

First contact. The public EC13 driver reads C1? and STATUS? twice before it reads the STATUS? it uses, "because
sometimes the chamber needs a bit till it is responding". identify() asks STATUS? up to
`first_contact_attempts` times (default FIRST_CONTACT_ATTEMPTS = 4, the four queries of that driver; each silent
attempt costs one link timeout) and takes the first reply in EC1x form; a silent or garbled controller after the
last attempt is an InstrumentError naming every attempt. A refusal (``?...``) is an answer, not silence: it is
not retried.
"""

from __future__ import annotations

import logging
import math
import re
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Literal, TypeVar

from drivers.line_transport import LineTransport, SerialLineTransport
from drivers.serial_link import Framing, ReplyTimeout, SerialPort
from qmg_lab.instruments import ChamberReading, InstrumentError, LimitError, ThermalChamber, check_limit

T = TypeVar("T")
SettingAck = Literal["auto", "ok", "none"]

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
IDENTIFY_QUERY = "STATUS?"  # no identity query is public: STATUS? checks the controller answers in EC1x form
FIRST_CONTACT_ATTEMPTS = 4  # STATUS? queries at first contact: the public EC13 driver's four (module docstring)
SELF_TEST: dict[int, str] = {  # the EC13's self-test digit (achim1/skippylab, climate_chambers.py)
    0: "system self test ok",
    1: "battery RAM error (check default settings)",
    2: "EE RAM error (check default settings)",
    3: "ROM error (call factory)",
}
SELF_TEST_WARNINGS = frozenset({1, 2})  # reported; everything else but 0 is a fault

_FLOAT = re.compile(r"^[+-]?\d+(\.\d+)?$")
_STATUS = re.compile(r"^([YN]{9,32})([0-9]?)$")

log = logging.getLogger(__name__)


class CommandRefused(InstrumentError):
    """The controller answered ``?`` + a reason: it heard the command and refused it."""


@dataclass(frozen=True)
class ChamberStatus:
    """A STATUS? reply: the Y/N flags and the self-test digit (None when the layout has none)."""

    flags: str
    self_test: int | None

    @property
    def power(self) -> bool:
        return self.flags[STATUS_POWER_CHAR] == "Y"

    @property
    def ramping(self) -> bool:
        return self.flags[STATUS_RAMPING_CHAR] == "Y"

    @property
    def text(self) -> str:
        return self.flags + ("" if self.self_test is None else str(self.self_test))


def parse_temperature(text: str) -> float:
    """C1?/SET?/RATE?/LTL?/UTL? reply: a signed decimal number, nothing else."""
    if not _FLOAT.match(text):
        raise ValueError(f"not a decimal number: {text!r}")
    return float(text)


def parse_status(text: str) -> ChamberStatus:
    """STATUS? reply: 9 to 32 Y/N flags, optionally followed by one self-test digit (the EC13: 18 + 1)."""
    m = _STATUS.match(text)
    if m is None:
        raise ValueError(f"not a Y/N status string of 9 to 32 flags and an optional self-test digit: {text!r}")
    return ChamberStatus(flags=m.group(1), self_test=int(m.group(2)) if m.group(2) else None)


def _as_sent(fmt: str, value: float) -> float:
    """`value` rounded as the command format `fmt` ("NAME={:.Nf}") writes it; non-finite values pass through
    (check_limit names them)."""
    try:
        v = float(value)
    except (TypeError, ValueError) as exc:
        raise LimitError(f"{fmt.split('=', maxsplit=1)[0]} value {value!r} is not a number") from exc
    return float(fmt.format(v).split("=", 1)[1]) if math.isfinite(v) else v


def _half_step(fmt: str) -> float:
    """Half the last decimal of a "NAME={:.Nf}" format: how far a read-back may differ from the value sent."""
    decimals = int(fmt.rsplit(".", 1)[1].rstrip("f}"))
    return 0.5 * 10.0**-decimals + 1e-9


class SunEC1xChamber(ThermalChamber):
    """The thermal chamber.

    link: a `LineTransport` (serial or VISA), or an open pyserial-like port (wrapped with `framing` and
    `port_factory`). min_c/max_c: setpoint limits (deg C); max_ramp_c_per_min: ramp limit; safe_setpoint_c:
    where safe_state() sends the chamber. ack: how settings are acknowledged ("auto", "ok", "none": see the
    module docstring). first_contact_attempts: STATUS? queries identify() makes before a silent controller is a
    fault (>= 1).
    """

    NAME = "EC1x chamber"

    def __init__(
        self,
        link: LineTransport | SerialPort,
        *,
        min_c: float,
        max_c: float,
        max_ramp_c_per_min: float,
        safe_setpoint_c: float,
        port_factory: Callable[[], SerialPort] | None = None,
        framing: Framing | None = None,
        ack: SettingAck = "auto",
        first_contact_attempts: int = FIRST_CONTACT_ATTEMPTS,
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
        if ack not in ("auto", "ok", "none"):
            raise ValueError(f"ack must be auto, ok or none, got {ack!r}")
        if int(first_contact_attempts) < 1:
            raise ValueError(f"first_contact_attempts must be at least 1, got {first_contact_attempts!r}")
        self.first_contact_attempts = int(first_contact_attempts)
        self.min_c, self.max_c = float(min_c), float(max_c)
        self.max_ramp_c_per_min = float(max_ramp_c_per_min)
        self.safe_setpoint_c = float(safe_setpoint_c)
        self.ack: SettingAck = ack
        self.framing = framing or FRAMING
        if isinstance(link, LineTransport):
            self._link: LineTransport = link
        else:
            self._link = SerialLineTransport(link, name=self.NAME, framing=self.framing, port_factory=port_factory)
        self._target_c: float | None = None
        self._ramp_c_per_min: float | None = None
        self._self_test: int | None = None
        self._heading: tuple[float, float] | None = None  # (SET= target, |SET? - target| last read): being watched
        self.unacknowledged = 0  # settings confirmed by read-back because no reply came (for the snapshot)

    # ------------------------------------------------------------------ transactions
    def _transact(self, text: str) -> str:
        self._link.send_line(text)
        return self._checked(text, self._link.read_reply(text))

    def _checked(self, text: str, line: str) -> str:
        if line.startswith(ERROR_PREFIX):
            raise CommandRefused(f"{self.NAME}: {text!r} refused: {line!r}")
        return line

    def _command(self, text: str) -> None:
        """A setting or action: acknowledged (OK), refused (?...), or silent and then confirmed by read-back."""
        if text.startswith("SET="):
            self._heading = None  # a new target: the previous one is no longer watched
        self._link.send_line(text)
        if self.ack != "none":
            try:
                line = self._checked(text, self._link.read_reply(text))
            except ReplyTimeout:
                if self.ack == "ok":
                    raise
                line = ""
            if line:
                if line != ACK:
                    raise InstrumentError(
                        f"{self.NAME}: garbled reply to {text!r}: received {line!r} instead of {ACK!r}"
                    )
                return
        self.unacknowledged += 1
        self._confirm(text)

    def _confirm(self, text: str) -> None:
        """Read a setting back (module docstring); InstrumentError if the controller did not take it."""
        if text in ("ON", "OFF"):
            status = self._status()
            if status.power != (text == "ON"):
                raise InstrumentError(f"{self.NAME}: {text!r} not taken: STATUS? = {status.text!r}")
            return
        name, _, value = text.partition("=")
        fmt = {"SET": SETPOINT_FORMAT, "RATE": RATE_FORMAT, "LTL": LOWER_LIMIT_FORMAT, "UTL": UPPER_LIMIT_FORMAT}[name]
        read_back = self._query(f"{name}?", parse_temperature)
        if abs(read_back - float(value)) <= _half_step(fmt):
            return
        if name == "SET":
            status = self._status()
            if status.ramping:  # SET? reports the ramping setpoint: on its way to the new target (watched)
                self._heading = (float(value), abs(read_back - float(value)))
                return
            why = (
                "the power is off (STATUS? char 0 N): SET? holds the ramping setpoint until ON"
                if not status.power
                else "not ramping"
            )
            raise InstrumentError(
                f"{self.NAME}: {text!r} not taken: SET? = {read_back:g} and STATUS? = {status.text!r} ({why})"
            )
        raise InstrumentError(f"{self.NAME}: {text!r} not taken: {name}? = {read_back:g}")

    def _query(self, text: str, parser: Callable[[str], T]) -> T:
        line = self._transact(text)
        try:
            return parser(line)
        except ValueError as exc:
            raise InstrumentError(f"{self.NAME}: garbled reply to {text!r}: received {line!r} ({exc})") from exc

    def _status(self) -> ChamberStatus:
        return self._query("STATUS?", parse_status)

    # ------------------------------------------------------------------ ThermalChamber
    def set_setpoint(self, setpoint_c: float, ramp_c_per_min: float) -> None:
        """RATE=ramp, ON, SET=setpoint (power first: module docstring). min_c <= setpoint <= max_c,
        0 < ramp <= max_ramp_c_per_min, checked on the values as sent (SET= 2 decimals, RATE= 3 decimals)."""
        setpoint_c, ramp_c_per_min = _as_sent(SETPOINT_FORMAT, setpoint_c), _as_sent(RATE_FORMAT, ramp_c_per_min)
        check_limit("chamber setpoint", setpoint_c, self.min_c, self.max_c, "deg C")
        self._check_ramp(ramp_c_per_min)
        self._command(RATE_FORMAT.format(ramp_c_per_min))
        self._command("ON")
        self._command(SETPOINT_FORMAT.format(setpoint_c))
        self._target_c, self._ramp_c_per_min = float(setpoint_c), float(ramp_c_per_min)

    def read(self) -> ChamberReading:
        """C1? (air, deg C), SET? (current ramping setpoint, deg C), STATUS? (char 8 = ramping)."""
        temperature = self._query("C1?", parse_temperature)
        setpoint = self._query("SET?", parse_temperature)
        status = self._status()
        self._watch_heading(setpoint, status.ramping)
        return ChamberReading(temperature_c=temperature, setpoint_c=setpoint, ramping=status.ramping)

    def _watch_heading(self, setpoint_c: float, ramping: bool) -> None:
        """A SET= confirmed by the ramping flag only: the ramping setpoint must keep closing on its target."""
        if self._heading is None:
            return
        target, distance = self._heading
        now = abs(setpoint_c - target)
        step = 2.0 * _half_step(SETPOINT_FORMAT)
        if now > distance + step:
            self._heading = None
            raise InstrumentError(
                f"{self.NAME}: {SETPOINT_FORMAT.format(target)!r} not taken: the ramping setpoint (SET? = "
                f"{setpoint_c:g}) moves away from it (it was {distance:g} deg C from it)"
            )
        self._heading = None if (not ramping and now <= step / 2.0) else (target, min(distance, now))

    def ramp_rate(self) -> float:
        """RATE?: the controller's ramp rate, deg C/min."""
        return float(self._query("RATE?", parse_temperature))

    def power_on(self) -> bool:
        """STATUS? char 0."""
        return self._status().power

    def write_limits(self) -> None:
        """LTL=min_c, UTL=max_c: the controller refuses setpoints outside them on its own."""
        self._command(LOWER_LIMIT_FORMAT.format(self.min_c))
        self._command(UPPER_LIMIT_FORMAT.format(self.max_c))

    def power_off(self) -> None:
        """OFF: heating and cooling off (the chamber drifts to ambient). Not the safe state."""
        self._command("OFF")

    # ------------------------------------------------------------------ Instrument
    def identify(self) -> str:
        """STATUS? in EC1x form, asked up to first_contact_attempts times (module docstring); a failed self-test
        is a fault (3, undocumented) or a warning (1, 2)."""
        status = self._first_status()
        self._self_test = status.self_test
        code = status.self_test
        if code is not None and code != 0:
            meaning = SELF_TEST.get(code, "undocumented self-test code")
            if code not in SELF_TEST_WARNINGS:
                raise InstrumentError(f"{self.NAME}: self-test failed: STATUS? = {status.text!r}: {code} ({meaning})")
            log.warning(
                "%s: self-test reports %d (%s); qmg-lab rewrites the settings it uses", self.NAME, code, meaning
            )
        test = "" if code is None else f"; self-test {code} ({SELF_TEST.get(code, 'undocumented')})"
        return f"Sun Electronic Systems EC1x (ASCII protocol; STATUS={status.text}{test})"

    def _first_status(self) -> ChamberStatus:
        """STATUS? until a reply in EC1x form, at most first_contact_attempts times (silent or garbled: again)."""
        failures: list[str] = []
        for attempt in range(1, self.first_contact_attempts + 1):
            try:
                return self._status()
            except CommandRefused:
                raise
            except InstrumentError as exc:
                failures.append(f"{attempt}: {exc}")
                log.info("%s: first contact, STATUS? attempt %d failed: %s", self.NAME, attempt, exc)
        raise InstrumentError(
            f"{self.NAME}: no STATUS? reply in EC1x form after {self.first_contact_attempts} attempts ("
            + "; ".join(failures)
            + ")"
        )

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
            "self_test": self._self_test,
            "self_test_meaning": None if self._self_test is None else SELF_TEST.get(self._self_test, "undocumented"),
        }

    def snapshot(self) -> dict[str, Any]:
        """Identity (STATUS? liveness), settings (limits, ramp rate, link and acknowledgement) and state()."""
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
                "setting_ack": self.ack,
                "settings_confirmed_by_read_back": self.unacknowledged,
                "framing": self._link.describe(),
            },
            "state": self.state(),
        }

    def safe_state(self) -> None:
        """ON, SET=safe_setpoint_c: the chamber goes actively to its safe setpoint at the last ramp rate."""
        self._command("ON")
        self._command(SETPOINT_FORMAT.format(self.safe_setpoint_c))
        self._target_c = self.safe_setpoint_c

    def close(self) -> None:
        self._link.close()

    def reconnect(self) -> None:
        """Close, reopen, identify, write the limits again (LTL=, UTL=: a controller that was power-cycled may
        have lost them), and re-send the last setpoint and ramp (harmless: the controller holds them anyway)."""
        log.info("%s: reconnecting", self.NAME)
        self._link.reopen()
        self.identify()
        self.write_limits()
        if self._target_c is not None and self._ramp_c_per_min is not None:
            self.set_setpoint(self._target_c, self._ramp_c_per_min)

    def _check_ramp(self, ramp_c_per_min: float) -> None:
        check_limit("chamber ramp", ramp_c_per_min, 0.0, self.max_ramp_c_per_min, "deg C/min")
        if ramp_c_per_min <= 0.0:
            raise LimitError(f"chamber ramp = {ramp_c_per_min:g} deg C/min must be positive")
