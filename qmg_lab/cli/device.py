"""Device characterisation and tuning commands of `qmg-lab` (qmg_lab/campaign/tuning.py, docs/bench-bringup.md).

characterize resonance/ringdown/noise and tune: they connect the whole station (the loops, the table and the
chamber all take part), end in the safe state, and exit 3 on an instrument fault or a failed measurement.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from typing import Annotated, Any

import typer
from rich.markup import escape
from rich.table import Table

from qmg_lab.cli.common import (
    EXIT_BAD_INPUT,
    EXIT_FAULT,
    ConfigArg,
    JsonOpt,
    SimOpt,
    characterize_app,
    connected_station,
    fail,
    load,
    out,
)
from qmg_lab.config.schema import Config, ConfigError
from qmg_lab.instruments import InstrumentError, LimitError, Station


def _print_result(data: dict[str, Any], json_out: bool, title: str) -> None:
    if json_out:
        out.print_json(json.dumps(data, default=float))
        return
    tbl = Table(title=title, show_header=False)
    tbl.add_column("what")
    tbl.add_column("value", justify="right")
    for k, v in data.items():
        if isinstance(v, dict):
            for k2, v2 in v.items():
                if not isinstance(v2, list):
                    tbl.add_row(f"{k}.{k2}", f"{v2:.7g}" if isinstance(v2, float) else str(v2))
        elif not isinstance(v, list):
            tbl.add_row(k, f"{v:.7g}" if isinstance(v, float) else str(v))
    out.print(tbl)


def _measure(config: Path, sim: bool, what: Callable[[Config, Station], dict[str, Any]]) -> dict[str, Any]:
    """Connect the station, run one characterisation, leave it safe; exit 3 on an instrument fault."""
    from qmg_lab.campaign.tuning import TuningError

    cfg, _ = load(config, sim)
    with connected_station(cfg) as st:
        try:
            return what(cfg, st)
        except LimitError as exc:
            st.safe_state()
            fail(EXIT_BAD_INPUT, str(exc))
        except (TuningError, InstrumentError) as exc:
            failures = st.safe_state()
            fail(
                EXIT_FAULT,
                f"{exc}"
                + (
                    f"; safe state not confirmed: {'; '.join(failures)}"
                    if failures
                    else "; instruments in their safe state"
                ),
            )
        finally:
            st.safe_state()
    raise AssertionError("unreachable")


@characterize_app.command("resonance")
def characterize_resonance(
    config: ConfigArg,
    sim: SimOpt = False,
    json_out: JsonOpt = False,
    record_s: Annotated[float, typer.Option("--record", help="s of locked record")] = 20.0,
) -> None:
    """f0 from the locked PLL and the drive voltage the AGC needs for the setpoint amplitude."""
    from dataclasses import asdict

    from qmg_lab.campaign.tuning import measure_resonance

    if not 1.0 <= record_s <= 3600.0:
        fail(EXIT_BAD_INPUT, f"--record {record_s:g} s: must lie in [1, 3600] s")
    data = _measure(config, sim, lambda cfg, st: asdict(measure_resonance(cfg, st, record_s)))
    _print_result(data, json_out, "resonance")


@characterize_app.command("ringdown")
def characterize_ringdown(
    config: ConfigArg,
    sim: SimOpt = False,
    json_out: JsonOpt = False,
    record_s: Annotated[
        float | None, typer.Option("--record", help="s of free decay (default: the configured tau)")
    ] = None,
) -> None:
    """Drive off, free decay of the drive amplitude: tau and Q = pi f0 tau."""
    from dataclasses import asdict

    from qmg_lab.campaign.tuning import measure_resonance, measure_ringdown

    if record_s is not None and not 5.0 <= record_s <= 36000.0:
        fail(EXIT_BAD_INPUT, f"--record {record_s:g} s: must lie in [5, 36000] s")

    def what(cfg: Config, st: Station) -> dict[str, Any]:
        res = measure_resonance(cfg, st, 5.0)
        return asdict(measure_ringdown(cfg, st, res.f0_hz, record_s))

    _print_result(_measure(config, sim, what), json_out, "ring-down")


@characterize_app.command("noise")
def characterize_noise(
    config: ConfigArg,
    sim: SimOpt = False,
    json_out: JsonOpt = False,
    record_s: Annotated[float, typer.Option("--record", help="s of static record")] = 1800.0,
) -> None:
    """Static record with the loops closed: ARW and bias instability from the Allan deviation."""
    from dataclasses import asdict

    from qmg_lab.campaign.tuning import measure_noise

    if not 60.0 <= record_s <= 7 * 86400.0:
        fail(EXIT_BAD_INPUT, f"--record {record_s:g} s: must lie in [60, 604800] s")
    _print_result(_measure(config, sim, lambda cfg, st: asdict(measure_noise(cfg, st, record_s))), json_out, "noise")


def tune(
    config: ConfigArg,
    output: Annotated[Path, typer.Option("-o", "--output", help="the tuned configuration to write (TOML)")],
    sim: SimOpt = False,
    json_out: JsonOpt = False,
    overwrite: Annotated[bool, typer.Option("--overwrite", help="replace an existing -o file")] = False,
) -> None:
    """Measure f0, Q, the drive voltage and the nominal SF; write them into the device section of a new
    configuration."""
    from qmg_lab.campaign.tuning import header_lines, tuned_config_text
    from qmg_lab.campaign.tuning import tune as run_tuning
    from qmg_lab.config.schema import parse_config

    if output.exists() and not overwrite:
        fail(EXIT_BAD_INPUT, f"{output} exists: choose another -o or add --overwrite")
    if output.resolve() == config.resolve():
        fail(EXIT_BAD_INPUT, f"-o {output} is the configuration itself: write the tuned one to a new file")
    _, text = load(config, sim)
    result = _measure(config, sim, lambda cfg, st: {"tuning": run_tuning(cfg, st)})["tuning"]
    tuned = tuned_config_text(text, result.device_values(), header_lines(result, config.name))
    try:
        parse_config(tuned, str(output))
    except ConfigError as exc:
        fail(EXIT_FAULT, f"the measured constants do not make a valid configuration: {exc}")
    try:
        output.write_text(tuned, encoding="utf-8")
    except OSError as exc:
        fail(EXIT_BAD_INPUT, f"cannot write {output}: {exc}")
    data = result.as_dict()
    data["file"] = str(output)
    _print_result(data, json_out, escape(f"tuned [device] written to {output}"))


def register(app: typer.Typer) -> None:
    """Add `qmg-lab tune` to the app (qmg_lab.cli.main)."""
    app.command()(tune)
