"""Protocol tests for serial drivers: a serial-like fake port that checks every byte written.

`ProtocolPort(pairs)` holds an ordered list of (command_bytes, reply_bytes). Bytes the driver writes are
collected; they must at every moment be a prefix of the next expected command, else AssertionError at once
(naming expected and received bytes). When a command is complete its reply (None = no reply: the driver's
read times out) is queued for reading. Reads return at once with what is queued (a pyserial read that timed
out returns what it had). `assert_complete()` checks that every pair was used and that the write and read
buffers are empty.

`expected_protocol(build, pairs)` is a context manager: it builds the driver on a ProtocolPort with
`build(port)`, yields the driver, and on a normal exit calls `assert_complete()`.

`ProtocolPort.reply_framing` (class attribute, None = replies as written) maps every reply before it is queued:
a test module sets it (through a parametrized fixture) to replay one dialogue under CR, LF and CR LF framings.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from typing import TypeVar

T = TypeVar("T")
Pair = tuple[bytes, bytes | None]


class ProtocolPort:
    """A pyserial-like port that plays back an expected (command, reply) dialogue and checks it byte by byte."""

    reply_framing: Callable[[bytes], bytes] | None = None

    def __init__(self, pairs: Sequence[Pair], *, port: str = "protocol://fake", timeout: float = 1.0) -> None:
        for i, pair in enumerate(pairs):
            if not (
                isinstance(pair, tuple)
                and len(pair) == 2
                and isinstance(pair[0], bytes)
                and pair[0]
                and (pair[1] is None or isinstance(pair[1], bytes))
            ):
                raise TypeError(f"pair {i} must be (non-empty command bytes, reply bytes or None), got {pair!r}")
        self._pairs = list(pairs)
        self._next = 0
        self._written = bytearray()
        self._rx = bytearray()
        self.port = port
        self.timeout = timeout
        self.is_open = True
        self.log: list[bytes] = []  # every completed command, in order
        self.discarded: list[bytes] = []  # reply bytes the driver threw away with reset_input_buffer

    # ---------------------------------------------------------------- checks
    @property
    def pairs_used(self) -> int:
        return self._next

    @property
    def bytes_written(self) -> bytes:
        """Everything written so far (completed commands and the pending partial one)."""
        return b"".join(self.log) + bytes(self._written)

    def assert_complete(self) -> None:
        unused = self._pairs[self._next :]
        assert not unused, f"{len(unused)} expected command(s) never sent, first {unused[0][0]!r}"
        assert not self._written, f"bytes written but not matching a whole command: {bytes(self._written)!r}"
        assert not self._rx, f"reply bytes never read by the driver: {bytes(self._rx)!r}"

    # ---------------------------------------------------------------- pyserial API
    def write(self, data: bytes) -> int:
        assert self.is_open, "write on a closed port"
        for byte in bytes(data):
            self._written.append(byte)
            self._match()
        return len(data)

    def _match(self) -> None:
        if self._next >= len(self._pairs):
            raise AssertionError(f"unexpected bytes written after the whole dialogue: {bytes(self._written)!r}")
        command, reply = self._pairs[self._next]
        if not command.startswith(bytes(self._written)):
            raise AssertionError(
                f"command {self._next}: expected {command!r}, the driver wrote {bytes(self._written)!r}"
            )
        if len(self._written) == len(command):
            self.log.append(bytes(self._written))
            self._written.clear()
            self._next += 1
            if reply is not None:
                frame = type(self).reply_framing
                self._rx.extend(frame(reply) if frame is not None else reply)

    def flush(self) -> None:
        pass

    def read(self, size: int = 1) -> bytes:
        out = bytes(self._rx[:size])
        del self._rx[:size]
        return out

    def read_until(self, expected: bytes = b"\n", size: int | None = None) -> bytes:
        i = self._rx.find(expected)
        n = len(self._rx) if i < 0 else i + len(expected)
        return self.read(n if size is None else min(n, size))

    def readline(self, size: int | None = None) -> bytes:
        return self.read_until(b"\n", size)

    @property
    def in_waiting(self) -> int:
        return len(self._rx)

    def reset_input_buffer(self) -> None:
        """Discard unread reply bytes (recorded in `discarded`, so a test can see a driver resynchronise)."""
        if self._rx:
            self.discarded.append(bytes(self._rx))
        self._rx.clear()

    def reset_output_buffer(self) -> None:
        pass

    def open(self) -> None:
        self.is_open = True

    def close(self) -> None:
        self.is_open = False


@contextmanager
def expected_protocol(build: Callable[[ProtocolPort], T], pairs: Sequence[Pair]) -> Iterator[T]:
    """Build the driver on a ProtocolPort playing `pairs`; after the block, every pair used, buffers empty."""
    port = ProtocolPort(pairs)
    driver = build(port)
    yield driver
    port.assert_complete()
