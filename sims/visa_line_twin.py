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

from sims.serial_twin import LineFramer, LineTwin, line_end
from sims.visa_resource import VisaLikeResource


class LineTwinVisaResource(VisaLikeResource):
    """A VISA-like message-based resource wired to a line twin (no thread, no OS)."""

    def __init__(self, twin: LineTwin, resource_name: str = "GPIB0::6::INSTR") -> None:
        super().__init__(resource_name)
        self.twin = twin
        self._framer = LineFramer(line_end(twin))
        self._serial = resource_name.upper().startswith("ASRL")

    def _more(self) -> bool:
        return False  # every reply is buffered as soon as its command is written

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
