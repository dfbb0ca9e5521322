"""`qmg-lab watch RUN.h5`: the live page of a run file (qmg_lab/watch/; docs/watch.md), and `run --watch`'s
helper that starts it beside a campaign in its own process."""

from __future__ import annotations

import subprocess
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Annotated

import typer

from qmg_lab.cli.common import (
    EXIT_BAD_INPUT,
    console,
    fail,
)

LOOPBACK = "127.0.0.1"  # also qmg_lab.watch.server.LOOPBACK; repeated so that `run` need not import Bokeh
OPEN_WARNING = (
    "warning: the page is open to every machine that can reach {host}:{port}, without a password; it shows "
    "the run and changes nothing. Use the default (127.0.0.1) unless the lab network needs it."
)


def _check_run_file(path: Path) -> None:
    """Refuse (exit 2, in words) what is not a readable run file, as every reader does (`open_run_file`)."""
    from qmg_lab.storage.layout import StorageError
    from qmg_lab.storage.runfile import check_structure

    try:
        check_structure(path)
    except StorageError as exc:
        fail(EXIT_BAD_INPUT, str(exc))


def watch(
    run_file: Annotated[Path, typer.Argument(help="run file (HDF5, qmg-lab/1 or /2)", show_default=False)],
    host: Annotated[
        str, typer.Option("--host", help="address to listen on; anything but 127.0.0.1 opens the page to the network")
    ] = LOOPBACK,
    port: Annotated[int, typer.Option("--port", help="TCP port (the next free one if taken)")] = 5006,
    wait: Annotated[bool, typer.Option("--wait", hidden=True, help="the run file may not exist yet")] = False,
) -> None:
    """A live page of a run file in the browser: SF, gain, temperatures, table, drive, PLL, plan and events
    against run time. Follows a running campaign; replays a finished, aborted or resumed one. Read-only."""
    if not wait:
        _check_run_file(run_file)
    from qmg_lab.watch.server import free_port, make_server, url

    if host != LOOPBACK:
        console.print(OPEN_WARNING.format(host=host, port=port), style="yellow")
    try:
        chosen = free_port(host, port)
        server = make_server(run_file, host, chosen)
    except OSError as exc:
        fail(EXIT_BAD_INPUT, f"cannot listen on {host}:{port}: {exc}")
    print(f"watching {run_file} at {url(host, chosen)}  (Ctrl-C stops the page, not the run)", flush=True)
    try:
        server.io_loop.start()
    except KeyboardInterrupt:
        console.print("watch stopped")


@contextmanager
def watch_beside(path: Path | None) -> Iterator[None]:
    """`qmg-lab run --watch`: `qmg-lab watch path` in its own process for as long as the run goes on (path None:
    nothing). The page's address is printed on stderr when the page is up."""
    if path is None:
        yield
        return
    proc = subprocess.Popen(
        [sys.executable, "-m", "qmg_lab", "watch", str(path), "--wait"],
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        text=True,
    )
    line = proc.stdout.readline().strip() if proc.stdout is not None else ""
    if line.startswith("watching"):
        console.print(line.split("  (")[0].replace("watching", "live page of", 1))
    else:
        console.print("the live page did not start; the run goes on without it", style="yellow")
    try:
        yield
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        console.print(f"live page closed; replay the run with: qmg-lab watch {path}")


def register(app: typer.Typer) -> None:
    """Add `qmg-lab watch` to the app (qmg_lab.cli.main)."""
    app.command()(watch)
