"""Damaged run files on the command line: `qmg-lab salvage`, and what `qmg-lab analyze` says about a file it
cannot read (qmg_lab/storage/salvage.py does the reading)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from qmg_lab.cli.common import (
    EXIT_BAD_INPUT,
    console,
    fail,
)
from qmg_lab.cli.signals import say


def damaged_file_report(path: Path, problem: str) -> str:
    """The analysis's error, then what of the file still reads and what does not (qmg_lab.storage.salvage.scan),
    and how to copy what reads."""
    from qmg_lab.storage.layout import StorageError
    from qmg_lab.storage.salvage import scan_isolated

    try:
        rows = scan_isolated(path)
    except StorageError as exc:
        return f"{problem}\nnothing of it can be read: {exc}"
    ok = [r for r in rows if r.complete]
    partial = [r for r in rows if not r.complete]
    lines = [problem, f"what still reads ({len(ok)} of {len(rows)} datasets whole):"]
    lines += [f"  {r.name}: {r.rows} rows" for r in ok]
    if partial:
        lines.append("what does not:")
        lines += [
            f"  {r.name}: {r.rows_read} of {r.rows} rows read; {r.error or 'the rest is missing'}" for r in partial
        ]
    lines.append(f"copy what reads into a new file: qmg-lab salvage {path} -o NEW.h5, then qmg-lab analyze NEW.h5")
    return "\n".join(lines)


def salvage(
    run_file: Annotated[Path, typer.Argument(help="damaged run file (HDF5, qmg-lab/1 or /2)", show_default=False)],
    output: Annotated[Path, typer.Option("-o", "--output", help="new file for what still reads", show_default=False)],
) -> None:
    """Copy what still reads of a damaged run file (cut short, or with chunks that do not decode) into a new
    file of the same layout; the damaged file is not changed."""
    from qmg_lab.storage.layout import StorageError
    from qmg_lab.storage.salvage import salvage_isolated as salvage_file

    if not run_file.is_file():
        fail(EXIT_BAD_INPUT, f"{run_file}: no such run file")
    try:
        rows = salvage_file(run_file, output)
    except StorageError as exc:
        fail(EXIT_BAD_INPUT, str(exc))
    except OSError as exc:
        fail(EXIT_BAD_INPUT, f"cannot write {output}: {exc}")
    for r in rows:
        state = "whole" if r.complete else f"{r.rows_read} of {r.rows} rows ({r.error or 'cut short'})"
        say(console.print, f"{r.name}: {state}", highlight=False, markup=False)
    say(console.print, f"salvaged into {output}", highlight=False, markup=False)


def register(app: typer.Typer) -> None:
    """Add `qmg-lab salvage` to the app (qmg_lab.cli.main)."""
    app.command()(salvage)
