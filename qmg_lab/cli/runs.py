"""`qmg-lab runs DIR`: the run files of a folder, one row each (qmg_lab/data/summary.py reads them).

On a terminal the rows are a table; when stdout is not a terminal (a pipe, a file) they are tab-separated values,
one line per file with a header line, so that `qmg-lab runs DIR | grep aborted` finds whole rows. `--where KEY=VALUE`
keeps the rows whose KEY (a key of the --json rows: operator, device_serial, status, name, kind, ...) equals VALUE,
ignoring case; given more than once, every condition must hold."""

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


#: the tab-separated columns when stdout is not a terminal: (header, row key)
TSV_COLUMNS = (
    ("file", "file"),
    ("status", "status"),
    ("config", "name"),
    ("start_utc", "created"),
    ("length_s", "duration_s"),
    ("steps_completed", "steps_completed"),
    ("steps_planned", "steps_planned"),
    ("sf_ppm", "sf_change_60s_ppm"),
    ("faults", "faults"),
    ("operator", "operator"),
    ("device_serial", "device_serial"),
)


def _conditions(where: list[str]) -> list[tuple[str, str]]:
    """KEY=VALUE pairs; a condition without "=" is bad input (exit 2)."""
    pairs = []
    for w in where:
        key, eq, value = w.partition("=")
        if not eq or not key.strip():
            fail(EXIT_BAD_INPUT, f"--where {w!r}: give KEY=VALUE, e.g. --where operator=ada")
        pairs.append((key.strip(), value.strip()))
    return pairs


def _selected(rows: list[dict[str, Any]], where: list[tuple[str, str]]) -> list[dict[str, Any]]:
    """The rows whose every KEY equals VALUE (text compared without case); unreadable files have no keys."""
    if not where:
        return rows
    known = set().union(*(r.keys() for r in rows)) if rows else set()
    unknown = sorted({k for k, _ in where} - known)
    if rows and unknown:
        fail(EXIT_BAD_INPUT, f"--where: no key {', '.join(unknown)}; the keys are {', '.join(sorted(known))}")
    return [r for r in rows if all(k in r and str(r[k]).casefold() == v.casefold() for k, v in where)]


def _tsv(rows: list[dict[str, Any]]) -> str:
    """Header and one line per row; tabs and newlines inside a value become spaces, a missing value is empty."""

    def cell(v: Any) -> str:
        if v is None or (isinstance(v, float) and not math.isfinite(v)):
            return ""
        return " ".join(str(v).split())

    lines = ["\t".join(h for h, _ in TSV_COLUMNS)]
    lines += ["\t".join(cell(r.get(k)) for _, k in TSV_COLUMNS) for r in rows]
    return "\n".join(lines)


def runs(
    folder: Annotated[Path, typer.Argument(help="folder of run files (*.h5)", show_default=False)],
    json_out: JsonOpt = False,
    where: Annotated[
        list[str] | None,
        typer.Option("--where", help="keep rows whose KEY equals VALUE (KEY=VALUE, e.g. operator=ada); repeatable"),
    ] = None,
) -> None:
    """List the run files of a folder: status, configuration, start, duration and headline results (SF ppm: the
    CLSF SF-change estimate's mean over the last 60 s of run time)."""
    from qmg_lab.data.summary import json_rows, list_runs

    if not folder.is_dir():
        fail(EXIT_BAD_INPUT, f"{folder}: no such folder")
    conditions = _conditions(where or [])
    rows = _selected(list_runs(folder), conditions)
    if json_out:
        out.print_json(json_rows(rows))
        return
    if not out.is_terminal:
        typer.echo(_tsv(rows))
        return
    # compact enough for 80 columns; kind, CLSF mode, g_c and the chamber temperature are in --json
    tab = Table(title=f"run files in {folder}", box=None, padding=(0, 1), header_style="bold")
    tab.add_column("file", no_wrap=True)
    for col in ("status", "config"):
        tab.add_column(col, overflow="fold")
    tab.add_column("start (UTC)", no_wrap=True)
    for col in ("length", "steps", "SF ppm", "faults"):
        tab.add_column(col, justify="right", no_wrap=True)
    tab.add_column("operator", overflow="fold")
    for r in rows:
        if "name" not in r:
            tab.add_row(Path(r["file"]).name, "unreadable (--json says why)", *["-"] * 7)
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
            r.get("operator") or "-",
        )
    if not rows:
        out.print(f"no run files (*.h5) in {folder}" + (" that match --where" if conditions else ""))
        return
    out.print(tab)


def register(app: typer.Typer) -> None:
    """Add `qmg-lab runs` to the app (qmg_lab.cli.main)."""
    app.command()(runs)
