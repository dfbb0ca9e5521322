"""Line transactions over a pyserial-like port, shared by the rate-table and chamber drivers.

A port is anything with pyserial's `write`, `flush`, `read_until(expected, size)`, `reset_input_buffer` and
`close`: `serial.Serial`, the object `serial.serial_for_url(...)` returns, or a twin's in-process port.
pyserial's `read_until` returns early with what it has when the port's timeout expires; this module turns
every short, unterminated, non-ASCII or unprintable line into an InstrumentError that names the command and
the bytes received, and turns transport exceptions (SerialException, OSError) into InstrumentError too.
"""

from __future__ import annotations

from collections.abc import Callable

from typing import Protocol

from qmg_lab.instruments import InstrumentError


class SerialPort(Protocol):
    """The subset of pyserial's Serial API the drivers use."""

    def write(self, data: bytes) -> int | None: ...

    def flush(self) -> None: ...

    def read_until(self, expected: bytes = ..., size: int | None = ...) -> bytes: ...

    def reset_input_buffer(self) -> None: ...

    def close(self) -> None: ...


class SerialLink:
    """Write commands and read terminated reply lines on one port, strictly.

    `name` prefixes every error message (e.g. "1291BR"); `command_terminator` is appended to every command;
    `reply_terminator` ends every reply line; replies longer than `max_reply_bytes` are refused.
    """

    def __init__(self, port: SerialPort, *, name: str, command_terminator: bytes, reply_terminator: bytes,
                 max_reply_bytes: int = 128) -> None:
        if not command_terminator or not reply_terminator:
            raise ValueError("command and reply terminators must not be empty")
        self.port = port
        self.name = name
        self.command_terminator = command_terminator
        self.reply_terminator = reply_terminator
        self.max_reply_bytes = int(max_reply_bytes)

    def send(self, command: bytes) -> None:
        """Discard stale input (a late reply to an earlier, failed transaction), then write `command`.

        `command` must already end with the command terminator.
        """
        if not command.endswith(self.command_terminator):
            raise ValueError(f"{self.name}: command {command!r} lacks the terminator {self.command_terminator!r}")
        try:
            self.port.reset_input_buffer()
            self.port.write(command)
            self.port.flush()
        except (OSError, ValueError) as exc:  # serial.SerialException is an OSError (IOError) subclass
            raise InstrumentError(f"{self.name}: cannot send {self._show(command)}: {exc}") from exc

    def read_line(self, command: bytes) -> str:
        """One reply line to `command`, terminator stripped, as ASCII text.

        Raises InstrumentError: nothing received (timeout), no terminator (truncated), bytes that are not
        printable ASCII (garbled).
        """
        try:
            data = self.port.read_until(self.reply_terminator, self.max_reply_bytes)
        except (OSError, ValueError) as exc:
            raise InstrumentError(f"{self.name}: reading the reply to {self._show(command)} failed: {exc}") from exc
        if not data:
            raise InstrumentError(f"{self.name}: timeout: no reply to {self._show(command)} (received b'')")
        if not data.endswith(self.reply_terminator):
            raise InstrumentError(
                f"{self.name}: truncated reply to {self._show(command)}: received {data!r} "
                f"without the terminator {self.reply_terminator!r}")
        body = data[: -len(self.reply_terminator)]
        if any(b < 0x20 or b > 0x7E for b in body):
            raise InstrumentError(f"{self.name}: garbled reply to {self._show(command)}: received {data!r}")
        return body.decode("ascii")

    def replace_port(self, port: SerialPort) -> None:
        """Use a newly opened port (reconnect)."""
        self.port = port

    def reopen(self, factory: Callable[[], SerialPort] | None) -> None:
        """Close the port and open a new one with `factory` (a driver's reconnect, before it re-identifies)."""
        if factory is None:
            raise InstrumentError(f"{self.name}: cannot reconnect: no port_factory was given")
        self.close()
        try:
            port = factory()
        except (OSError, ValueError) as exc:
            raise InstrumentError(f"{self.name}: reopening the port failed: {exc}") from exc
        self.replace_port(port)

    def close(self) -> None:
        """Close the port; errors on closing an already dead link are ignored."""
        try:
            self.port.close()
        except (OSError, ValueError):
            pass

    def _show(self, command: bytes) -> str:
        """The command as it appears in messages: its text without the terminator."""
        return repr(command[: -len(self.command_terminator)].decode("ascii", "replace")) if command.endswith(
            self.command_terminator) else repr(command)
