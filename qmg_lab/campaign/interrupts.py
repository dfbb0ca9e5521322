"""Deferred stop requests: a campaign stops between blocks, never half-way through a write, whichever way the
process is asked to stop.

Every stop signal takes Ctrl-C's path: SIGINT (Ctrl-C), SIGTERM (kill, systemd, a batch scheduler), SIGHUP (the
terminal or the SSH session that started the run went away), SIGQUIT (Ctrl-\\) and, on Windows, SIGBREAK
(Ctrl-Break). Handlers are installed only for the signals the platform has (`STOP_SIGNALS`), and not over an
inherited "ignore" of SIGHUP: a run started under `nohup` goes on when its terminal hangs up. The first
signal sets a flag that the campaign checks between lock-in blocks (it then brings every instrument to its safe state
and marks the file "aborted", the signal named in `abort_reason`); the process then exits 128 + the signal's number
(`exit_code`), the shell's convention for "ended by signal n" (130 for Ctrl-C). A second signal raises
`StopRequested` (a KeyboardInterrupt) at once, unless a protected section (an HDF5 write, the safe state, the
file's last close) is running: then it is raised when the section ends.

Not seen by Python on Windows: closing the console window (CTRL_CLOSE_EVENT is not mapped to a signal by the C
runtime; Windows ends the process a few seconds later) and logging off. Use Ctrl-C or Ctrl-Break there.
"""

from __future__ import annotations

import signal
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from types import FrameType
from typing import Any

#: the stop signals and what each one means to the operator (only those the platform defines are installed)
SIGNAL_MEANINGS: dict[str, str] = {
    "SIGINT": "interrupted by the operator (Ctrl-C)",
    "SIGTERM": "stopped by SIGTERM (termination request: kill, systemd or a batch scheduler)",
    "SIGHUP": "stopped by SIGHUP (the terminal or SSH session that started the run hung up)",
    "SIGQUIT": "stopped by SIGQUIT (quit request, Ctrl-\\)",
    "SIGBREAK": "stopped by SIGBREAK (Ctrl-Break)",
}
#: stop signals whose inherited "ignore" is kept: SIGHUP, which `nohup` ignores so that a run outlives its
#: terminal. SIGINT is taken over even when ignored: a shell starts background jobs (`cmd &`) with SIGINT ignored,
#: and Ctrl-C or `kill -INT` must still stop the campaign safely
KEPT_IF_IGNORED: frozenset[int] = frozenset({int(signal.SIGHUP)} if hasattr(signal, "SIGHUP") else set())
STOP_SIGNALS: tuple[signal.Signals, ...] = tuple(
    getattr(signal, name) for name in SIGNAL_MEANINGS if hasattr(signal, name)
)


def signal_reason(signum: int) -> str:
    """The abort reason for a stop signal, naming it (e.g. "stopped by SIGTERM (...)")."""
    try:
        name = signal.Signals(signum).name
    except ValueError:
        return f"stopped by signal {signum}"
    return SIGNAL_MEANINGS.get(name, f"stopped by {name}")


def exit_code(signum: int) -> int:
    """The process's exit code after a stop signal: 128 + its number (SIGINT 130, SIGTERM 143, SIGHUP 129)."""
    return 128 + int(signum)


class StopRequested(KeyboardInterrupt):
    """A second stop signal: raised where it cannot wait (outside protected sections). `signum` names it."""

    def __init__(self, signum: int) -> None:
        super().__init__(signal_reason(signum))
        self.signum = int(signum)


class InterruptGuard:
    """Install with `with InterruptGuard() as guard:`; check `guard.requested`; wrap writes in `guard.protect()`.

    `signum` is the first stop signal received (None before one); `reason()` names it. Nested guards are
    allowed: an inner one installs its handlers and puts the outer ones back on exit.
    """

    def __init__(self) -> None:
        self.requested = False
        self.signum: int | None = None
        self._count = 0
        self._protect_depth = 0
        self._pending: int | None = None
        self._previous: dict[int, Callable[[int, FrameType | None], Any] | int | None] = {}
        self._installed = False

    def __enter__(self) -> InterruptGuard:
        if threading.current_thread() is threading.main_thread():
            for sig in STOP_SIGNALS:
                try:
                    if sig in KEPT_IF_IGNORED and signal.getsignal(sig) is signal.SIG_IGN:
                        continue  # ignored by whoever started the run (nohup): it stays ignored
                    self._previous[sig] = signal.signal(sig, self._handle)
                except (OSError, ValueError):  # a signal this process may not catch here
                    continue
            self._installed = True
        return self

    def __exit__(self, *exc: object) -> None:
        if self._installed:
            for sig, previous in self._previous.items():
                signal.signal(sig, previous)
            self._previous.clear()
            self._installed = False

    def reason(self) -> str:
        """The abort reason of the stop request (Ctrl-C's if none was received: a KeyboardInterrupt)."""
        return signal_reason(self.signum if self.signum is not None else signal.SIGINT)

    def exit_code(self) -> int:
        """128 + the first stop signal's number (130 if none was received)."""
        return exit_code(self.signum if self.signum is not None else signal.SIGINT)

    def _handle(self, signum: int, frame: FrameType | None) -> None:
        self._count += 1
        self.requested = True
        if self.signum is None:
            self.signum = int(signum)
        if self._count >= 2:
            if self._protect_depth > 0:
                self._pending = int(signum)
            else:
                raise StopRequested(signum)

    @contextmanager
    def protect(self) -> Iterator[None]:
        """A section a second stop signal must not cut (it is raised when the section ends)."""
        self._protect_depth += 1
        try:
            yield
        finally:
            self._protect_depth -= 1
            if self._protect_depth == 0 and self._pending is not None:
                pending, self._pending = self._pending, None
                raise StopRequested(pending)
