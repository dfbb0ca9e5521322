"""A VISA-like resource in front of a line twin: the EC1x chamber twin as ``GPIB0::6::INSTR``.

Many EC1x controllers sit on GPIB (through a GPIB adapter), not on a serial port; the driver then talks
through pyvisa (drivers/line_transport.py, `VisaLineTransport`). This resource offers that driver what a pyvisa
MessageBasedResource offers (write, read, read_bytes, query, clear, close, timeout, the terminations,
resource_name) and hands every command line to the same byte-level twin the serial ports reach
(`respond(line) -> reply bytes`, split at the twin's `line_end` as sims/serial_twin.py does):

* write(msg): msg + write_termination goes to the twin; its reply bytes (if any) wait in the receive buffer;
* read(): the buffered bytes up to read_termination (removed); on a bus with an END line (every resource not
  named ASRL..., e.g. GPIB's EOI) a reply without that terminator ends with its last byte, as the controller
  asserts END there; nothing (or, on ASRL, no terminator): VisaIOError(TMO) at once (the clock is virtual;
  `timeout` in ms is only recorded), a partial ASRL reply stays buffered;
* read_bytes(n): the next n buffered bytes, or VisaIOError(TMO) if fewer are there.

A reply that is not ASCII raises UnicodeDecodeError, as pyvisa's read does; a closed resource raises pyvisa's
InvalidSession.
"""

from __future__ import annotations

import pyvisa.constants
import pyvisa.errors

from sims.serial_twin import LineFramer, LineTwin, line_end


class LineTwinVisaResource:
    """A VISA-like message-based resource wired to a line twin (no thread, no OS)."""

    def __init__(self, twin: LineTwin, resource_name: str = "GPIB0::6::INSTR") -> None:
        self.twin = twin
        self.resource_name = resource_name
        self.write_termination = "\r\n"  # pyvisa's defaults; drivers set their own
        self.read_termination = "\n"
        self.timeout: float | None = 2000.0
        self._framer = LineFramer(line_end(twin))
        self._rx = bytearray()
        self._closed = False
        self._serial = resource_name.upper().startswith("ASRL")

    def _check_open(self) -> None:
        if self._closed:
            raise pyvisa.errors.InvalidSession()

    @staticmethod
    def _timeout() -> pyvisa.errors.VisaIOError:
        return pyvisa.errors.VisaIOError(pyvisa.constants.StatusCode.error_timeout)

    def write(self, message: str) -> int:
        self._check_open()
        data = (message + (self.write_termination or "")).encode("ascii")
        for line in self._framer.feed(data):
            self._rx += self.twin.respond(line)
        return len(data)

    def read(self) -> str:
        self._check_open()
        term = (self.read_termination or "").encode("ascii")
        if not self._rx or (term and term not in self._rx and self._serial):
            raise self._timeout()
        if not term or term not in self._rx:  # END (EOI) ends the message
            out = bytes(self._rx)
            self._rx.clear()
            return out.decode("ascii")
        head, _, rest = bytes(self._rx).partition(term)
        self._rx = bytearray(rest)
        return head.decode("ascii")

    def read_bytes(self, count: int) -> bytes:
        self._check_open()
        if len(self._rx) < count:
            raise self._timeout()
        out = bytes(self._rx[:count])
        del self._rx[:count]
        return out

    def query(self, message: str) -> str:
        self.write(message)
        return self.read()

    def clear(self) -> None:
        self._check_open()
        self._rx.clear()

    def close(self) -> None:
        self._closed = True
