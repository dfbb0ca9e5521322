"""One command line out, one reply line in: the same exchange over a pyserial port or a VISA resource.

The EC1x chamber controller sits on RS-232 on some benches and on GPIB (through a GPIB adapter) on others: the
public Sun EC13 driver in achim1/skippylab (skippylab/instruments/climate_chambers.py) reaches its chamber
through a GPIB controller. A driver that speaks in lines takes a `LineTransport` and does not care which:

* `SerialLineTransport(port, name=, framing=, port_factory=)`: a pyserial-like port through
  drivers/serial_link.py (commands end with the framing's terminator; replies ending CR, LF or CR LF).
* `VisaLineTransport(resource, name=, framing=, reopen=)`: a pyvisa message-based resource (or a VISA-like
  twin resource). Commands end with the framing's command terminator (the resource's write termination).
  Replies: on a serial (ASRL) resource, read byte by byte up to the first CR or LF (`read_any_line`), so that
  CR, LF and CR LF replies are all read (a CR LF reply's LF is skipped before the next reply); on GPIB and the
  other buses, one VISA read up to LF or the END (EOI) line, as the bus frames it.

Both raise `ReplyTimeout` (an InstrumentError) when the instrument stays silent, InstrumentError for anything
else that goes wrong (garbled, not printable ASCII, I/O error), each naming the command.
"""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Callable
from typing import Any, Protocol, runtime_checkable

from pyvisa.constants import StatusCode
from pyvisa.errors import VisaIOError
from pyvisa.resources import SerialInstrument

from drivers.serial_link import Framing, ReplyTimeout, SerialLink, SerialPort
from qmg_lab.instruments import InstrumentError

log = logging.getLogger(__name__)

LINE_ENDS = b"\r\n"
MAX_LINE_BYTES = 256
GPIB_READ_TERMINATION = "\n"  # the END (EOI) line ends a GPIB reply whatever its last character


@runtime_checkable
class LineTransport(Protocol):
    """What a line-oriented driver needs of its link (commands and replies as text, terminators excluded)."""

    def send_line(self, text: str) -> None: ...

    def read_reply(self, text: str) -> str: ...

    def reopen(self) -> None: ...

    def close(self) -> None: ...

    def describe(self) -> dict[str, Any]: ...


def is_serial_resource(resource: Any) -> bool:
    """True for an RS-232 VISA resource: a pyvisa SerialInstrument, or a VISA-like resource named ASRL..."""
    if isinstance(resource, SerialInstrument):
        return True
    return str(getattr(resource, "resource_name", "")).upper().startswith("ASRL")


def read_any_line(resource: Any, max_bytes: int = MAX_LINE_BYTES) -> str:
    """One reply line from a VISA resource, whatever ends it (CR, LF or CR LF), as ASCII text.

    Reads one byte at a time (`read_bytes(1)`, so the resource's termination character plays no part); CR and
    LF bytes before the content (the LF left over from a CR LF reply) are skipped. A VISA timeout propagates
    (pyvisa's VisaIOError); more than `max_bytes` without a line end raises ValueError; a byte that is not
    ASCII raises UnicodeDecodeError, as pyvisa's own read does.
    """
    line = bytearray()
    while True:
        byte = bytes(resource.read_bytes(1))
        if byte in (b"\r", b"\n"):
            if line:
                return line.decode("ascii")
            continue
        line += byte
        if len(line) > max_bytes:
            raise ValueError(f"more than {max_bytes} bytes without CR or LF: {bytes(line)!r}")


class SerialLineTransport:
    """A `LineTransport` over a pyserial-like port (drivers/serial_link.py does the framing)."""

    def __init__(
        self,
        port: SerialPort,
        *,
        name: str,
        framing: Framing,
        port_factory: Callable[[], SerialPort] | None = None,
    ) -> None:
        self.framing = framing
        self._link = SerialLink(port, name=name, framing=framing)
        self._end = framing.command_end
        self._factory = port_factory

    def send_line(self, text: str) -> None:
        self._link.send(text.encode("ascii") + self._end)

    def read_reply(self, text: str) -> str:
        return self._link.read_line(text.encode("ascii") + self._end)

    def reopen(self) -> None:
        self._link.reopen(self._factory)

    def close(self) -> None:
        self._link.close()

    def describe(self) -> dict[str, Any]:
        return {
            "transport": "serial",
            "command_terminator": self.framing.command_terminator,
            "reply_terminator": self.framing.reply_terminator,
        }


class VisaLineTransport:
    """A `LineTransport` over a pyvisa message-based resource (GPIB, RS-232 through VISA, or a twin's)."""

    def __init__(
        self,
        resource: Any,
        *,
        name: str,
        framing: Framing,
        reopen: Callable[[], Any] | None = None,
    ) -> None:
        self.name = name
        self.framing = framing
        self._reopen = reopen
        self._resource: Any = None
        self._attach(resource)

    def _attach(self, resource: Any) -> None:
        resource.write_termination = self.framing.command_end.decode("ascii")
        resource.read_termination = GPIB_READ_TERMINATION
        self._serial = is_serial_resource(resource)
        self._resource = resource

    @property
    def resource(self) -> Any:
        if self._resource is None:
            raise InstrumentError(f"{self.name}: the VISA resource is closed")
        return self._resource

    def send_line(self, text: str) -> None:
        try:
            self.resource.write(text)
        except InstrumentError:
            raise
        except Exception as exc:  # VisaIOError, OSError, closed sessions: link faults
            raise InstrumentError(f"{self.name}: cannot send {text!r}: {exc}") from exc

    def read_reply(self, text: str) -> str:
        try:
            reply = read_any_line(self.resource) if self._serial else str(self.resource.read())
        except VisaIOError as exc:
            if exc.error_code == StatusCode.error_timeout:
                raise ReplyTimeout(f"{self.name}: timeout: no reply to {text!r}") from exc
            raise InstrumentError(f"{self.name}: reading the reply to {text!r} failed: {exc}") from exc
        except UnicodeDecodeError as exc:
            raise InstrumentError(f"{self.name}: garbled reply to {text!r}: {exc.object!r} (not ASCII)") from exc
        except InstrumentError:
            raise
        except Exception as exc:  # ValueError (no line end), OSError, closed sessions
            raise InstrumentError(f"{self.name}: reading the reply to {text!r} failed: {exc}") from exc
        body = reply.strip(" \t\r\n")
        if not body or not body.isprintable():
            raise InstrumentError(f"{self.name}: garbled reply to {text!r}: received {reply!r}")
        return body

    def reopen(self) -> None:
        if self._reopen is None:
            raise InstrumentError(f"{self.name}: cannot reconnect: no reopen factory was given")
        self.close()
        try:
            resource = self._reopen()
        except InstrumentError:
            raise
        except Exception as exc:
            raise InstrumentError(f"{self.name}: reopening the VISA resource failed: {exc}") from exc
        self._attach(resource)

    def close(self) -> None:
        resource, self._resource = self._resource, None
        if resource is not None:
            with contextlib.suppress(Exception):  # closing a dead session is not news
                resource.close()

    def describe(self) -> dict[str, Any]:
        return {
            "transport": "visa",
            "resource": str(getattr(self._resource, "resource_name", "")),
            "command_terminator": self.framing.command_terminator,
            "reply_terminator": "CR, LF or CR LF" if self._serial else "LF or END (EOI)",
        }
