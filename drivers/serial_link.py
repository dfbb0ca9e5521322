"""Line transactions over a pyserial-like port, shared by the rate-table and chamber drivers.

A port is anything with pyserial's `write`, `flush`, `read(size)`, `in_waiting`, `reset_input_buffer` and
`close`: `serial.Serial`, the object `serial.serial_for_url(...)` returns, or a twin's in-process port.

Framing (`Framing`): every command is sent with the configured command terminator. Replies are read
tolerantly, because the real framing of the 1291BR and the EC1x is unconfirmed:

* a reply line ends at CR, at LF or at CR LF (``reply_terminator="auto"``), or at exactly the configured
  terminator (``"CR"``, ``"LF"``, ``"CRLF"``);
* CR and LF bytes before a line (the LF left over from a CR LF line, a blank line) are skipped;
* spaces and tabs around the line's content are stripped;
* a line consisting of the prompt (e.g. ``>``) is complete as soon as the prompt is read, whether or not its
  terminator follows; a terminator that follows later is skipped as above;
* the content is still checked strictly: it must be printable ASCII, and the drivers parse it strictly.

pyserial's `read` returns what it has when the port's timeout expires; this module turns every empty, short
(unterminated), non-ASCII or unprintable line into an InstrumentError that names the command and the bytes
received, and turns transport exceptions (SerialException, OSError) into InstrumentError too.
"""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

from qmg_lab.instruments import InstrumentError

log = logging.getLogger(__name__)


class ReplyTimeout(InstrumentError):
    """Nothing (or only line ends and blanks) arrived within the timeout: the instrument stayed silent.

    Distinct from a garbled or truncated reply, so that a driver can treat silence after a setting as "this
    controller does not acknowledge settings" (drivers/chamber.py) while a wrong reply stays a fault.
    """


TERMINATORS: dict[str, bytes] = {"CR": b"\r", "LF": b"\n", "CRLF": b"\r\n"}
_LINE_ENDS = b"\r\n"
_BLANKS = b" \t"
_SKIP = _LINE_ENDS + _BLANKS  # bytes skipped before a line
_SKIPPED = frozenset(_SKIP)
_PRINTABLE = bytes(range(0x20, 0x7F))  # printable ASCII: a line's content must consist of these only


class SerialPort(Protocol):
    """The subset of pyserial's Serial API the drivers use."""

    def write(self, data: bytes) -> int | None: ...

    def flush(self) -> None: ...

    def read(self, size: int = ...) -> bytes: ...

    @property
    def in_waiting(self) -> int: ...

    def reset_input_buffer(self) -> None: ...

    def close(self) -> None: ...


@dataclass(frozen=True)
class Framing:
    """How lines are delimited on one serial protocol.

    command_terminator: appended to every command ("CR", "LF" or "CRLF"). reply_terminator: "auto" (a reply
    line ends at CR, LF or CR LF) or exactly one of "CR", "LF", "CRLF". prompt: the prompt text a controller
    sends when it is ready for the next command ("" = no prompt); it is accepted with or without a terminator.
    """

    command_terminator: str = "CRLF"
    reply_terminator: str = "auto"
    prompt: str = ""

    def __post_init__(self) -> None:
        if self.command_terminator not in TERMINATORS:
            raise ValueError(
                f"command_terminator must be one of {', '.join(TERMINATORS)}, got {self.command_terminator!r}"
            )
        if self.reply_terminator != "auto" and self.reply_terminator not in TERMINATORS:
            raise ValueError(
                f"reply_terminator must be auto or one of {', '.join(TERMINATORS)}, got {self.reply_terminator!r}"
            )
        if any(not 0x21 <= ord(ch) <= 0x7E for ch in self.prompt):
            raise ValueError(f"prompt must be printable ASCII without spaces, got {self.prompt!r}")

    @property
    def command_end(self) -> bytes:
        return TERMINATORS[self.command_terminator]

    @property
    def reply_end(self) -> bytes | None:
        """The exact reply terminator, or None for "auto"."""
        return None if self.reply_terminator == "auto" else TERMINATORS[self.reply_terminator]

    def describe(self) -> str:
        """e.g. "replies ending CR, LF or CR LF" (for error messages)."""
        if self.reply_end is None:
            return "CR, LF or CR LF"
        return {"CR": "CR", "LF": "LF", "CRLF": "CR LF"}[self.reply_terminator]


class SerialLink:
    """Write commands and read reply lines on one port: tolerant framing, strict content.

    `name` prefixes every error message (e.g. "1291BR"); `framing` gives the terminators and the prompt;
    reply lines longer than `max_reply_bytes` are refused.
    """

    def __init__(self, port: SerialPort, *, name: str, framing: Framing, max_reply_bytes: int = 128) -> None:
        self.port = port
        self.name = name
        self.framing = framing
        self.command_terminator = framing.command_end
        self._reply_end = framing.reply_end  # the framing is frozen: its bytes are looked up once
        self._prompt = framing.prompt.encode("ascii")
        self.max_reply_bytes = int(max_reply_bytes)
        self._rx = bytearray()  # bytes read from the port but not yet consumed by a line
        self._log = logging.getLogger(f"{__name__}.{name}")

    def send(self, command: bytes) -> None:
        """Discard stale input (a late reply to an earlier, failed transaction), then write `command`.

        `command` must already end with the command terminator.
        """
        if not command.endswith(self.command_terminator):
            raise ValueError(f"{self.name}: command {command!r} lacks the terminator {self.command_terminator!r}")
        if self._rx and self._rx.strip(_SKIP):
            self._log.debug("discarding stale bytes %r before %r", bytes(self._rx), command)
        self._rx.clear()
        try:
            self.port.reset_input_buffer()
            self.port.write(command)
            self.port.flush()
        except (OSError, ValueError) as exc:  # serial.SerialException is an OSError (IOError) subclass
            raise InstrumentError(f"{self.name}: cannot send {self._show(command)}: {exc}") from exc
        self._log.debug("sent %r", command)

    def _fill(self, command: bytes) -> bool:
        """Read what the port has (at least one byte, waiting up to the port's timeout). False on timeout."""
        try:
            waiting = self.port.in_waiting
            data = self.port.read(max(1, int(waiting)))
        except (OSError, ValueError) as exc:
            raise InstrumentError(f"{self.name}: reading the reply to {self._show(command)} failed: {exc}") from exc
        self._rx.extend(data)
        return bool(data)

    def _line_end(self) -> tuple[int, int] | None:
        """(end of content, end of terminator) of the first complete line in the buffer, or None."""
        exact = self._reply_end
        if exact is not None:
            i = self._rx.find(exact)
            return None if i < 0 else (i, i + len(exact))
        cr, lf = self._rx.find(b"\r"), self._rx.find(b"\n")
        i = lf if cr < 0 else cr if lf < 0 else min(cr, lf)
        if i < 0:
            return None
        return i, i + 1  # a CR's LF (CR LF framing) is skipped as the next line's leading terminator

    def read_line(self, command: bytes) -> str:
        """One reply line to `command`, terminator and surrounding blanks stripped, as ASCII text.

        Raises InstrumentError: nothing received (timeout), no terminator (truncated), more than
        max_reply_bytes, or bytes that are not printable ASCII (garbled).
        """
        received = bytearray()  # what this line consumed before its content (skipped bytes), for messages
        prompt = self._prompt
        if not self._rx and not self._fill(command):  # nothing buffered: nothing to look at before reading
            raise ReplyTimeout(f"{self.name}: timeout: no reply to {self._show(command)} (received b'')")
        while True:
            # leading CR/LF (and blanks) belong to no line
            if self._rx and self._rx[0] in _SKIPPED:
                n = len(self._rx) - len(self._rx.lstrip(_SKIP))
                received += self._rx[:n]
                del self._rx[:n]
            if prompt and self._rx.startswith(prompt):
                after = self._rx[len(prompt) : len(prompt) + 1]  # the byte after the prompt, if any
                if not after or after in _SKIP:
                    del self._rx[: len(prompt)]
                    received += prompt
                    if self._log.isEnabledFor(logging.DEBUG):
                        self._log.debug("received %r (prompt) for %r", bytes(received), command)
                    return self.framing.prompt
            end = self._line_end()
            if end is not None:
                line = bytes(self._rx[: end[1]])  # content and terminator
                del self._rx[: end[1]]
                body = line[: end[0]]
                break
            if len(self._rx) > self.max_reply_bytes:
                data = bytes(received + self._rx)
                self._rx.clear()
                raise InstrumentError(
                    f"{self.name}: garbled reply to {self._show(command)}: more than "
                    f"{self.max_reply_bytes} bytes without a terminator: received {data!r}"
                )
            if not self._fill(command):
                data = bytes(received + self._rx)
                self._rx.clear()
                if not data.strip(_LINE_ENDS + _BLANKS):
                    raise ReplyTimeout(f"{self.name}: timeout: no reply to {self._show(command)} (received {data!r})")
                raise InstrumentError(
                    f"{self.name}: truncated reply to {self._show(command)}: received {data!r} "
                    f"without a terminator ({self.framing.describe()})"
                )
        if self._log.isEnabledFor(logging.DEBUG):
            self._log.debug("received %r for %r", bytes(received) + line, command)
        body = body.strip(_BLANKS)
        if not body or body.translate(None, _PRINTABLE):  # empty, or bytes left that are not printable ASCII
            data = bytes(received) + line
            raise InstrumentError(f"{self.name}: garbled reply to {self._show(command)}: received {data!r}")
        return body.decode("ascii")

    def replace_port(self, port: SerialPort) -> None:
        """Use a newly opened port (reconnect)."""
        self.port = port
        self._rx.clear()

    def reopen(self, factory: Callable[[], SerialPort] | None) -> None:
        """Close the port and open a new one with `factory` (a driver's reconnect, before it re-identifies)."""
        if factory is None:
            raise InstrumentError(f"{self.name}: cannot reconnect: no port_factory was given")
        self.close()
        log.info("%s: reopening the serial port", self.name)
        try:
            port = factory()
        except (OSError, ValueError) as exc:
            raise InstrumentError(f"{self.name}: reopening the port failed: {exc}") from exc
        self.replace_port(port)

    def close(self) -> None:
        """Close the port; errors on closing an already dead link are ignored."""
        with contextlib.suppress(OSError, ValueError):
            self.port.close()

    def _show(self, command: bytes) -> str:
        """The command as it appears in messages: its text without the terminator."""
        return (
            repr(command[: -len(self.command_terminator)].decode("ascii", "replace"))
            if command.endswith(self.command_terminator)
            else repr(command)
        )
