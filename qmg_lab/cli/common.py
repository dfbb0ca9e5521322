"""What every command module of the CLI shares: the consoles, the exit codes, the common arguments, and the three
steps most commands take (fail with a message, load the configuration, connect the station).

The command modules (main.py and bench.py, device.py, files.py, runs.py, watch.py) import from here, never from
each other; main.py builds the app and registers each module's commands explicitly (`register(app)`).

Exit codes: 0 done; 2 bad input (configuration, file, arguments: a message naming what is wrong, no traceback);
3 instrument fault (safe state reached); 130 interrupted (safe state reached); 128 + n after stop signal n.
"""

from __future__ import annotations

import sys
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Annotated, Any, NoReturn

import typer
from rich.markup import escape

from qmg_lab.cli.signals import SteadyConsole, say
from qmg_lab.config.schema import Config, ConfigError, load_config, stream_timing_problem
from qmg_lab.instruments import InstrumentError, Station

console = SteadyConsole(stderr=True)  # a broken pipe turns it off, never ends the process (cli/signals.py)
out = SteadyConsole()

#: what an unencodable character becomes on a console or redirected stream that cannot encode it (a Windows
#: console or file in cp1252 has no ≤, µ or −): its escape (\u2264), never a UnicodeEncodeError
STREAM_ERRORS = "backslashreplace"


def tolerant_streams() -> None:
    """Make stdout and stderr write every character: keep each stream's encoding (the console's code page, or
    what PYTHONIOENCODING says), replace what it cannot encode by its backslash escape
    (io.TextIOWrapper.reconfigure). Called once at the start of the command line."""
    for stream in (sys.stdout, sys.stderr):
        reconfigure = getattr(stream, "reconfigure", None)  # a TextIOWrapper; not a test runner's capture
        if reconfigure is not None:
            reconfigure(errors=STREAM_ERRORS)


EXIT_BAD_INPUT, EXIT_FAULT, EXIT_INTERRUPTED = 2, 3, 130

ConfigArg = Annotated[Path, typer.Argument(help="campaign configuration (TOML)", show_default=False)]

FLAG_METAVAR = ""  # typer's rich help shows an option's metavar in place of its type; a flag has none


def flag(*names: str, help: str) -> Any:
    """A boolean option that takes no value (`--sim`, not `--sim true`), shown in --help without a value: typer's
    help writes a bool option's type as `<bool>`, which reads as if it took one; an empty metavar shows none."""
    return typer.Option(*names, help=help, metavar=FLAG_METAVAR)


SimOpt = Annotated[bool, flag("--sim", help="use every instrument's simulated twin")]
JsonOpt = Annotated[bool, flag("--json", help="print one JSON object on stdout")]
OutputOpt = Annotated[Path | None, typer.Option("-o", "--output", help="run file to write (HDF5)")]
QuietOpt = Annotated[bool, flag("--quiet", "-q", help="no live progress")]

#: `qmg-lab characterize ...`: main.py's campaign characterizations (bandwidth, linearity) and device.py's
#: device measurements (resonance, ringdown, noise) share this group
characterize_app = typer.Typer(
    no_args_is_help=True,
    help="FTR characterization: bandwidth (Fig. 3), linearity (Fig. 2); the device: resonance, ringdown, noise",
)


def fail(code: int, message: str) -> NoReturn:
    # the message is text, not markup: "[plan]" or "[-100, 100] deg/s" must reach the operator as written; and
    # soft-wrapped (the terminal folds it, no newline is written into it), so a long path in it copies whole
    say(console.print, f"[bold red]error:[/] {escape(message)}", highlight=False, markup=True, soft_wrap=True)
    raise typer.Exit(code)


def warn_network_share(run_file: Path) -> None:
    """Warn on stderr when the run file's folder is on a network file system (qmg_lab/storage/network_share.py:
    HDF5 SWMR needs POSIX write semantics); the run goes on."""
    from qmg_lab.storage.network_share import swmr_warning

    warning = swmr_warning(run_file)
    if warning is not None:
        say(console.print, f"[bold yellow]warning:[/] {escape(warning)}", highlight=False, markup=True, soft_wrap=True)


def load(path: Path, sim: bool, campaign: bool = False) -> tuple[Config, str]:
    """The configuration (every instrument a twin with --sim); campaign=True: also the CLSF's stream timing."""
    try:
        cfg, text = load_config(path)
    except ConfigError as exc:
        fail(EXIT_BAD_INPUT, str(exc))
    cfg = cfg.with_all_sim() if sim else cfg
    if campaign:
        problem = stream_timing_problem(cfg)
        if problem is not None:
            fail(EXIT_BAD_INPUT, f"{path}: {problem}")
    return cfg, text


@contextmanager
def connected_station(cfg: Config, realtime: bool = False) -> Iterator[Station]:
    """Build the station; on the way out every instrument is made safe and closed. realtime: the lock-in twin
    paced to the wall clock (`run --sim --realtime`, a rehearsal: qmg_lab.station.RealTimePacing)."""
    from qmg_lab.station import RealTimePacing, build_station

    if realtime and not cfg.lockin.sim:
        fail(EXIT_BAD_INPUT, "--realtime paces the lock-in twin, and [lockin] sim is false: hardware runs in real time")
    try:
        station = build_station(cfg, pacing=RealTimePacing() if realtime else None)
    except ConfigError as exc:
        fail(EXIT_BAD_INPUT, str(exc))
    except (InstrumentError, OSError) as exc:
        fail(EXIT_FAULT, f"could not connect the station: {exc}")
    try:
        yield station
    finally:
        station.close()
