"""What every command module of the CLI shares: the consoles, the exit codes, the common arguments, and the three
steps most commands take (fail with a message, load the configuration, connect the station).

The command modules (main.py and bench.py, device.py, files.py, runs.py, watch.py) import from here, never from
each other; main.py builds the app and registers each module's commands explicitly (`register(app)`).

Exit codes: 0 done; 2 bad input (configuration, file, arguments: a message naming what is wrong, no traceback);
3 instrument fault (safe state reached); 130 interrupted (safe state reached); 128 + n after stop signal n.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Annotated, NoReturn

import typer
from rich.console import Console
from rich.markup import escape

from qmg_lab.cli.signals import say
from qmg_lab.config.schema import Config, ConfigError, load_config, stream_timing_problem
from qmg_lab.instruments import InstrumentError, Station

console = Console(stderr=True)
out = Console()

EXIT_BAD_INPUT, EXIT_FAULT, EXIT_INTERRUPTED = 2, 3, 130

ConfigArg = Annotated[Path, typer.Argument(help="campaign configuration (TOML)", show_default=False)]
SimOpt = Annotated[bool, typer.Option("--sim", help="use every instrument's simulated twin")]
JsonOpt = Annotated[bool, typer.Option("--json", help="print one JSON object on stdout")]
OutputOpt = Annotated[Path | None, typer.Option("-o", "--output", help="run file to write (HDF5)")]
QuietOpt = Annotated[bool, typer.Option("--quiet", "-q", help="no live progress")]

#: `qmg-lab characterize ...`: main.py's campaign characterizations (bandwidth, linearity) and device.py's
#: device measurements (resonance, ringdown, noise) share this group
characterize_app = typer.Typer(
    no_args_is_help=True,
    help="FTR characterization: bandwidth (Fig. 3), linearity (Fig. 2); the device: resonance, ringdown, noise",
)


def fail(code: int, message: str) -> NoReturn:
    # the message is text, not markup: "[plan]" or "[-100, 100] deg/s" must reach the operator as written
    say(console.print, f"[bold red]error:[/] {escape(message)}", highlight=False, markup=True)
    raise typer.Exit(code)


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
def connected_station(cfg: Config) -> Iterator[Station]:
    """Build the station; on the way out every instrument is made safe and closed."""
    from qmg_lab.station import build_station

    try:
        station = build_station(cfg)
    except ConfigError as exc:
        fail(EXIT_BAD_INPUT, str(exc))
    except (InstrumentError, OSError) as exc:
        fail(EXIT_FAULT, f"could not connect the station: {exc}")
    try:
        yield station
    finally:
        station.close()
