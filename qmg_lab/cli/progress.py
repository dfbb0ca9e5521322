"""Live progress of a running campaign: a rich panel on a terminal, a line every few seconds otherwise."""

from __future__ import annotations

import contextlib
import time

from rich.console import Console
from rich.live import Live
from rich.table import Table

from qmg_lab.campaign.runner import Progress

REFRESH_S = 0.25  # terminal panel refresh
LINE_EVERY_S = 10.0  # plain-text line interval (logs, CI)


def _fmt_s(seconds: float) -> str:
    seconds = max(0.0, seconds)
    h, rem = divmod(int(round(seconds)), 3600)
    m, s = divmod(rem, 60)
    return f"{h:d}:{m:02d}:{s:02d}"


class ProgressView:
    """Context manager; `update(progress)` is called by the campaign after every block."""

    def __init__(self, console: Console, enabled: bool = True) -> None:
        self.console = console
        self.enabled = enabled
        self.live: Live | None = None
        self._last = 0.0

    def __enter__(self) -> ProgressView:
        if self.enabled and self.console.is_terminal:
            self.live = Live(console=self.console, refresh_per_second=4, transient=True)
            self.live.__enter__()
        return self

    def __exit__(self, *exc: object) -> None:
        if self.live is not None:
            live, self.live = self.live, None
            with contextlib.suppress(OSError, ValueError):  # a dead terminal: not the run's outcome's business
                live.__exit__(None, None, None)

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
        now = time.monotonic()
        if now - self._last < (REFRESH_S if self.live is not None else LINE_EVERY_S):
            return
        self._last = now
        remaining = p.planned_s - p.done_s
        rate = p.run_time_s / max(p.wall_s, 1e-9)
        if self.live is not None:
            self.live.update(self._panel(p, remaining, rate))
        else:
            self.console.print(
                f"step {p.step.index + 1}/{p.n_steps} {p.step.kind} {p.step_elapsed_s:.0f}/{p.step.duration_s:.0f} s"
                f" | chamber {p.chamber_c:.2f} (sp {p.chamber_setpoint_c:.2f}) degC"
                f" | table {p.table_rate_dps:+.3f} deg/s | SF change {p.sf_change_ppm:+.1f} ppm"
                f" | elapsed {_fmt_s(p.run_time_s)} remaining {_fmt_s(remaining)}"
                f" | {rate:.0f}x{' | SUSPENDED: ' + p.suspended if p.suspended else ''}",
                highlight=False,
            )

    @staticmethod
    def _panel(p: Progress, remaining: float, rate: float) -> Table:
        t = Table(show_header=False, title="qmg-lab run", expand=False)
        t.add_column("", style="bold")
        t.add_column("")
        t.add_row(
            "step", f"{p.step.index + 1}/{p.n_steps}  {p.step.kind}  {p.step_elapsed_s:.0f}/{p.step.duration_s:.0f} s"
        )
        t.add_row("chamber", f"{p.chamber_c:.3f} degC (setpoint {p.chamber_setpoint_c:.3f})")
        t.add_row("table", f"{p.table_rate_dps:+.4f} deg/s")
        t.add_row("CLSF SF change", f"{p.sf_change_ppm:+.1f} ppm   gain {p.gain_correction:.6f}")
        t.add_row("elapsed / remaining", f"{_fmt_s(p.run_time_s)} / {_fmt_s(remaining)}   ({rate:.0f}x real time)")
        if p.suspended:
            t.add_row("[red]suspended[/]", p.suspended)
        return t
