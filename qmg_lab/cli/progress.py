"""Live progress of a running campaign: a rich panel on a terminal, a line every few seconds otherwise.

The SF figure is a 60 s moving mean: one dither period's estimate scatters by hundreds of ppm (about 690 ppm RMS
on the paper's configuration), so the view averages the latest estimate of every block over the last 60 s of
run time (30 blocks on the twins' 2 s blocks, 120 on hardware at 0.5 s) and says so.

The first run in a fresh environment spends its first blocks in numba, compiling the numerical kernels (the
twins' before the first block, the CLSF's when its first dither periods arrive; cached afterwards). While one of
the first `COMPILE_BLOCKS` blocks has been awaited longer than `COMPILE_NOTICE_AFTER_S`, the view says so, with
the expected duration, instead of showing "0x real time" in silence.
"""

from __future__ import annotations

import contextlib
import threading
import time
from collections.abc import Callable

from rich.console import Console, Group, RenderableType
from rich.live import Live
from rich.table import Table

from qmg_lab.campaign.runner import Progress
from qmg_lab.clsf.moving_mean import SF_MEAN_WINDOW_S, MovingMean

REFRESH_S = 1.0  # terminal panel refresh, s: the live panel is rebuilt and redrawn once a second (a redraw costs
# about 1.5 % of a core at 4 a second on a real-time run: benchmarks/realtime_cpu.py)
LINE_EVERY_S = 10.0  # plain-text line interval (logs, CI)
COMPILE_NOTICE_AFTER_S = 3.0  # wall time waiting for a block before the view says why, s
COMPILE_BLOCKS = 20  # the blocks during which numba may still be compiling (a later wait is not a compile)
# with a cold numba cache (a fresh environment) a short twin campaign took 87 s longer than with a warm one on a
# loaded 2-core machine (33 s of CPU; the issue saw 40-70 s); later runs load the kernels from the cache at once
FIRST_RUN_COMPILE = "about a minute, 40-90 s"


def _fmt_s(seconds: float) -> str:
    seconds = max(0.0, seconds)
    h, rem = divmod(int(round(seconds)), 3600)
    m, s = divmod(rem, 60)
    return f"{h:d}:{m:02d}:{s:02d}"


def compile_notice(waited_s: float, first: bool) -> str:
    """Why nothing has happened for `waited_s`, in words."""
    return (
        f"waiting {waited_s:.0f} s for the {'first' if first else 'next'} block: numba is compiling the numerical "
        f"kernels (the first run in a fresh environment takes {FIRST_RUN_COMPILE}; later runs load them from "
        "its cache)"
    )


class ProgressView:
    """Context manager; `update(progress)` is called by the campaign after every block."""

    def __init__(self, console: Console, enabled: bool = True, clock: Callable[[], float] = time.monotonic) -> None:
        self.console = console
        self.enabled = enabled
        self.live: Live | None = None
        self._last = 0.0
        self._clock = clock
        self._last_block = clock()  # wall clock of the last block (or of the start)
        self._blocks = 0
        self._timer: threading.Timer | None = None
        self._shown: Table | None = None
        self.sf_mean = MovingMean(SF_MEAN_WINDOW_S)

    def __enter__(self) -> ProgressView:
        self._last_block = self._clock()
        if self.enabled and self.console.is_terminal:
            self.live = Live(self, console=self.console, refresh_per_second=1.0 / REFRESH_S, transient=True)
            self.live.__enter__()
        elif self.enabled:
            self._arm_notice()
        return self

    def _arm_notice(self) -> None:
        """Line mode: print the compile notice once if the next block is late (only the first blocks)."""
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None
        if self._blocks < COMPILE_BLOCKS:
            self._timer = threading.Timer(COMPILE_NOTICE_AFTER_S, self._print_notice)
            self._timer.daemon = True
            self._timer.start()

    def __exit__(self, *exc: object) -> None:
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None
        if self.live is not None:
            live, self.live = self.live, None
            with contextlib.suppress(OSError, ValueError):  # a dead terminal: not the run's outcome's business
                live.__exit__(None, None, None)

    def __rich__(self) -> RenderableType:
        """What the live panel shows (rendered by its refresh thread): the last panel and the compile notice."""
        notice = self.waiting_text()
        if self._shown is None:
            return notice or "starting the campaign ..."
        return Group(self._shown, notice) if notice else self._shown

    def waiting_text(self) -> str:
        """The compile notice while one of the first blocks is late, else ""."""
        waited = self._clock() - self._last_block
        if self._blocks >= COMPILE_BLOCKS or waited < COMPILE_NOTICE_AFTER_S:
            return ""
        return compile_notice(waited, first=self._blocks == 0)

    def _print_notice(self) -> None:
        notice = self.waiting_text()
        if notice:
            with contextlib.suppress(OSError, ValueError):  # a dead terminal: the campaign goes on
                self.console.print(notice, highlight=False)

    def update(self, p: Progress) -> None:
        """Show the progress; a console write that fails (a dead terminal after SIGHUP, a full or closed stdout
        or stderr) turns the view off, and the campaign goes on."""
        if not self.enabled:
            return
        try:
            self._show(p)
        except (OSError, ValueError):
            self.enabled = False

    def _show(self, p: Progress) -> None:
        self._blocks += 1
        self._last_block = self._clock()
        if self.live is None:
            self._arm_notice()
        self.sf_mean.add(p.run_time_s, p.sf_change_ppm)
        now = self._clock()
        if now - self._last < (REFRESH_S if self.live is not None else LINE_EVERY_S):
            return
        self._last = now
        remaining = p.planned_s - p.done_s
        rate = p.run_time_s / max(p.wall_s, 1e-9)
        if self.live is not None:
            self._shown = self._panel(p, remaining, rate)  # the Live display renders it through __rich__
        else:
            self.console.print(
                f"step {p.step.index + 1}/{p.n_steps} {p.step.kind} {p.step_elapsed_s:.0f}/{p.step.duration_s:.0f} s"
                f" | chamber {p.chamber_c:.2f} (sp {p.chamber_setpoint_c:.2f}) degC"
                f" | table {p.table_rate_dps:+.3f} deg/s | SF change {self.sf_text()}"
                f" | elapsed {_fmt_s(p.run_time_s)} remaining {_fmt_s(remaining)}"
                f" | {rate:.0f}x{' | SUSPENDED: ' + p.suspended if p.suspended else ''}",
                highlight=False,
            )

    def sf_text(self) -> str:
        """The SF change as the panel shows it: the 60 s mean and how many block estimates it holds."""
        if not self.sf_mean.count:
            return "- (no CLSF estimate yet)"
        return f"{self.sf_mean.mean:+.1f} ppm ({SF_MEAN_WINDOW_S:.0f} s mean of {self.sf_mean.count})"

    def _panel(self, p: Progress, remaining: float, rate: float) -> Table:
        t = Table(show_header=False, title="qmg-lab run", expand=False)
        t.add_column("", style="bold")
        t.add_column("")
        t.add_row(
            "step", f"{p.step.index + 1}/{p.n_steps}  {p.step.kind}  {p.step_elapsed_s:.0f}/{p.step.duration_s:.0f} s"
        )
        t.add_row("chamber", f"{p.chamber_c:.3f} degC (setpoint {p.chamber_setpoint_c:.3f})")
        t.add_row("table", f"{p.table_rate_dps:+.4f} deg/s")
        t.add_row("CLSF SF change", f"{self.sf_text()}   gain {p.gain_correction:.6f}")
        t.add_row("elapsed / remaining", f"{_fmt_s(p.run_time_s)} / {_fmt_s(remaining)}   ({rate:.0f}x real time)")
        if p.suspended:
            t.add_row("[red]suspended[/]", p.suspended)
        return t
