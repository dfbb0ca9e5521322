"""Bring-up commands of `qmg-lab` (docs/bench-bringup.md): each connects only the instrument it drives.

table rate/stop/raw, chamber setpoint/raw, generator square/mute/raw, lockin get/set. The raw consoles print
exactly the bytes sent and received with their timing (qmg_lab/cli/raw_console.py). Exit codes as everywhere:
2 bad input, 3 instrument fault (the instrument put in its safe state where it was connected).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Annotated, Any

import typer

from qmg_lab.cli.common import (
    EXIT_BAD_INPUT,
    EXIT_FAULT,
    ConfigArg,
    SimOpt,
    fail,
    load,
    out,
)
from qmg_lab.instruments import InstrumentError, LimitError

table_app = typer.Typer(no_args_is_help=True, help="Bring-up: drive the rate table by hand")
chamber_app = typer.Typer(no_args_is_help=True, help="Bring-up: set the thermal chamber by hand")
generator_app = typer.Typer(no_args_is_help=True, help="Bring-up: set the DS345 by hand")
lockin_app = typer.Typer(no_args_is_help=True, help="Bring-up: read and write HF2 nodes by hand")


def register(app: typer.Typer) -> None:
    """Add the bring-up groups to the `qmg-lab` app (qmg_lab.cli.main)."""
    app.add_typer(table_app, name="table")
    app.add_typer(chamber_app, name="chamber")
    app.add_typer(generator_app, name="generator")
    app.add_typer(lockin_app, name="lockin")


@contextmanager
def _bring_up(config: Path, sim: bool, name: str) -> Iterator[Any]:
    """Connect only the instrument `name` (a bench where only it is cabled can bring it up); on a fault it
    is put in its safe state and the command exits 3."""
    from qmg_lab.station import connect_instrument

    cfg, _ = load(config, sim)
    try:
        conn = connect_instrument(cfg, name)
    except (InstrumentError, OSError) as exc:
        fail(EXIT_FAULT, f"could not connect the {name}: {exc}")
    try:
        yield conn.instrument
    except LimitError as exc:
        fail(EXIT_BAD_INPUT, str(exc))
    except InstrumentError as exc:
        try:
            conn.instrument.safe_state()
        except Exception as again:
            fail(EXIT_FAULT, f"{exc}; safe state not confirmed: {again}")
        fail(EXIT_FAULT, str(exc))
    finally:
        conn.close()


# ====================================================================================== bring-up
# click reads every token that starts with "-" as an option, so `table rate CONFIG -5` needed `--`. The commands whose
# arguments after CONFIG are all numbers take an unknown "option" as an argument instead: "-5" and "-1e-3" are
# numbers, and anything else ("--acel") still fails as a number with exit 2 and the argument named.
NEGATIVE_NUMBERS = {"ignore_unknown_options": True}


def _manual(config: Path, sim: bool, name: str, action: Callable[[Any], str]) -> None:
    with _bring_up(config, sim, name) as inst:
        out.print(action(inst))


@table_app.command("rate", context_settings=NEGATIVE_NUMBERS)
def table_rate(
    config: ConfigArg,
    rate_dps: Annotated[float, typer.Argument(help="deg/s")],
    accel_dps2: Annotated[float, typer.Option("--accel", help="deg/s^2")] = 100.0,
    sim: SimOpt = False,
) -> None:
    """Rate mode: ramp to RATE_DPS."""

    def act(table: Any) -> str:
        table.set_rate(rate_dps, accel_dps2)
        r = table.read()
        return f"table commanded to {rate_dps:g} deg/s at {accel_dps2:g} deg/s^2; now {r.rate_dps:.4f} deg/s"

    _manual(config, sim, "table", act)


@table_app.command("stop")
def table_stop(config: ConfigArg, sim: SimOpt = False) -> None:
    """Decelerate the table to rest."""

    def act(table: Any) -> str:
        table.stop()
        r = table.read()
        return f"table stopping; now {r.rate_dps:.4f} deg/s"

    _manual(config, sim, "table", act)


@chamber_app.command("setpoint", context_settings=NEGATIVE_NUMBERS)
def chamber_setpoint(
    config: ConfigArg,
    setpoint_c: Annotated[float, typer.Argument(help="deg C")],
    ramp_c_per_min: Annotated[float, typer.Option("--ramp", help="deg C/min")] = 1.0,
    sim: SimOpt = False,
) -> None:
    """Ramp the chamber to SETPOINT_C."""

    def act(chamber: Any) -> str:
        chamber.set_setpoint(setpoint_c, ramp_c_per_min)
        r = chamber.read()
        return f"chamber setpoint {setpoint_c:g} degC at {ramp_c_per_min:g} degC/min; air {r.temperature_c:.2f} degC"

    _manual(config, sim, "chamber", act)


@generator_app.command("square", context_settings=NEGATIVE_NUMBERS)
def generator_square(
    config: ConfigArg,
    frequency_hz: Annotated[float, typer.Argument(help="Hz")],
    amplitude_vpp: Annotated[float, typer.Argument(help="Vpp")],
    sim: SimOpt = False,
) -> None:
    """DS345 square wave."""

    def act(generator: Any) -> str:
        generator.set_square(frequency_hz, amplitude_vpp, 0.0)
        return f"DS345 square {frequency_hz:g} Hz {amplitude_vpp:g} Vpp"

    _manual(config, sim, "generator", act)


@generator_app.command("mute")
def generator_mute(config: ConfigArg, sim: SimOpt = False) -> None:
    """DS345 amplitude to zero (AMPL 0VP: it has no output switch)."""

    def act(generator: Any) -> str:
        generator.mute()
        return "DS345 muted"

    _manual(config, sim, "generator", act)


# ====================================================================================== raw console
RawCommand = Annotated[
    str, typer.Argument(help="the command as text; backslash escapes (\\r, \\n, \\xNN) allowed", show_default=False)
]
WaitOpt = Annotated[
    float | None, typer.Option("--wait", help="wait this long for a first byte, s (default: the configured timeout_s)")
]
IdleOpt = Annotated[float, typer.Option("--idle", help="the reply is over after this long without a byte, s")]
NoTermOpt = Annotated[bool, typer.Option("--no-terminator", help="do not append the configured command terminator")]


def _raw_serial(
    name: str, config: Path, command: str, sim: bool, wait_s: float | None, idle_s: float, no_terminator: bool
) -> None:
    from qmg_lab.cli.raw_console import decode_escapes, serial_exchange
    from qmg_lab.station import open_raw_serial

    cfg, _ = load(config, sim)
    try:
        data = decode_escapes(command)
    except ValueError as exc:
        fail(EXIT_BAD_INPUT, str(exc))
    if not data:
        fail(EXIT_BAD_INPUT, "the command is empty")
    if wait_s is not None and not 0 < wait_s <= 60:
        fail(EXIT_BAD_INPUT, f"--wait {wait_s:g} s: must be > 0 and <= 60 s")
    if not 0 < idle_s <= 10:
        fail(EXIT_BAD_INPUT, f"--idle {idle_s:g} s: must be > 0 and <= 10 s")
    section = getattr(cfg, name)
    try:
        port, framing, close, at_once = open_raw_serial(cfg, name)
    except (InstrumentError, OSError) as exc:
        fail(EXIT_FAULT, f"could not open the {name}'s port: {exc}")
    try:
        if not no_terminator:
            data += framing.command_end
        where = "twin" if section.sim else section.port
        out.print(
            f"{name} raw on {where} ({section.baudrate} baud; command terminator "
            f"{framing.command_terminator}, replies {framing.describe()})",
            highlight=False,
            markup=False,
            soft_wrap=True,
        )
        ex = serial_exchange(port, data, wait_s=wait_s or section.timeout_s, idle_s=idle_s, answers_at_once=at_once)
    except (OSError, ValueError) as exc:
        fail(EXIT_FAULT, f"{name}: the raw exchange failed: {exc}")
    finally:
        close()
    for line in ex.render():
        out.print(line, highlight=False, markup=False, soft_wrap=True)


@table_app.command("raw")
def table_raw(
    config: ConfigArg,
    command: RawCommand,
    sim: SimOpt = False,
    wait_s: WaitOpt = None,
    idle_s: IdleOpt = 0.3,
    no_terminator: NoTermOpt = False,
) -> None:
    """Send COMMAND to the 1291BR as typed (+ the command terminator); print the bytes sent and received."""
    _raw_serial("table", config, command, sim, wait_s, idle_s, no_terminator)


@chamber_app.command("raw")
def chamber_raw(
    config: ConfigArg,
    command: RawCommand,
    sim: SimOpt = False,
    wait_s: WaitOpt = None,
    idle_s: IdleOpt = 0.3,
    no_terminator: NoTermOpt = False,
) -> None:
    """Send COMMAND to the chamber controller as typed (+ the command terminator); print the bytes."""
    _raw_serial("chamber", config, command, sim, wait_s, idle_s, no_terminator)


@generator_app.command("raw")
def generator_raw(
    config: ConfigArg,
    command: Annotated[str, typer.Argument(help="e.g. '*IDN?' or 'FREQ 7'", show_default=False)],
    sim: SimOpt = False,
) -> None:
    """Send COMMAND to the DS345 (a query, with '?', reads one reply); print the bytes and the timing."""
    from qmg_lab.cli.raw_console import visa_exchange
    from qmg_lab.station import open_raw_visa

    cfg, _ = load(config, sim)
    if not command.strip():
        fail(EXIT_BAD_INPUT, "the command is empty")
    try:
        resource, close = open_raw_visa(cfg)
    except (InstrumentError, OSError) as exc:
        fail(EXIT_FAULT, f"could not open the generator: {exc}")
    try:
        ex = visa_exchange(resource, command)
    except Exception as exc:
        fail(EXIT_FAULT, f"generator: {command!r}: {type(exc).__name__}: {exc}")
    finally:
        close()
    for line in ex.render():
        out.print(line, highlight=False, markup=False, soft_wrap=True)


NodePath = Annotated[
    str, typer.Argument(help="node path, e.g. oscs/0/freq (the /devN prefix is added)", show_default=False)
]


def _node_path(path: str, device: str) -> str:
    p = path.strip().lower()
    if not p or any(ch.isspace() for ch in p):
        fail(EXIT_BAD_INPUT, f"node path {path!r} is empty or contains blanks")
    return p if p.startswith("/dev") else f"/{device}/{p.lstrip('/')}"


def _raw_node(config: Path, sim: bool, path: str, value: str | None) -> None:
    from qmg_lab.cli.raw_console import node_get, node_set
    from qmg_lab.station import open_raw_hf2

    cfg, _ = load(config, sim)
    try:
        connection, device, close = open_raw_hf2(cfg)
    except (InstrumentError, OSError) as exc:
        fail(EXIT_FAULT, f"could not reach the HF2: {exc}")
    node = _node_path(path, device)
    try:
        ex, _ = node_get(connection, node) if value is None else node_set(connection, node, value)
    except Exception as exc:
        fail(EXIT_BAD_INPUT if "not" in str(exc).lower() else EXIT_FAULT, f"HF2 {node}: {exc}")
    finally:
        close()
    for t, d, p in ex.lines:
        out.print(f"{t * 1e3:10.1f} ms  {d} {p}", highlight=False, markup=False, soft_wrap=True)


@lockin_app.command("get")
def lockin_get(config: ConfigArg, path: NodePath, sim: SimOpt = False) -> None:
    """Read one HF2 node through the data server; print the call, the value and the time it took."""
    _raw_node(config, sim, path, None)


@lockin_app.command("set")
def lockin_set(
    config: ConfigArg,
    path: NodePath,
    value: Annotated[str, typer.Argument(help="integer, number or text", show_default=False)],
    sim: SimOpt = False,
) -> None:
    """Write one HF2 node, then read it back; print both calls and their timing."""
    _raw_node(config, sim, path, value)
