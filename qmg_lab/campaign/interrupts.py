"""Deferred Ctrl-C: a campaign stops between blocks, never half-way through a write.

The first SIGINT sets a flag that the campaign checks between lock-in blocks (it then brings every instrument to
its safe state and marks the file "aborted"). A second SIGINT raises KeyboardInterrupt at once, unless a protected
section (an HDF5 write) is running: then it is raised when the section ends.
"""

from __future__ import annotations

import signal
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from types import FrameType
from typing import Any


class InterruptGuard:
    """Install with `with InterruptGuard() as guard:`; check `guard.requested`; wrap writes in `guard.protect()`."""

    def __init__(self) -> None:
        self.requested = False
        self._count = 0
        self._protect_depth = 0
        self._pending = False
        self._previous: Callable[[int, FrameType | None], Any] | int | None = None
        self._installed = False

    def __enter__(self) -> InterruptGuard:
        if threading.current_thread() is threading.main_thread():
            self._previous = signal.signal(signal.SIGINT, self._handle)
            self._installed = True
        return self

    def __exit__(self, *exc: object) -> None:
        if self._installed:
            signal.signal(signal.SIGINT, self._previous)
            self._installed = False

    def _handle(self, signum: int, frame: FrameType | None) -> None:
        self._count += 1
        self.requested = True
        if self._count >= 2:
            if self._protect_depth > 0:
                self._pending = True
            else:
                raise KeyboardInterrupt

    @contextmanager
    def protect(self) -> Iterator[None]:
        """A section a second Ctrl-C must not cut (it is raised when the section ends)."""
        self._protect_depth += 1
        try:
            yield
        finally:
            self._protect_depth -= 1
            if self._protect_depth == 0 and self._pending:
                self._pending = False
                raise KeyboardInterrupt
