"""`qmg-lab watch RUN.h5`: the live page of a run file (qmg_lab/watch/; docs/watch.md), and `run --watch`'s
helper that starts it beside a campaign in its own process."""

from __future__ import annotations

import subprocess
import sys
import threading
from collections.abc import Iterator
from contextlib import contextmanager, suppress
from pathlib import Path
from typing import Annotated

import typer

from qmg_lab.cli.common import (
    EXIT_BAD_INPUT,
    console,
    fail,
)

LOOPBACK = "127.0.0.1"  # also qmg_lab.watch.server.LOOPBACK; repeated so that `run` need not import Bokeh
DEFAULT_PORT = 5006  # also qmg_lab.watch.server.DEFAULT_PORT
#: `run --watch`: how long the final page stays up after the run has ended (s), unless Ctrl-C closes it sooner:
#: long enough to walk back to the bench and read how it ended
DEFAULT_LINGER_S = 1800.0
OPEN_WARNING = (
    "warning: the page is open to every machine that can reach {host}:{port}, without a password; it shows "
    "the run and changes nothing. Use the default (127.0.0.1) unless the lab network needs it."
)


def _check_run_file(path: Path) -> None:
    """Refuse (exit 2) what is not a readable run file, in the words `analyze` uses: both ask the same guarded
    open (`open_run_file`'s structure check)."""
    from qmg_lab.cli.files import damaged_file_report
    from qmg_lab.storage.layout import DamagedFileError, StorageError
    from qmg_lab.storage.runfile import check_structure

    if not path.is_file():
        fail(EXIT_BAD_INPUT, f"{path}: no such run file")
    try:
        check_structure(path)
    except DamagedFileError as exc:
        fail(EXIT_BAD_INPUT, damaged_file_report(path, str(exc)))
    except StorageError as exc:
        fail(EXIT_BAD_INPUT, str(exc))


def watch(
    run_file: Annotated[Path, typer.Argument(help="run file (HDF5, qmg-lab/1 or /2)", show_default=False)],
    host: Annotated[
        str, typer.Option("--host", help="address to listen on; anything but 127.0.0.1 opens the page to the network")
    ] = LOOPBACK,
    port: Annotated[int, typer.Option("--port", help="TCP port (the next free one if taken)")] = 5006,
    wait: Annotated[bool, typer.Option("--wait", hidden=True, help="the run file may not exist yet")] = False,
    linger_after_stdin: Annotated[
        float | None,
        typer.Option(
            "--linger-after-stdin",
            hidden=True,
            help="run --watch: once stdin closes (the run's process ended, however), serve this many s more, then stop",
        ),
    ] = None,
) -> None:
    """A live page of a run file in the browser: what is happening now (status, SF change, temperatures, PLL
    lock, step, expected end, faults), then SF, gain, temperatures, table, drive, PLL, plan and events against
    run time. Follows a running campaign; replays a finished, aborted or resumed one. Read-only."""
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
    if linger_after_stdin is not None:
        _stop_after_stdin_closes(server.io_loop, linger_after_stdin)
    try:
        server.io_loop.start()
    except KeyboardInterrupt:
        console.print("watch stopped")


def _stop_after_stdin_closes(loop: object, linger_s: float) -> None:
    """Stop the server's IO loop `linger_s` s after stdin reaches its end: the pipe from `run --watch`'s process
    closes when that process ends, normally or killed (a thread blocks on the read, on Linux and Windows alike)."""

    def read_to_end() -> None:
        with suppress(OSError, ValueError):
            sys.stdin.read()
        loop.add_callback(lambda: loop.call_later(max(linger_s, 0.0), loop.stop))  # type: ignore[attr-defined]

    threading.Thread(target=read_to_end, name="qmg-lab watch: run process", daemon=True).start()


@contextmanager
def watch_beside(path: Path | None, port: int = DEFAULT_PORT, linger_s: float = DEFAULT_LINGER_S) -> Iterator[None]:
    """`qmg-lab run --watch`: `qmg-lab watch path` in its own process (path None: nothing). The page's address is
    printed on stderr when the page is up. After the run the page stays up with the final status for `linger_s`
    s, or until Ctrl-C. The page's process is in its own process group, so the Ctrl-C that stops the run does not
    stop the page; its stdin is a pipe from this process, so that if this process is killed the page still stops
    `linger_s` s later (qmg-lab watch --linger-after-stdin)."""
    if path is None:
        yield
        return
    group = (
        {"creationflags": subprocess.CREATE_NEW_PROCESS_GROUP}  # type: ignore[attr-defined]
        if sys.platform == "win32"
        else {"start_new_session": True}
    )
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "qmg_lab",
            "watch",
            str(path),
            "--wait",
            "--port",
            str(port),
            "--linger-after-stdin",
            repr(float(linger_s)),
        ],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        text=True,
        **group,
    )
    line = proc.stdout.readline().strip() if proc.stdout is not None else ""
    address = ""
    if line.startswith("watching"):
        address = line.split(" at ", 1)[1].split()[0]
        console.print(f"live page of {path} at {address}")
    else:
        console.print("the live page did not start; the run goes on without it", style="yellow")
    try:
        yield
    finally:
        _close_stdin(proc)  # the run has ended: the page stops itself linger_s s from now
        if address and proc.poll() is None and linger_s > 0:
            console.print(
                f"the live page stays at {address} with the run's final status for {linger_s:g} s; Ctrl-C closes it now"
            )
            with suppress(subprocess.TimeoutExpired, KeyboardInterrupt):
                proc.wait(timeout=linger_s + 10.0)
        if proc.poll() is None:
            proc.terminate()
            try:
                proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
        console.print(f"live page closed; replay the run with: qmg-lab watch {path}")


def _close_stdin(proc: subprocess.Popen[str]) -> None:
    if proc.stdin is not None:
        with suppress(OSError):
            proc.stdin.close()


def register(app: typer.Typer) -> None:
    """Add `qmg-lab watch` to the app (qmg_lab.cli.main)."""
    app.command()(watch)
