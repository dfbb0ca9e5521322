"""What `qmg-lab run` says and returns when it is asked to stop, and how it survives a dead terminal.

* Exit codes after a stop signal: 128 + the signal's number (qmg_lab.campaign.interrupts.exit_code): Ctrl-C 130,
  SIGHUP 129, SIGQUIT 131, SIGTERM 143, Windows' SIGBREAK 149.
* The last words about the safe state repeat the run file's `safe_state` event word for word
  (qmg_lab.campaign.pipeline.safe_state_words), so the terminal never says "safe" when the file says "not confirmed".
* A dead terminal (SIGHUP, a closed SSH session: writes fail with EIO), a full stdout/stderr (ENOSPC) or a reader
  that went away (EPIPE: `qmg-lab run ... | head -1`) never changes how a campaign ends: a console write that fails
  is dropped (`say`); the CLI's consoles are `SteadyConsole`s, which turn themselves off on a broken pipe where
  rich's Console raises SystemExit(1) (`Console.on_broken_pipe`); and at exit the standard streams are pointed at
  the null device if they cannot be flushed (`settle_streams`), so Python's own final flush does not turn the exit
  code into 120.
"""

from __future__ import annotations

import contextlib
import os
import sys
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any

import typer
from rich.console import Console


class SteadyConsole(Console):
    """A rich Console whose broken pipe turns it off instead of ending the process: rich's `on_broken_pipe`
    points stdout at the null device and raises SystemExit(1), which would abort a campaign because its output's
    reader went away. Here the console goes quiet and its own stream is pointed at the null device."""

    def on_broken_pipe(self) -> None:
        self.quiet = True
        with contextlib.suppress(OSError, ValueError, AttributeError):
            null = os.open(os.devnull, os.O_WRONLY)
            os.dup2(null, self.file.fileno())
            os.close(null)


def say(print_: Callable[..., Any], *args: Any, **kwargs: Any) -> None:
    """Call a console's print; a write that fails (dead terminal, full device, closed pipe) is dropped."""
    with contextlib.suppress(OSError, ValueError):  # ValueError: the stream was closed
        print_(*args, **kwargs)


def settle_streams() -> None:
    """Flush stdout and stderr; a stream that cannot be written any more is replaced by the null device."""
    for name in ("stdout", "stderr"):
        stream = getattr(sys, name)
        try:
            stream.flush()
        except (OSError, ValueError, AttributeError):
            try:
                null = os.open(os.devnull, os.O_WRONLY)
                os.dup2(null, stream.fileno())
                os.close(null)
            except (OSError, ValueError, AttributeError):
                setattr(sys, name, None)


@contextmanager
def stop_exits(console_print: Callable[..., Any]) -> Iterator[None]:
    """A second stop signal that ends the command where it cannot wait (StopRequested) exits 128 + its number
    with its reason said (typer would make every KeyboardInterrupt exit 130)."""
    from qmg_lab.campaign.interrupts import StopRequested, exit_code

    try:
        yield
    except StopRequested as exc:
        say(console_print, f"error: {exc}", highlight=False, markup=False, soft_wrap=True)
        raise typer.Exit(exit_code(exc.signum)) from None
