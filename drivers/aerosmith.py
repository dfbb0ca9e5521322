"""Driver for the Ideal Aerosmith 1291BR single-axis rate table over a pyserial-like port.

Protocol: the command table in drivers/aerosmith_commands.py (mnemonic + value + CR LF; one reply line, then
the prompt ">"; refusals answer "E<nn> text"). The framing (terminators, prompt) is a `Framing`, read tolerantly
by drivers/serial_link.py (replies ending CR, LF or CR LF; the prompt with or without its terminator). The
content of every transaction is checked strictly: the value line must parse, the prompt must follow, nothing
else is accepted; any deviation raises InstrumentError naming the command and the bytes received. Limits are
checked before anything is sent (LimitError).

First contact: public Aerosmith code enables the servo (SRV) before it commands motion; qmg-lab's first
driver never did. With `servo_enable_command` (the station passes `[table] servo_enable_command`, default
"SRV"; None or "" sends nothing) the driver sends that command once per connection (again after a reconnect)
before the first JOG or SGO, and expects the prompt (an error line is raised as for any command). The
command's exact form (bare "SRV", or with an argument) is not confirmed: it is configuration, sent as written.

Sequences:
* set_rate(r, a): [servo command,] ACL a, JOG r, then STA to resynchronise (and to see an interlock at once).
* set_sinusoid(A, f, a): requires the peak acceleration of rate(t) = A sin(2 pi f t), A 2 pi f, to be <= a
  and a <= max_accel; then [servo command,] ACL a, AMP A, FRQ f, SGO, STA.
* stop(): STO, STA.  safe_state(): STO only (idempotent, one transaction).
* read(): PVE, PPO, STA -> TableReading (interlock = STA bit 2).
"""

from __future__ import annotations

import contextlib
import logging
import math
from collections.abc import Callable
from typing import Any

from drivers import aerosmith_commands as proto
from drivers.serial_link import Framing, SerialLink, SerialPort
from qmg_lab.instruments import (
    InstrumentError,
    InterlockError,
    LimitError,
    RateTable,
    TableReading,
    check_limit,
)

MAX_SINE_FREQUENCY_HZ = 100.0

log = logging.getLogger(__name__)


class Aerosmith1291BR(RateTable):
    """The 1291BR rate table.

    port: an open pyserial-like port (9600 8N1 on hardware). max_rate_dps, max_accel_dps2: the station's
    limits (commands beyond them are refused before sending). port_factory: a callable that opens a new port,
    used by reconnect(). framing: terminators and prompt (default proto.FRAMING: commands CR LF, replies
    CR/LF/CR LF, prompt ">"). servo_enable_command: sent before the first motion of each connection (None:
    nothing is sent).
    """

    NAME = "1291BR"

    def __init__(
        self,
        port: SerialPort,
        *,
        max_rate_dps: float,
        max_accel_dps2: float,
        port_factory: Callable[[], SerialPort] | None = None,
        framing: Framing | None = None,
        servo_enable_command: str | None = None,
    ) -> None:
        if servo_enable_command is not None and not (
            servo_enable_command.isascii() and servo_enable_command.isprintable() and " " not in servo_enable_command
        ):
            raise ValueError(
                f"servo_enable_command must be printable ASCII without spaces, got {servo_enable_command!r}"
            )
        self.servo_enable_command = servo_enable_command or None
        self._servo_enabled = False  # sent on this connection?
        if not (math.isfinite(max_rate_dps) and max_rate_dps > 0):
            raise ValueError(f"max_rate_dps must be a positive finite number, got {max_rate_dps!r}")
        if not (math.isfinite(max_accel_dps2) and max_accel_dps2 > 0):
            raise ValueError(f"max_accel_dps2 must be a positive finite number, got {max_accel_dps2!r}")
        self.max_rate_dps = float(max_rate_dps)
        self.max_accel_dps2 = float(max_accel_dps2)
        self.framing = framing or proto.FRAMING
        if not self.framing.prompt:
            raise ValueError("the 1291BR framing needs a prompt (the controller's ready prompt, e.g. '>')")
        self._link = SerialLink(port, name=self.NAME, framing=self.framing, max_reply_bytes=proto.MAX_REPLY_BYTES)
        # the bytes of every command without a value, encoded once (the framing is fixed for the driver's life)
        self._encoded = {
            key: cmd.encode(None, self.framing.command_end) for key, cmd in proto.COMMANDS.items() if not cmd.arg_format
        }
        self._factory = port_factory
        self._mode = "rate"
        self._rate_command_dps = 0.0
        self._accel_dps2: float | None = None
        self._sine: tuple[float, float] | None = None

    # ------------------------------------------------------------------ transactions
    def _transact(self, key: str, value: float | None = None) -> Any:
        """Send one command from the table; return its parsed reply (None for prompt-only commands)."""
        cmd = proto.COMMANDS[key]
        raw = self._encoded.get(key) if value is None else None
        if raw is None:
            raw = cmd.encode(value, self.framing.command_end)
        self._link.send(raw)
        result: Any = None
        line = self._link.read_line(raw)
        if line.startswith("E"):  # every error line does (proto.ERROR_LINE); values and the prompt do not
            self._raise_if_error(raw, line)
        if cmd.reply is not None:
            try:
                result = cmd.reply(line)
            except ValueError as exc:
                raise InstrumentError(
                    f"{self.NAME}: garbled reply to {cmd.mnemonic!r}: received {line!r} ({exc})"
                ) from exc
            try:
                line = self._link.read_line(raw)
            except InstrumentError as exc:
                raise InstrumentError(f"{self.NAME}: missing prompt after {cmd.mnemonic!r}: {exc}") from exc
            if line.startswith("E"):
                self._raise_if_error(raw, line)
        self._expect_prompt(cmd.mnemonic, line)
        return result

    def _expect_prompt(self, command: str, line: str) -> None:
        if line != self.framing.prompt:
            raise InstrumentError(
                f"{self.NAME}: missing prompt after {command!r}: received {line!r} instead of the prompt "
                f"{self.framing.prompt!r}"
            )

    def _enable_servo(self) -> None:
        """The configured servo command, once per connection, before motion (prompt only)."""
        if self.servo_enable_command is None or self._servo_enabled:
            return
        raw = self.servo_enable_command.encode("ascii") + self.framing.command_end
        self._link.send(raw)
        line = self._link.read_line(raw)
        if line.startswith("E"):
            self._raise_if_error(raw, line)
        self._expect_prompt(self.servo_enable_command, line)
        self._servo_enabled = True

    def _raise_if_error(self, raw: bytes, line: str) -> None:
        """InterlockError / InstrumentError if `line` is an error line "E<nn> <text>" (after reading its prompt)."""
        m = proto.ERROR_LINE.match(line)
        if m is None:
            return
        code = int(m.group(1))
        text = raw[: -len(self.framing.command_end)].decode("ascii")
        # the prompt follows the error line; consume it so the link stays in step
        with contextlib.suppress(InstrumentError):
            self._link.read_line(raw)
        meaning = proto.ERROR_CODES.get(code, "undocumented error code")
        exc_type = InterlockError if code == proto.ERROR_INTERLOCK else InstrumentError
        raise exc_type(f"{self.NAME}: {text!r} refused: E{code:02d} {m.group(2)} ({meaning})")

    def _check_interlock(self, status: int, after: str) -> None:
        if status & proto.TableStatus.INTERLOCK:
            raise InterlockError(f"{self.NAME}: interlock tripped (STA={status}) after {after}")

    # ------------------------------------------------------------------ RateTable
    def set_rate(self, rate_dps: float, accel_dps2: float) -> None:
        """ACL accel, JOG rate, STA. |rate| <= max_rate_dps, 0 < accel <= max_accel_dps2."""
        rate_dps, accel_dps2 = self._sent("jog", rate_dps), self._sent("accel", accel_dps2)
        check_limit("table rate", rate_dps, -self.max_rate_dps, self.max_rate_dps, "deg/s")
        self._check_accel(accel_dps2)
        self._enable_servo()
        self._transact("accel", accel_dps2)
        self._transact("jog", rate_dps)
        self._mode, self._rate_command_dps, self._accel_dps2, self._sine = (
            "rate",
            float(rate_dps),
            float(accel_dps2),
            None,
        )
        self._check_interlock(self._transact("status"), "JOG")

    def set_sinusoid(self, amplitude_dps: float, frequency_hz: float, accel_dps2: float) -> None:
        """ACL, AMP, FRQ, SGO, STA for rate(t) = A sin(2 pi f t); needs A * 2 pi f <= accel <= max_accel,
        checked on the values as sent (rounded to the command formats), as the controller will check them."""
        amplitude_dps = self._sent("sine_amplitude", amplitude_dps)
        frequency_hz = self._sent("sine_frequency", frequency_hz)
        accel_dps2 = self._sent("accel", accel_dps2)
        check_limit("sinusoid amplitude", amplitude_dps, 0.0, self.max_rate_dps, "deg/s")
        check_limit("sinusoid frequency", frequency_hz, 0.0, MAX_SINE_FREQUENCY_HZ, "Hz")
        if frequency_hz <= 0.0 or amplitude_dps <= 0.0:
            raise LimitError(
                f"sinusoid amplitude ({amplitude_dps:g} deg/s) and frequency ({frequency_hz:g} Hz) must be positive"
            )
        self._check_accel(accel_dps2)
        peak = amplitude_dps * 2.0 * math.pi * frequency_hz
        if peak > accel_dps2:
            raise LimitError(
                f"sinusoid peak acceleration amplitude*2*pi*frequency = {peak:g} deg/s^2 exceeds the "
                f"acceleration limit {accel_dps2:g} deg/s^2"
            )
        self._enable_servo()
        self._transact("accel", accel_dps2)
        self._transact("sine_amplitude", amplitude_dps)
        self._transact("sine_frequency", frequency_hz)
        self._transact("sine_go")
        self._mode, self._sine, self._accel_dps2 = (
            "sine",
            (float(amplitude_dps), float(frequency_hz)),
            float(accel_dps2),
        )
        self._check_interlock(self._transact("status"), "SGO")

    def stop(self) -> None:
        """STO (decelerate at the last ACL), then STA."""
        self._transact("stop")
        self._mode, self._rate_command_dps, self._sine = "rate", 0.0, None
        self._transact("status")

    def read(self) -> TableReading:
        """PVE (deg/s), PPO (deg, in [0, 360)), STA."""
        rate = self._transact("velocity")
        position = self._transact("position")
        status = self._transact("status")
        return TableReading(
            rate_dps=rate, position_deg=position, status=status, interlock=bool(status & proto.TableStatus.INTERLOCK)
        )

    def motion_complete(self, tolerance_dps: float) -> bool:
        """MCO<tol>: True when the rate is within `tolerance_dps` of the command (rate mode)."""
        check_limit("motion-complete tolerance", tolerance_dps, 0.0, self.max_rate_dps, "deg/s")
        return bool(self._transact("motion_complete", tolerance_dps))

    # ------------------------------------------------------------------ Instrument
    def identify(self) -> str:
        """The public command set has no identity query: STA (assumed) checks that a 1291BR-style controller
        answers with its framing; the identity string says so."""
        status = self._transact("identify")
        return f"Ideal Aerosmith 1291BR (3-letter mnemonic protocol; STA={status})"

    def state(self) -> dict[str, Any]:
        reading = self.read()
        return {
            "mode": self._mode,
            "rate_command_dps": self._rate_command_dps,
            "accel_dps2": self._accel_dps2,
            "sine_amplitude_dps": None if self._sine is None else self._sine[0],
            "sine_frequency_hz": None if self._sine is None else self._sine[1],
            "rate_dps": reading.rate_dps,
            "position_deg": reading.position_deg,
            "status": reading.status,
            "status_bits": [b.name for b in proto.TableStatus if reading.status & b],
            "interlock": reading.interlock,
            "max_rate_dps": self.max_rate_dps,
            "max_accel_dps2": self.max_accel_dps2,
        }

    def snapshot(self) -> dict[str, Any]:
        """Identity (STA liveness), settings (limits, framing, the assumed command table) and state()."""
        return {
            "identity": self.identify(),
            "firmware": None,  # no public 1291BR command reports it (docs/bench-bringup.md)
            "settings": {
                "max_rate_dps": self.max_rate_dps,
                "max_accel_dps2": self.max_accel_dps2,
                "framing": {
                    "command_terminator": self.framing.command_terminator,
                    "reply_terminator": self.framing.reply_terminator,
                    "prompt": self.framing.prompt,
                },
                "commands": {c.key: c.mnemonic for c in proto.COMMANDS.values()},
                "servo_enable_command": self.servo_enable_command,
            },
            "state": self.state(),
        }

    def safe_state(self) -> None:
        """STO: the table decelerates to rest. Idempotent (STO at rest is accepted)."""
        self._transact("stop")
        self._mode, self._rate_command_dps, self._sine = "rate", 0.0, None

    def close(self) -> None:
        self._link.close()

    def reconnect(self) -> None:
        """Close the port, open a new one with the factory, identify. Motion is not re-commanded: the
        controller keeps running its last command across a host link drop (assumed)."""
        log.info("%s: reconnecting", self.NAME)
        self._link.reopen(self._factory)
        self._servo_enabled = False  # a power-cycled controller may have its servo off: sent again before motion
        self.identify()

    # ------------------------------------------------------------------ helpers
    @staticmethod
    def _sent(key: str, value: float) -> float:
        """`value` as the command `key` will carry it (limits are checked on what the table receives)."""
        try:
            return proto.COMMANDS[key].quantize(float(value))
        except (TypeError, ValueError) as exc:
            raise LimitError(f"{proto.COMMANDS[key].mnemonic} value {value!r} is not a number") from exc

    def _check_accel(self, accel_dps2: float) -> None:
        check_limit("table acceleration", accel_dps2, 0.0, self.max_accel_dps2, "deg/s^2")
        if accel_dps2 <= 0.0:
            raise LimitError(f"table acceleration = {accel_dps2:g} deg/s^2 must be positive")
