"""`qmg-lab runs DIR`: the run files of a folder, one row each (qmg_lab/data/summary.py reads them)."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Annotated, Any

import typer
from rich.table import Table

from qmg_lab.cli.common import (
    EXIT_BAD_INPUT,
    JsonOpt,
    fail,
    out,
)


def _fmt(v: Any, fmt: str) -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "-"
    return fmt.format(v)


def _duration(s: Any) -> str:
    if not isinstance(s, float) or not math.isfinite(s):
        return "-"
    h, rem = divmod(int(round(s)), 3600)
    return f"{h}:{rem // 60:02d}:{rem % 60:02d}"


def runs(
    folder: Annotated[Path, typer.Argument(help="folder of run files (*.h5)", show_default=False)],
    json_out: JsonOpt = False,
) -> None:
    """List the run files of a folder: status, configuration, start, duration and headline results (SF ppm: the
    CLSF SF-change estimate's mean over the last 60 s of run time)."""
    from qmg_lab.data.summary import json_rows, list_runs

    if not folder.is_dir():
        fail(EXIT_BAD_INPUT, f"{folder}: no such folder")
    rows = list_runs(folder)
    if json_out:
        out.print_json(json_rows(rows))
        return
    # compact enough for 80 columns; kind, CLSF mode, g_c and the chamber temperature are in --json
    tab = Table(title=f"run files in {folder}", box=None, padding=(0, 1), header_style="bold")
    tab.add_column("file", no_wrap=True)
    for col in ("status", "config"):
        tab.add_column(col, overflow="fold")
    tab.add_column("start (UTC)", no_wrap=True)
    for col in ("length", "steps", "SF ppm", "faults"):
        tab.add_column(col, justify="right", no_wrap=True)
    for r in rows:
        if "name" not in r:
            tab.add_row(Path(r["file"]).name, "unreadable (--json says why)", *["-"] * 6)
            continue
        planned = r["steps_planned"]
        tab.add_row(
            Path(r["file"]).name,
            r["status"] + (f", resumed {r['resume_count']}x" if r["resume_count"] else ""),
            r["name"],
            r["created"].replace("T", " ").removesuffix("Z")[:16],
            _duration(r["duration_s"]),
            f"{r['steps_completed']}/{planned if planned >= 0 else '?'}",
            _fmt(r["sf_change_60s_ppm"], "{:+.1f}"),
            str(r["faults"]),
        )
    if not rows:
        out.print(f"no run files (*.h5) in {folder}")
        return
    out.print(tab)


def register(app: typer.Typer) -> None:
    """Add `qmg-lab runs` to the app (qmg_lab.cli.main)."""
    app.command()(runs)
