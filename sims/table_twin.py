"""Byte-level twin of the Ideal Aerosmith 1291BR rate-table controller.

It plays the instrument: it parses command lines itself (it shares no code with the driver) and reads/writes
the shared `sims.world.World` under `world.lock`. Protocol implemented (documented in docs/instruments.md):

* a command line is ``<MNE><value>`` CR LF (the serial plumbing delivers it without the LF; the CR must be
  there, else E05). Mnemonics are three upper-case letters; the value is a decimal number.
* answer: settings/actions -> ``b">\\r"``; queries -> ``b"<value>\\r>\\r"``; refusals ->
  ``b"E<nn> <text>\\r>\\r"`` with E01 unknown command, E02 bad/missing argument, E03 outside the controller's
  range, E04 interlock tripped, E05 framing.
* framing options (the real framing is unconfirmed; the driver must cope with each): `command_end` (CR LF by
  default; CR or LF), `reply_end` (CR by default; LF or CR LF) ends every reply line, `prompt_end` (CR by
  default; LF, CR LF, or b"" for a bare prompt) follows the prompt ``>``.
* ACL a (0 < a <= max_accel_dps2), JOG r (|r| <= max_rate_dps; world.set_table_rate(r, a)), STO
  (world.stop_table(a)), PVE -> world.table_rate_dps() "%.6f" (the delivered rate, scale error included),
  PPO -> world.table_angle_deg() wrapped to [0, 360) "%.4f", STA -> status integer, MCO tol -> "1" if rate
  mode and |PVE - command| <= tol, AMP A, FRQ f, SGO (world.set_table_sine(A, f); E03 if A 2 pi f > ACL).
* STA bits: 1 moving (profile rate != 0), 2 at rate (rate mode, ramp finished), 4 interlock, 8 servo on,
  16 sinusoid running.
* servo (public Aerosmith code enables it with SRV before motion): SRV or SRV1 switches it on, SRV0 off
  (prompt only). `servo_on` gives its state at power-up (required: the station passes [sim]
  table_servo_on_at_start, whose default lives in the configuration schema only). While it is off, JOG and
  SGO answer E06 SERVO OFF (STO is accepted).
* while world.table.interlock is set, JOG and SGO answer E04 (STO is accepted).
"""

from __future__ import annotations

import math
import re

import numpy as np

from sims.serial_twin import FaultableTwin
from sims.world import World

PROMPT_TEXT = b">"
PROMPT = b">\r"  # the default framing's prompt line
_LINE = re.compile(r"^([A-Z]{3})(.*)$")
_NUMBER = re.compile(r"^[+-]?(\d+(\.\d*)?|\.\d+)([eE][+-]?\d+)?$")

STA_MOVING, STA_AT_RATE, STA_INTERLOCK, STA_SERVO_ON, STA_SINE = 1, 2, 4, 8, 16


class _Refused(Exception):
    def __init__(self, code: int, text: str) -> None:
        super().__init__(text)
        self.code, self.text = code, text


class RateTableTwin(FaultableTwin):
    """The 1291BR controller. max_rate_dps / max_accel_dps2 / max_sine_hz: the controller's own limits."""

    def __init__(
        self,
        world: World,
        *,
        max_rate_dps: float = 1000.0,
        max_accel_dps2: float = 1000.0,
        max_sine_hz: float = 100.0,
        command_end: bytes = b"\r\n",
        reply_end: bytes = b"\r",
        prompt_end: bytes = b"\r",
        servo_on: bool,
    ) -> None:
        if command_end not in (b"\r", b"\n", b"\r\n") or reply_end not in (b"\r", b"\n", b"\r\n"):
            raise ValueError("command_end and reply_end must be CR, LF or CR LF")
        if prompt_end not in (b"", b"\r", b"\n", b"\r\n"):
            raise ValueError("prompt_end must be empty, CR, LF or CR LF")
        self.command_end, self.reply_end = command_end, reply_end
        self.prompt = PROMPT_TEXT + prompt_end
        self._line_tail = reply_end + self.prompt  # what follows a value line
        self.world = world
        self.max_rate_dps = float(max_rate_dps)
        self.max_accel_dps2 = float(max_accel_dps2)
        self.max_sine_hz = float(max_sine_hz)
        with world.lock:
            self._accel = world.table.accel_dps2
        self._amplitude = 0.0
        self._frequency = 0.0
        self.servo_on = bool(servo_on)
        self.commands_seen = 0
        self._handlers = {
            "ACL": self._acl,
            "JOG": self._jog,
            "STO": self._sto,
            "PPO": self._ppo,
            "PVE": self._pve,
            "STA": self._sta,
            "MCO": self._mco,
            "AMP": self._amp,
            "FRQ": self._frq,
            "SGO": self._sgo,
            "SRV": self._srv,
        }

    # ---------------------------------------------------------------- framing
    def execute(self, line: bytes) -> bytes:
        self.commands_seen += 1
        try:
            body = self.command_body(line)
            if body is None:
                raise _Refused(5, "FRAMING")
            try:
                text = body.decode("ascii")
            except UnicodeDecodeError:
                raise _Refused(1, "UNKNOWN COMMAND") from None
            handler = self._handlers.get(text)  # a bare mnemonic (the queries): no argument to split off
            arg = ""
            if handler is None:
                m = _LINE.match(text)
                handler = self._handlers.get(m.group(1)) if m else None
                if m is None or handler is None:
                    raise _Refused(1, "UNKNOWN COMMAND")
                arg = m.group(2)
            with self.world.lock:
                self.world.now()  # wall-clock worlds integrate up to now
                value = handler(arg)
        except _Refused as r:
            return f"E{r.code:02d} {r.text}".encode("ascii") + self.reply_end + self.prompt
        if value is None:
            return self.prompt
        return value.encode("ascii") + self._line_tail

    @staticmethod
    def _number(arg: str) -> float:
        if not _NUMBER.match(arg):
            raise _Refused(2, "BAD ARGUMENT")
        v = float(arg)
        if not math.isfinite(v):
            raise _Refused(2, "BAD ARGUMENT")
        return v

    @staticmethod
    def _no_arg(arg: str) -> None:
        if arg:
            raise _Refused(2, "BAD ARGUMENT")

    # ---------------------------------------------------------------- commands
    def _acl(self, arg: str) -> None:
        a = self._number(arg)
        if not 0.0 < a <= self.max_accel_dps2:
            raise _Refused(3, "RANGE")
        self._accel = a

    def _motion_allowed(self) -> None:
        if self.world.table.interlock:
            raise _Refused(4, "INTERLOCK")
        if not self.servo_on:
            raise _Refused(6, "SERVO OFF")

    def _srv(self, arg: str) -> None:
        if arg not in ("", "0", "1"):
            raise _Refused(2, "BAD ARGUMENT")
        self.servo_on = arg != "0"

    def _jog(self, arg: str) -> None:
        r = self._number(arg)
        if abs(r) > self.max_rate_dps:
            raise _Refused(3, "RANGE")
        self._motion_allowed()
        self.world.set_table_rate(r, self._accel)

    def _sto(self, arg: str) -> None:
        self._no_arg(arg)
        self.world.stop_table(self._accel)

    def _ppo(self, arg: str) -> str:
        self._no_arg(arg)
        text = f"{self.world.table_angle_deg() % 360.0:.4f}"
        return "0.0000" if text == "360.0000" else text

    def _pve(self, arg: str) -> str:
        self._no_arg(arg)
        return f"{self.world.table_rate_dps():.6f}"

    def status(self) -> int:
        """The STA integer from the world's table state (call under world.lock)."""
        tab = self.world.table
        bits = STA_SERVO_ON if self.servo_on else 0
        if tab.rate_dps != 0.0:
            bits |= STA_MOVING
        if tab.mode == "rate" and tab.rate_dps == tab.rate_command_dps:
            bits |= STA_AT_RATE
        if tab.mode == "sine":
            bits |= STA_SINE
        if tab.interlock:
            bits |= STA_INTERLOCK
        return bits

    def _sta(self, arg: str) -> str:
        self._no_arg(arg)
        return str(self.status())

    def _mco(self, arg: str) -> str:
        tol = self._number(arg)
        if tol < 0.0:
            raise _Refused(3, "RANGE")
        tab = self.world.table
        done = tab.mode == "rate" and abs(self.world.table_rate_dps() - tab.rate_command_dps) <= tol
        return "1" if done else "0"

    def _amp(self, arg: str) -> None:
        a = self._number(arg)
        if not 0.0 <= a <= self.max_rate_dps:
            raise _Refused(3, "RANGE")
        self._amplitude = a

    def _frq(self, arg: str) -> None:
        f = self._number(arg)
        if not 0.0 < f <= self.max_sine_hz:
            raise _Refused(3, "RANGE")
        self._frequency = f

    def _sgo(self, arg: str) -> None:
        self._no_arg(arg)
        if self._frequency <= 0.0 or self._amplitude * 2.0 * math.pi * self._frequency > self._accel:
            raise _Refused(3, "RANGE")
        self._motion_allowed()
        self.world.set_table_sine(self._amplitude, self._frequency)


class TableEncoder:
    """The 1291BR's own measure of its motion as it leaves the controller: a TTL quadrature pair (A, B) from its
    angle encoder, `lines_per_rev` quadrature cycles per revolution after the controller's divider, landing on
    HF2 DIO input bits `a_bit` and `b_bit` (docs/wiring.md, "The table's encoder on the DIO").

    Sourced: none of it (the 1291BR manual is not public). Assumed, each a configuration key: that the controller
    offers its encoder as TTL A/B (the usual form of a servo table's position output), the divider
    ([sim] table_encoder_lines_per_rev) and the bits ([table] encoder_a_dio_bit / encoder_b_dio_bit).

    The encoder reads the angle the servo holds. The world's delivered angle theta (sims/world.py) carries the
    once-per-revolution ripple of the rate, r sin(theta + phi_r) (encoder eccentricity: the servo holds the
    encoder's rate); integrated over the turn that is the encoder reading
        theta_e = theta + r (180/pi) cos(theta + phi_r)        deg (first order in r; constant dropped)
    The encoder counts c = floor(theta_e 4 L / 360) (L = lines_per_rev, 4 counts per quadrature cycle) and puts
    c mod 4 on the pair as the Gray sequence (A, B) = 00, 01, 11, 10.
    """

    GRAY = (0b00, 0b01, 0b11, 0b10)  # (A << 1) | B for c mod 4 = 0, 1, 2, 3

    def __init__(self, world: World, *, lines_per_rev: int, a_bit: int, b_bit: int) -> None:
        if lines_per_rev < 1:
            raise ValueError("lines_per_rev must be >= 1")
        if not (0 <= a_bit < 32 and 0 <= b_bit < 32) or a_bit == b_bit:
            raise ValueError("a_bit and b_bit must be two different DIO bits 0-31")
        self.world = world
        self.lines_per_rev, self.a_bit, self.b_bit = int(lines_per_rev), int(a_bit), int(b_bit)

    def counts(self, angle_deg: np.ndarray) -> np.ndarray:
        """Encoder counts at the delivered table angles `angle_deg` (class docstring)."""
        p = self.world.params
        theta = np.asarray(angle_deg, dtype=np.float64)
        r = p.table_rate_ripple_ppm * 1e-6
        theta_e = theta + r * (180.0 / math.pi) * np.cos(np.deg2rad(theta + p.table_ripple_phase_deg))
        return np.floor(theta_e * (4 * self.lines_per_rev / 360.0)).astype(np.int64)

    def dio_word(self, angle_deg: np.ndarray) -> np.ndarray:
        """The DIO input word (uint32) at the angles: A on a_bit, B on b_bit, every other bit 0."""
        gray = np.asarray(self.GRAY, dtype=np.uint32)[np.mod(self.counts(angle_deg), 4)]
        a = (gray >> np.uint32(1)) & np.uint32(1)
        b = gray & np.uint32(1)
        return (a << np.uint32(self.a_bit)) | (b << np.uint32(self.b_bit))
