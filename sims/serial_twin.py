"""Serial plumbing for the byte-level twins: in-process port, pty server, loopback TCP server.

A twin is a `LineTwin`: `respond(line) -> bytes` takes one received command line (the bytes before the twin's
`line_end` byte, LF unless the twin's commands end CR; a CR before an LF is included) and returns the bytes the
instrument writes back. Framing into lines is per connection (`LineFramer`), so one twin can serve several
connections. Three ways to reach a twin:

1. `InProcessSerial(twin)`: the pyserial `Serial` methods drivers use, no thread, no OS buffer. A reply is
   available as soon as the command's LF is written; a read that finds no terminator returns what there is at
   once (the virtual-time equivalent of a pyserial timeout).
2. `serve_pty(twin) -> (device_path, stop)`: a thread on the master side of `os.openpty()`; the driver opens
   `serial.Serial(device_path)` and sees a real tty (raw mode: no echo, no CR/LF translation). POSIX only
   (Linux, macOS): `pty_supported()` says whether this system has pseudo-terminals; `tty` is imported only here.
3. `serve_socket(twin, host="127.0.0.1", port=0) -> ("socket://127.0.0.1:N", stop)`: a loopback TCP server
   for `serial.serial_for_url(url)`; any number of sequential or simultaneous connections. Every system.

Threads wait in `select` on their descriptors and a wake-up socket pair (Windows' `select` takes sockets only),
so `stop()` returns at once and never sleeps.
"""

from __future__ import annotations

import ipaddress
import os
import select
import socket
import threading
from collections.abc import Callable
from typing import Protocol

import serial

MAX_LINE_BYTES = 1024


class LineTwin(Protocol):
    """A byte-level instrument: one command line in, the instrument's reply bytes out."""

    def respond(self, line: bytes) -> bytes: ...


def line_end(twin: object) -> bytes:
    """The byte that ends a command line for `twin` (its `line_end` attribute; LF by default)."""
    end = getattr(twin, "line_end", b"\n")
    return end if isinstance(end, bytes) and len(end) == 1 else b"\n"


class LineFramer:
    """Split a byte stream into lines ending with `end` (one byte, LF by default). An over-long line
    (> MAX_LINE_BYTES without `end`) is passed on as it is, so that the twin answers it with its framing error,
    and the buffer restarts."""

    def __init__(self, end: bytes = b"\n") -> None:
        self._buf = bytearray()
        self._end = end

    def feed(self, data: bytes) -> list[bytes]:
        if data and not self._buf and data.find(self._end) == len(data) - 1:  # the usual write: one whole line
            return [bytes(data[:-1])]
        self._buf.extend(data)
        lines: list[bytes] = []
        while True:
            i = self._buf.find(self._end)
            if i < 0:
                break
            lines.append(bytes(self._buf[:i]))
            del self._buf[: i + 1]
        if len(self._buf) > MAX_LINE_BYTES:
            lines.append(bytes(self._buf))
            self._buf.clear()
        return lines


def _answer(twin: LineTwin, framer: LineFramer, data: bytes) -> bytes:
    """The twin's replies to the complete lines `data` ends (with what the framer held before), in order."""
    lines = framer.feed(data)
    if len(lines) == 1:
        return twin.respond(lines[0])
    return b"".join([twin.respond(line) for line in lines])


class InProcessSerial:
    """A pyserial-like port wired straight to a twin (same thread, no OS involved)."""

    def __init__(self, twin: LineTwin, *, port: str = "inprocess://twin", timeout: float | None = 1.0) -> None:
        self.twin = twin
        self.port = port
        self.timeout = timeout  # kept for API compatibility; reads never wait
        self.baudrate = 9600
        self._framer = LineFramer(line_end(twin))
        self._rx = bytearray()
        self._open = True

    # ---------------------------------------------------------------- state
    @property
    def is_open(self) -> bool:
        return self._open

    def open(self) -> None:
        self._open = True
        self._framer = LineFramer(line_end(self.twin))
        self._rx.clear()

    def close(self) -> None:
        self._open = False

    def _check_open(self) -> None:
        if not self._open:
            raise serial.PortNotOpenError()

    # ---------------------------------------------------------------- writing
    def write(self, data: bytes) -> int:
        if not self._open:
            raise serial.PortNotOpenError()
        data = bytes(data)
        self._rx += _answer(self.twin, self._framer, data)
        return len(data)

    def flush(self) -> None:
        if not self._open:
            raise serial.PortNotOpenError()

    def reset_output_buffer(self) -> None:
        self._check_open()

    # ---------------------------------------------------------------- reading
    @property
    def in_waiting(self) -> int:
        if not self._open:
            raise serial.PortNotOpenError()
        return len(self._rx)

    def reset_input_buffer(self) -> None:
        if not self._open:
            raise serial.PortNotOpenError()
        self._rx.clear()

    def read(self, size: int = 1) -> bytes:
        if not self._open:
            raise serial.PortNotOpenError()
        if size >= len(self._rx):  # the usual read: everything there is
            out = bytes(self._rx)
            self._rx.clear()
            return out
        out = bytes(self._rx[:size])
        del self._rx[:size]
        return out

    def read_until(self, expected: bytes = b"\n", size: int | None = None) -> bytes:
        """Bytes up to and including `expected`, at most `size`; what there is if the terminator is absent."""
        self._check_open()
        i = self._rx.find(expected)
        n = len(self._rx) if i < 0 else i + len(expected)
        if size is not None:
            n = min(n, size)
        return self.read(n)

    def readline(self, size: int | None = None) -> bytes:
        return self.read_until(b"\n", size)


# -------------------------------------------------------------------------------------------------- threads


class _Server:
    """A select() loop in a daemon thread; `stop()` wakes it through a socket pair and joins it."""

    def __init__(self, name: str) -> None:
        self._wake_r, self._wake_w = socket.socketpair()
        self._thread = threading.Thread(target=self._run_guarded, name=name, daemon=True)
        self._stopped = False
        self.error: BaseException | None = None

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        if self._stopped:
            return
        self._stopped = True
        self._wake_w.send(b"x")
        self._thread.join(timeout=5.0)
        for end in (self._wake_r, self._wake_w):
            end.close()
        self._close()

    def _run_guarded(self) -> None:
        try:
            self._run()
        except BaseException as exc:
            self.error = exc

    def _run(self) -> None:
        raise NotImplementedError

    def _close(self) -> None:
        raise NotImplementedError


def pty_supported() -> bool:
    """Whether this system has pseudo-terminals for `serve_pty` (POSIX: Linux, macOS; not Windows)."""
    return os.name == "posix" and hasattr(os, "openpty")


class _PtyServer(_Server):
    def __init__(self, twin: LineTwin) -> None:
        if not pty_supported():
            raise OSError(
                "the twins' pty transport needs a POSIX system (Linux, macOS): on Windows set sim_transport = "
                '"inprocess" (or "socket") in [table] and [chamber]'
            )
        import tty  # POSIX only (termios): imported where it is used, so the module imports on Windows

        super().__init__("pty-twin")
        self.twin = twin
        self.master, self.slave = os.openpty()
        tty.setraw(self.slave)  # no echo, no CR -> LF translation on the driver's side
        self.path = os.ttyname(self.slave)

    def _run(self) -> None:
        framer = LineFramer(line_end(self.twin))
        wake = self._wake_r.fileno()
        while True:
            ready, _, _ = select.select([self.master, wake], [], [])
            if wake in ready:
                return
            try:
                data = os.read(self.master, 4096)
            except OSError:  # EIO: no slave open right now
                continue
            if data:
                reply = _answer(self.twin, framer, data)
                if reply:
                    os.write(self.master, reply)

    def _close(self) -> None:
        os.close(self.master)
        os.close(self.slave)


def serve_pty(twin: LineTwin) -> tuple[str, Callable[[], None]]:
    """Serve `twin` on a new pseudo-terminal. Returns (slave device path, stop callable)."""
    server = _PtyServer(twin)
    server.start()
    return server.path, server.stop


class _SocketServer(_Server):
    def __init__(self, twin: LineTwin, host: str, port: int) -> None:
        super().__init__("socket-twin")
        if not ipaddress.ip_address(host).is_loopback:
            raise ValueError(f"serve_socket host must be a loopback address (127.0.0.0/8 or ::1), got {host!r}")
        self.twin = twin
        family = socket.AF_INET6 if ":" in host else socket.AF_INET
        self.listener = socket.socket(family, socket.SOCK_STREAM)
        if os.name == "posix":  # on Windows SO_REUSEADDR would let another socket take a port in use
            self.listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self.listener.bind((host, port))
        self.listener.listen(4)
        self.address = self.listener.getsockname()[:2]
        self._conns: dict[socket.socket, LineFramer] = {}

    def _run(self) -> None:
        while True:
            watched: list[socket.socket] = [self.listener, self._wake_r, *self._conns]
            ready, _, _ = select.select(watched, [], [])
            if self._wake_r in ready:
                return
            if self.listener in ready:
                conn, _ = self.listener.accept()
                conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
                self._conns[conn] = LineFramer(line_end(self.twin))
            for s in [c for c in self._conns if c in ready]:
                try:
                    data = s.recv(4096)
                except OSError:
                    data = b""
                if not data:
                    self._conns.pop(s)
                    s.close()
                    continue
                reply = _answer(self.twin, self._conns[s], data)
                if reply:
                    try:
                        s.sendall(reply)
                    except OSError:
                        self._conns.pop(s)
                        s.close()

    def _close(self) -> None:
        for s in list(self._conns):
            s.close()
        self._conns.clear()
        self.listener.close()


def serve_socket(twin: LineTwin, host: str = "127.0.0.1", port: int = 0) -> tuple[str, Callable[[], None]]:
    """Serve `twin` on a loopback TCP port. Returns ("socket://HOST:PORT" for serial.serial_for_url, stop)."""
    server = _SocketServer(twin, host, port)
    server.start()
    h, p = server.address
    url_host = f"[{h}]" if ":" in h else h
    return f"socket://{url_host}:{p}", server.stop


# -------------------------------------------------------------------------------------------------- twin base

ReplyFilter = Callable[[bytes, bytes], bytes]


TERMINATORS: dict[str, bytes] = {"CR": b"\r", "LF": b"\n", "CRLF": b"\r\n"}


def terminator(name: str) -> bytes:
    """ "CR" | "LF" | "CRLF" -> the bytes."""
    try:
        return TERMINATORS[name]
    except KeyError:
        raise ValueError(f"terminator must be one of {', '.join(TERMINATORS)}, got {name!r}") from None


class FaultableTwin:
    """Base of the line twins: `respond` = `execute` + the fault hook, and the twin's command framing.

    `fault_hook(command_line, reply) -> bytes` is the one place where a reply can be dropped (return b""),
    garbled or truncated before it reaches the wire; None (default) sends replies unchanged.
    `command_end`: the terminator the instrument expects after every command (CR LF by default); lines are
    split at its last byte (`line_end`), and `command_complete(line)` checks the bytes before it.
    """

    fault_hook: ReplyFilter | None = None
    command_end: bytes = b"\r\n"

    @property
    def line_end(self) -> bytes:
        return self.command_end[-1:]

    def command_complete(self, line: bytes) -> bool:
        """True if `line` (as split at line_end) carries the rest of the command terminator (the CR of CR LF)."""
        head = self.command_end[:-1]
        return line.endswith(head) if head else True

    def command_text(self, line: bytes) -> bytes:
        """The command without its terminator."""
        head = self.command_end[:-1]
        return line[: -len(head)] if head else line

    def command_body(self, line: bytes) -> bytes | None:
        """`command_text(line)` if `command_complete(line)`, else None (one call per command line)."""
        head = self.command_end[:-1]
        if not head:
            return line
        return line[: -len(head)] if line.endswith(head) else None

    def execute(self, line: bytes) -> bytes:
        raise NotImplementedError

    def respond(self, line: bytes) -> bytes:
        reply = self.execute(line)
        hook = self.fault_hook
        return hook(line, reply) if hook is not None else reply
