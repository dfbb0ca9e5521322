"""Expected-protocol testing for VISA drivers: a fake message-based resource that checks the wire.

    with expected_protocol([(b"FUNC 1", None), (b"*ESR?", b"0")]) as res:
        DS345(res).some_call()

`ProtocolResource` behaves like a pyvisa MessageBasedResource as far as a driver can see (write, read, query,
close, clear, timeout, resource_name, write_termination, read_termination). Every message written is turned
into the bytes that would go on the wire (message + write_termination, ASCII) and compared, byte for byte,
with the next expected command + the documented terminator (LF for the DS345). A pair (command, reply) whose
reply is not None queues the reply for the next read; `TIMEOUT` as the reply makes that read raise pyvisa's
VisaIOError(VI_ERROR_TMO), as a silent instrument would. `read_bytes(n)` reads replies byte by byte (as a
driver does on an RS-232 resource, `resource_name="ASRL1::INSTR"`); the reply bytes are then given with their
terminator (b"0\r"), and line-end bytes left over at the end (the LF of a CR LF reply) count as read. On
leaving the block every pair must have been used and every reply read: a driver that sends too little, too
much, or the wrong bytes fails the test. A violation raises ProtocolError at once and is remembered, so a
driver that wraps it into its own error (as it should wrap real I/O errors) still fails the test when the
block ends.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Iterator, Sequence
from contextlib import contextmanager

import pyvisa.constants
import pyvisa.errors

from sims.visa_resource import VisaLikeResource

TIMEOUT = object()  # reply sentinel: the instrument stays silent, the read times out


class ProtocolError(AssertionError):
    """The driver did not follow the expected protocol."""


class ProtocolResource(VisaLikeResource):
    """A fake VISA resource that replays an expected list of (command, reply) pairs."""

    def __init__(
        self,
        pairs: Sequence[tuple[bytes, bytes | object | None]],
        terminator: bytes = b"\n",
        resource_name: str = "GPIB0::19::INSTR",
    ) -> None:
        for cmd, reply in pairs:
            if not isinstance(cmd, bytes) or not (reply is None or reply is TIMEOUT or isinstance(reply, bytes)):
                raise TypeError(f"protocol pair ({cmd!r}, {reply!r}) must be (bytes, bytes | None | TIMEOUT)")
        super().__init__(resource_name)  # pyvisa's default terminations; the driver must set its own
        self._pairs = deque(pairs)
        self._terminator = terminator
        self._replies: deque[bytes | object] = deque()
        self.sent: list[bytes] = []  # every message as it went on the wire
        self.violation: ProtocolError | None = None  # first violation (kept even if the driver swallows it)

    def _fail(self, message: str) -> ProtocolError:
        error = ProtocolError(message)
        if self.violation is None:
            self.violation = error
        return error

    def write(self, message: str) -> int:
        if self.closed:
            raise pyvisa.errors.InvalidSession()
        wire = (message + self.write_termination).encode("ascii")
        self.sent.append(wire)
        if self._replies:
            raise self._fail(f"wrote {wire!r} while a reply was still unread: {self._replies[0]!r}")
        if not self._pairs:
            raise self._fail(f"wrote {wire!r}, but no more messages were expected")
        cmd, reply = self._pairs.popleft()
        if wire != cmd + self._terminator:
            raise self._fail(f"wrote {wire!r}, expected {cmd + self._terminator!r}")
        if reply is not None:
            self._replies.append(reply)
        return len(wire)

    def read(self) -> str:
        if self.closed:
            raise pyvisa.errors.InvalidSession()
        if not self._replies:
            raise self._fail("read with no reply expected")
        reply = self._replies.popleft()
        if reply is TIMEOUT:
            raise pyvisa.errors.VisaIOError(pyvisa.constants.StatusCode.error_timeout)
        assert isinstance(reply, bytes)
        text = reply.decode("ascii")  # like pyvisa: a non-ASCII reply raises UnicodeDecodeError
        if self.read_termination and text.endswith(self.read_termination):
            text = text[: -len(self.read_termination)]
        return text

    def _more(self) -> bool:
        """The next reply's bytes (for read_bytes); False (timeout) if none is queued or it is TIMEOUT."""
        if not self._replies:
            return False
        reply = self._replies.popleft()
        if reply is TIMEOUT:
            return False
        assert isinstance(reply, bytes)
        self._rx += reply
        return True

    def clear(self) -> None:
        self._replies.clear()

    @property
    def closed(self) -> bool:
        return self._closed

    def check_done(self) -> None:
        """Raise ProtocolError unless the conversation had no violation, used every pair and read every reply."""
        if self.violation is not None:
            raise self.violation
        if self._pairs:
            raise ProtocolError(f"{len(self._pairs)} expected message(s) never sent, first: {self._pairs[0]!r}")
        if self._replies:
            raise ProtocolError(f"reply never read: {self._replies[0]!r}")
        if self._rx.strip(b"\r\n"):
            raise ProtocolError(f"reply bytes never read: {bytes(self._rx)!r}")


@contextmanager
def expected_protocol(
    pairs: Sequence[tuple[bytes, bytes | object | None]],
    terminator: bytes = b"\n",
    resource_name: str = "GPIB0::19::INSTR",
) -> Iterator[ProtocolResource]:
    """Yield a ProtocolResource; on a clean exit, check the whole conversation was used."""
    resource = ProtocolResource(pairs, terminator, resource_name)
    yield resource
    resource.check_done()
