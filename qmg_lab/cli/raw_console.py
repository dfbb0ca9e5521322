"""The raw console of bring-up: one message to one instrument, exactly the bytes sent and received, with timing.

For adapting the drivers to a real manual (docs/bench-bringup.md): nothing is interpreted, every byte is shown
as Python bytes (b'8\\r>\\r'), each chunk with its time since the command was written.

* serial (1291BR, EC1x): `serial_exchange(port, data, wait_s, idle_s)` writes `data`, then reads until nothing
  has arrived for `idle_s` after the last byte, or until `wait_s` passed with nothing at all.
* VISA (DS345): `visa_exchange(resource, message)` writes message + write_termination; a message containing '?'
  is a query and one reply is read (VISA strips the read termination, shown separately).
* HF2 nodes: `node_get(connection, path)` / `node_set(connection, path, value)` on the data-server connection
  (zhinst's ziDAQServer API, or the twin's), printing the call and its result.

The functions return `Exchange` records; the CLI prints them. Times come from time.perf_counter.
"""

from __future__ import annotations

import codecs
import time
from dataclasses import dataclass, field
from typing import Any


@dataclass
class Exchange:
    """What went over the wire: (seconds since the write, direction '>>' sent or '<<' received, bytes or text)."""

    lines: list[tuple[float, str, str]] = field(default_factory=list)
    sent: bytes = b""
    received: bytes = b""

    def add(self, t: float, direction: str, payload: str) -> None:
        self.lines.append((t, direction, payload))

    def render(self) -> list[str]:
        out = [f"{t * 1e3:10.1f} ms  {d} {p}" for t, d, p in self.lines]
        out.append(f"sent {len(self.sent)} bytes {self.sent!r}; received {len(self.received)} bytes {self.received!r}")
        return out


def decode_escapes(text: str) -> bytes:
    """The command as typed, with backslash escapes (\\r, \\n, \\xNN) turned into bytes; ASCII only."""
    try:
        raw = codecs.decode(text, "unicode_escape")
        return raw.encode("latin-1")
    except (UnicodeDecodeError, UnicodeEncodeError) as exc:
        raise ValueError(f"cannot encode {text!r} as bytes: {exc}") from None


def serial_exchange(port: Any, data: bytes, *, wait_s: float, idle_s: float, answers_at_once: bool = False) -> Exchange:
    """Write `data` on a pyserial-like port, then collect what comes back (see the module docstring).
    answers_at_once: the port is an in-process twin, whose reply is complete when the write returns (its reads
    never wait), so the first empty read ends the exchange."""
    ex = Exchange(sent=data)
    port.reset_input_buffer()
    t0 = time.perf_counter()
    port.write(data)
    port.flush()
    ex.add(time.perf_counter() - t0, ">>", repr(data))
    received = bytearray()
    last = None
    base_timeout = getattr(port, "timeout", None)
    try:
        while True:
            now = time.perf_counter()
            if last is None and now - t0 >= wait_s:
                break
            if last is not None and now - last >= idle_s:
                break
            remaining = (wait_s - (now - t0)) if last is None else (idle_s - (now - last))
            if hasattr(port, "timeout"):
                port.timeout = max(0.001, remaining)
            chunk = port.read(max(1, int(getattr(port, "in_waiting", 0) or 0)))
            if chunk:
                last = time.perf_counter()
                received += chunk
                ex.add(last - t0, "<<", repr(bytes(chunk)))
            elif answers_at_once:
                break  # nothing now is nothing at all
    finally:
        if hasattr(port, "timeout"):
            port.timeout = base_timeout
    if not received:
        ex.add(time.perf_counter() - t0, "<<", f"nothing within {wait_s:g} s")
    ex.received = bytes(received)
    return ex


def visa_exchange(resource: Any, message: str) -> Exchange:
    """Write `message` (+ the resource's write termination); if it is a query ('?'), read one reply."""
    wt = getattr(resource, "write_termination", "") or ""
    rt = getattr(resource, "read_termination", "") or ""
    sent = (message + wt).encode("ascii")
    ex = Exchange(sent=sent)
    t0 = time.perf_counter()
    resource.write(message)
    ex.add(time.perf_counter() - t0, ">>", repr(sent))
    if "?" in message:
        reply = resource.read()
        t = time.perf_counter() - t0
        ex.received = reply.encode("ascii", "backslashreplace") + rt.encode("ascii")
        ex.add(t, "<<", f"{reply.encode('ascii', 'backslashreplace')!r} + read termination {rt!r} (stripped by VISA)")
    return ex


def node_get(connection: Any, path: str) -> tuple[Exchange, Any]:
    """getDouble(path), falling back to getString for text nodes; returns the exchange and the value."""
    ex = Exchange()
    t0 = time.perf_counter()
    try:
        value: Any = connection.getDouble(path)
        call = "getDouble"
    except Exception:
        value = connection.getString(path)
        call = "getString"
    ex.add(time.perf_counter() - t0, "<<", f"{call}({path!r}) -> {value!r}")
    return ex, value


def node_set(connection: Any, path: str, value: str) -> tuple[Exchange, Any]:
    """Set `path` to `value` (an integer, a float or text, as it parses), then read it back."""
    parsed: Any
    for kind in (int, float):
        try:
            parsed = kind(value)
            break
        except ValueError:
            continue
    else:
        parsed = value
    ex = Exchange()
    t0 = time.perf_counter()
    connection.set(path, parsed)
    ex.add(time.perf_counter() - t0, ">>", f"set({path!r}, {parsed!r})")
    back, got = node_get(connection, path)
    ex.lines.extend((t + (time.perf_counter() - t0) * 0, d, p) for t, d, p in back.lines)
    return ex, got
