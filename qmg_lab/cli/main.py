"""The `qmg-lab` command line (the README's commands; docs/architecture.md).

Exit codes: 0 done; 2 bad input (configuration, file, arguments: a message naming what is wrong, no traceback);
3 instrument fault (safe state reached); 130 interrupted (safe state reached).

This module builds the typer app, holds the campaign commands (check, run, instruments, characterize, analyze,
study, budget), each a thin layer over the package that does the work, and registers the other modules'
commands explicitly: bench.py (bring-up), device.py (device characterization, tune), files.py (salvage),
runs.py, watch.py. What they share is in common.py; none of them imports this module.
"""

from __future__ import annotations

import json
import logging
import sys
import tempfile
from datetime import UTC, datetime
from pathlib import Path
from typing import Annotated, Any

import typer
from rich.markup import escape
from rich.table import Table

from qmg_lab import __version__
from qmg_lab.cli import bench, device, files, heap, runs, sfcal, watch
from qmg_lab.cli.common import (
    EXIT_BAD_INPUT,
    EXIT_FAULT,
    EXIT_INTERRUPTED,
    ConfigArg,
    JsonOpt,
    OutputOpt,
    QuietOpt,
    SimOpt,
    characterize_app,
    console,
    fail,
    flag,
    load,
    out,
    tolerant_streams,
    warn_network_share,
)
from qmg_lab.cli.signals import say, settle_streams, stop_exits
from qmg_lab.config.schema import NOTES_MAX_CHARS, Config, config_fingerprint
from qmg_lab.instruments import INSTRUMENT_NAMES, InstrumentError

app = typer.Typer(
    add_completion=False,
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    help="Closed-loop scale-factor self-calibration campaigns for MEMS gyroscopes (HF2LI, DS345, "
    "1291BR), on the bench or on simulated twins.",
)
app.add_typer(characterize_app, name="characterize")

log = logging.getLogger(__name__)

LOG_LEVELS = ("DEBUG", "INFO", "WARNING", "ERROR")


@app.callback()
def _options(
    ctx: typer.Context,
    log_level: Annotated[
        str | None,
        typer.Option(
            "--log-level",
            help="print the module loggers on stderr from this level: DEBUG (every serial byte), "
            "INFO (connections, reconnects, run events), WARNING (faults), ERROR",
        ),
    ] = None,
) -> None:
    """Options for every command."""
    if ctx.invoked_subcommand != "run":  # `run` settles once its station is up (_execute)
        heap.settle()
    if log_level is None:
        return
    level = log_level.upper()
    if level not in LOG_LEVELS:
        fail(EXIT_BAD_INPUT, f"--log-level {log_level!r}: one of {', '.join(LOG_LEVELS)}")
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
    for name in ("qmg_lab", "drivers"):
        logger = logging.getLogger(name)
        logger.setLevel(level)
        logger.addHandler(handler)


# ====================================================================================== check
@app.command()
def check(config: ConfigArg, json_out: JsonOpt = False) -> None:
    """Validate a configuration, show the plan, its duration and every command against the limits."""
    from qmg_lab.campaign.plan import build_plan, limit_checks, plan_duration_s
    from qmg_lab.clsf.stream_plan import StreamPlan

    cfg, text = load(config, False, campaign=True)
    steps = build_plan(cfg)
    checks = limit_checks(cfg, steps)
    bad = [c for c in checks if not c.ok]
    stream = StreamPlan(
        cfg.lockin.demod_rate_hz, cfg.dither.frequency_hz, cfg.lockin.demod_order, cfg.lockin.demod_timeconstant_s
    )
    if json_out:
        out.print_json(
            json.dumps(
                {
                    "clsf_timing": stream.summary() if cfg.clsf.mode != "off" else None,
                    "config": str(config),
                    "config_sha256": config_fingerprint(text),
                    "kind": cfg.campaign.kind,
                    "steps": [{**s.__dict__, "kind": s.label} for s in steps],
                    "duration_s": plan_duration_s(steps),
                    "limits": [
                        dict(what=c.what, value=c.value, low=c.low, high=c.high, unit=c.unit, ok=c.ok) for c in checks
                    ],
                }
            )
        )
    else:
        tbl = Table(
            title=f"{cfg.campaign.name}: {cfg.campaign.kind}, {len(steps)} steps, {plan_duration_s(steps) / 3600:.2f} h"
        )
        for col in ("#", "kind", "duration", "table rate", "chamber target"):
            tbl.add_column(col, justify="right" if col != "kind" else "left")
        for s in _summarise_steps(steps):
            tbl.add_row(*s)
        out.print(tbl)
        lim = Table(title="limits")
        for col in ("check", "value", "allowed", "ok"):
            lim.add_column(col)
        for c in checks:
            lim.add_row(
                c.what,
                f"{c.value:g} {c.unit}",
                f"[{c.low:g}, {c.high:g}] {c.unit}",
                "[green]ok[/]" if c.ok else "[bold red]REFUSED[/]",
            )
        out.print(lim)
        instruments = ", ".join(f"{n}: {mode}" for n, mode in cfg.instrument_modes().items())
        out.print(f"instruments: {instruments}")
        if cfg.clsf.mode != "off":
            sp = stream.summary()
            out.print(
                f"CLSF timing: lock-in {sp['rate_hz']:g} Sa/s, {sp['samples_per_period']:.4f} samples per "
                f"{cfg.dither.frequency_hz:g} Hz dither period (edge phase gap {sp['edge_phase_gap']:.3f} of a "
                f"sample, must be <= 0.25); demod filter order {cfg.lockin.demod_order}, "
                f"tc {cfg.lockin.demod_timeconstant_s * 1e6:g} us: delay {sp['filter_delay_s'] * 1e6:g} us, "
                f"|H| at 1/3/5 x dither {sp['filter_gain_h1']:.5f}/{sp['filter_gain_h3']:.5f}/"
                f"{sp['filter_gain_h5']:.5f} (compensated by the estimator)"
            )
    if bad:
        fail(EXIT_BAD_INPUT, "the plan breaks instrument limits: " + "; ".join(c.describe() for c in bad))


def _summarise_steps(steps: list[Any]) -> list[tuple[str, ...]]:
    """Rows for the plan table; long runs of alternating rate steps are folded into one row."""
    rows: list[tuple[str, ...]] = []
    i = 0
    while i < len(steps):
        s = steps[i]
        j = i
        while (
            j + 1 < len(steps)
            and steps[j + 1].kind == s.kind
            and s.kind in ("rate", "hold")
            and abs(steps[j + 1].table_rate_dps) == abs(s.table_rate_dps)
            and steps[j + 1].chamber_target_c == s.chamber_target_c
        ):
            j += 1
        n = j - i + 1
        rate = f"{s.table_rate_dps:+g} deg/s" if n == 1 else f"+-{abs(s.table_rate_dps):g} deg/s"
        dur = f"{s.duration_s:.4g} s" if n == 1 else f"{n} x {s.duration_s:.4g} s"
        rows.append(
            (
                f"{s.index}" if n == 1 else f"{s.index}-{steps[j].index}",
                s.label,
                dur,
                rate,
                f"{s.chamber_target_c:g} degC",
            )
        )
        i = j + 1
    return rows


# ====================================================================================== run
def _default_output(cfg: Config) -> Path:
    stamp = datetime.now(UTC).strftime("%Y%m%dT%H%M%SZ")
    safe = "".join(ch if ch.isalnum() or ch in "-_" else "_" for ch in cfg.campaign.name)
    return Path("runs") / f"{safe}-{stamp}.h5"


@app.command()
def run(
    config: ConfigArg,
    sim: SimOpt = False,
    output: OutputOpt = None,
    resume: Annotated[Path | None, typer.Option("--resume", help="continue this run file")] = None,
    quiet: QuietOpt = False,
    overwrite: Annotated[bool, typer.Option("--overwrite", help="replace an existing -o file")] = False,
    watch_page: Annotated[
        bool, typer.Option("--watch", help="a live page of the run in the browser (127.0.0.1)")
    ] = False,
    realtime: Annotated[
        bool, flag("--realtime", help="pace the twins at wall-clock speed: a rehearsal of the bench's timing")
    ] = False,
    port: Annotated[
        int, typer.Option("--port", help="with --watch: the page's TCP port (the next free one if taken)")
    ] = watch.DEFAULT_PORT,
    watch_linger: Annotated[
        float,
        typer.Option(
            "--watch-linger",
            help="with --watch: seconds the page stays up with the final status after the run (Ctrl-C closes it)",
        ),
    ] = watch.DEFAULT_LINGER_S,
    note: Annotated[str, typer.Option("--note", help="why this run: a note stored in the new file")] = "",
) -> None:
    """Run a campaign, with live progress and a summary at the end."""
    from qmg_lab.cli.watch import watch_beside

    if len(note) > NOTES_MAX_CHARS:
        fail(EXIT_BAD_INPUT, f"--note has {len(note)} characters; at most {NOTES_MAX_CHARS} are stored")
    if note and resume is not None:
        fail(EXIT_BAD_INPUT, "--note is a new run's note; a resumed run keeps the note it was started with")
    cfg, text = load(config, sim, campaign=True)
    if watch_page and resume is None and output is None:
        output = _default_output(cfg)  # the page needs the file's name before the run makes it
    with watch_beside((resume or output) if watch_page else None, port, watch_linger):
        summary = _execute(
            cfg, text, output=output, resume=resume, quiet=quiet, overwrite=overwrite, realtime=realtime, note=note
        )
        _print_summary(summary)  # before the page's linger


def _execute(
    cfg: Config,
    text: str,
    *,
    output: Path | None,
    resume: Path | None,
    quiet: bool,
    overwrite: bool = False,
    realtime: bool = False,
    note: str = "",
) -> Any:
    """Run a campaign into a new file or resume one through the one pipeline (qmg_lab.campaign.pipeline.run_campaign:
    every check that needs no instrument first, the file's lock, the stop signals, the station, the file, its close
    and its read-back; docs/reliability.md). This adds the progress view and turns the run's end into the exit code
    and its words: 0 only if the closed file holds the whole run."""
    from qmg_lab.campaign.pipeline import RunHooks, run_campaign
    from qmg_lab.cli.progress import ProgressView

    if resume is not None and output is not None and output.resolve() != resume.resolve():
        fail(EXIT_BAD_INPUT, f"--resume {resume} and -o {output} name different files")
    if realtime and not cfg.lockin.sim:
        fail(EXIT_BAD_INPUT, "--realtime paces the lock-in twin, and [lockin] sim is false: hardware runs in real time")
    path = resume if resume is not None else (output or _default_output(cfg))
    warn_network_share(path)  # HDF5 SWMR on a network share: readers may see a stale file
    view = ProgressView(console, enabled=not quiet)

    def file_open(writer: Any) -> None:
        log.info("run file %s; instruments %s", writer.path, cfg.instrument_modes())
        heap.settle()  # start-up is over: the campaign makes garbage from here on (qmg_lab.cli.heap)

    with stop_exits(console.print):
        end = run_campaign(
            cfg,
            text,
            path,
            resume=resume is not None,
            overwrite=overwrite,
            realtime=realtime,
            note=note,
            hooks=RunHooks(progress=view.update, view=view, file_open=file_open),
        )
    if not end.ok:
        fail(end.exit_code, end.message)
    return end.summary


def _print_summary(summary: Any) -> None:
    tbl = Table(title=f"run {summary.status}", show_header=False)
    tbl.add_column("what")
    tbl.add_column("value", justify="right")
    rows = [
        ("file", summary.path),
        ("steps", f"{summary.steps_completed} / {summary.steps_planned}"),
        ("simulated / run time", f"{summary.simulated_s:.1f} s"),
        ("wall time", f"{summary.wall_s:.1f} s ({summary.simulated_s / max(summary.wall_s, 1e-9):.0f}x real time)"),
        ("samples", f"{summary.samples} ({summary.samples_lost} lost)"),
        ("suspensions / recoveries", f"{summary.suspensions} / {summary.recoveries}"),
        ("CLSF SF change, last 60 s mean", f"{summary.sf_change_mean_ppm:.1f} ppm"),
        ("CLSF gain correction", f"{summary.gain_correction:.6f}"),
    ]
    for r in rows:
        tbl.add_row(*r)
    say(out.print, tbl)


# ====================================================================================== instruments
@app.command()
def instruments(config: ConfigArg, sim: SimOpt = False, json_out: JsonOpt = False) -> None:
    """Connect each instrument on its own, identify it and show its state; exit 3 if any failed."""
    from qmg_lab.station import connect_instrument

    cfg, _ = load(config, sim)
    report: dict[str, dict[str, Any]] = {}
    for name in INSTRUMENT_NAMES:
        entry: dict[str, Any] = {"simulated": bool(getattr(cfg, name).sim)}
        try:
            conn = connect_instrument(cfg, name)
        except (InstrumentError, OSError) as exc:
            entry.update(identity=None, state=None, ok=False, error=f"could not connect: {exc}")
            report[name] = entry
            continue
        try:
            entry["identity"] = conn.instrument.identify()
            entry["state"] = conn.instrument.state()
            entry["ok"] = True
        except InstrumentError as exc:
            entry.update(identity=entry.get("identity"), state=None, ok=False, error=str(exc))
        finally:
            conn.close()
        report[name] = entry
    if json_out:
        out.print_json(json.dumps(report, default=str))
    else:
        tbl = Table(title="instruments")
        for col in ("instrument", "simulated", "identity", "state"):
            tbl.add_column(col)
        for name, e in report.items():
            state = e.get("error") or ", ".join(f"{k}={v}" for k, v in list((e.get("state") or {}).items())[:6])
            identity = e["identity"] or "(not identified)"  # never a bare None in the table
            tbl.add_row(name, "twin" if e["simulated"] else "hardware", str(identity), state)
        out.print(tbl)
    failed = [n for n, e in report.items() if not e["ok"]]
    if failed:
        fail(EXIT_FAULT, "could not connect or identify: " + "; ".join(f"{n} ({report[n]['error']})" for n in failed))


# ====================================================================================== characterize
def _characterize(kind: str, config: Path, sim: bool, json_out: bool, output: Path | None, quiet: bool) -> None:
    from qmg_lab.analysis.compute import analyze
    from qmg_lab.config.edit import with_values  # tomlkit: only characterize rewrites the configuration's text

    cfg, text = load(config, sim, campaign=True)
    text = with_values(text, {"campaign.kind": kind})
    cfg = cfg.model_copy(update={"campaign": cfg.campaign.model_copy(update={"kind": kind})})
    tmp = None
    if output is None:
        tmp = tempfile.TemporaryDirectory(prefix="qmg-lab-")
        output = Path(tmp.name) / f"{kind}.h5"
    try:
        _execute(cfg, text, output=output, resume=None, quiet=quiet or json_out)
        result = analyze(output).to_json()
    finally:
        if tmp is not None:
            tmp.cleanup()
    if kind == "bandwidth":
        picked = {k: result.get(k) for k in ("bandwidth_hz", "settling_time_s", "phase_reference", "bode")}
    else:
        picked = dict(result.get("linearity") or {})
        picked["levels"] = result.get("levels")
    picked["file"] = None if tmp is not None else str(output)
    if json_out:
        out.print_json(json.dumps(picked, default=float))
    else:
        for k, v in picked.items():
            if not isinstance(v, list):
                out.print(f"{k}: {v}")


@characterize_app.command("bandwidth")
def characterize_bandwidth(
    config: ConfigArg,
    sim: SimOpt = False,
    json_out: JsonOpt = False,
    output: OutputOpt = None,
    quiet: QuietOpt = False,
) -> None:
    """Sinusoidal table rates: closed-loop FTR response, -3 dB bandwidth and settling time (paper Fig. 3)."""
    _characterize("bandwidth", config, sim, json_out, output, quiet)


@characterize_app.command("linearity")
def characterize_linearity(
    config: ConfigArg,
    sim: SimOpt = False,
    json_out: JsonOpt = False,
    output: OutputOpt = None,
    quiet: QuietOpt = False,
) -> None:
    """Constant table rates: scale factor, nonlinearity and asymmetry (paper Fig. 2)."""
    _characterize("linearity", config, sim, json_out, output, quiet)


# ====================================================================================== analyze
@app.command()
def analyze(
    run_file: Annotated[
        Path, typer.Argument(help="run file (HDF5, qmg-lab/1 or /2), or a study directory", show_default=False)
    ],
    json_out: JsonOpt = False,
    figures: Annotated[Path | None, typer.Option("--figures", help="write the figures to this folder")] = None,
    fmt: Annotated[
        str, typer.Option("--format", help="figure file format: png, svg or pdf", show_default=True)
    ] = "png",
    sf_model: Annotated[
        Path | None,
        typer.Option("--sf-model", help="pickoff-ratio model (characterize sf-model): the calibrated SF beside CLSF"),
    ] = None,
) -> None:
    """The paper's results from a run file: true vs CLSF scale factor, accuracy, Allan deviation, figures."""
    import dataclasses

    from qmg_lab.cli.files import damaged_file_report
    from qmg_lab.storage.layout import DamagedFileError, StorageError
    from qmg_lab.storage.runfile import check_structure

    if fmt not in ("png", "svg", "pdf"):
        fail(EXIT_BAD_INPUT, f"--format {fmt}: use png, svg or pdf")
    if not run_file.exists():
        fail(EXIT_BAD_INPUT, f"{run_file}: no such run file")
    if run_file.is_dir():
        _analyze_study(run_file, json_out, figures)
        return
    if figures is not None and figures.exists() and not figures.is_dir():
        fail(EXIT_BAD_INPUT, f"--figures {figures} is a file: name a folder for the figures (made if missing)")
    try:  # a file cut short or with damaged metadata is answered before the analysis is even imported
        check_structure(run_file)
    except DamagedFileError as exc:
        fail(EXIT_BAD_INPUT, damaged_file_report(run_file, str(exc)))
    except StorageError as exc:
        fail(EXIT_BAD_INPUT, str(exc))

    from qmg_lab.analysis.compute import analyze as run_analysis
    from qmg_lab.analysis.render import render_table
    from qmg_lab.storage.salvage import salvage_summary
    from qmg_lab.storage.writer import read_run, status_detail

    model = None
    if sf_model is not None:
        from qmg_lab.clsf.pickoff_model import PickoffRatioModel

        try:
            model = PickoffRatioModel.load(sf_model)
        except ValueError as exc:
            fail(EXIT_BAD_INPUT, str(exc))
    calibrated = None
    try:
        result = run_analysis(run_file)
        if model is not None:
            from qmg_lab.analysis.calibrated_sf import evaluate

            try:
                calibrated = evaluate(run_file, model, result)
            except ValueError as exc:
                fail(EXIT_BAD_INPUT, str(exc))
        head = read_run(run_file, select=())
        detail = status_detail(head)
        salvaged = salvage_summary(head.attrs)  # a salvaged file says so first, with what it lost
        written = []
        if figures is not None:
            from qmg_lab.analysis.report import write_figures

            try:
                written = write_figures(run_file, figures, fmt=fmt)  # type: ignore[arg-type]  # checked above
            except OSError as exc:
                fail(EXIT_BAD_INPUT, f"--figures {figures}: cannot write the figures there ({exc})")
    except DamagedFileError as exc:  # what still reads, and what does not
        fail(EXIT_BAD_INPUT, damaged_file_report(run_file, str(exc)))
    except StorageError as exc:
        fail(EXIT_BAD_INPUT, str(exc))
    if json_out:
        data = result.to_json()
        data["status_detail"] = detail  # "status" stays the file's attribute; this is how to read it
        data["salvaged"] = salvaged or None
        if figures is not None:
            data["figures"] = [str(p) for p in written]
        if calibrated is not None:
            data["calibrated_sf"] = {**calibrated.to_json(), "model_file": str(sf_model)}
        out.print_json(json.dumps(data, default=float))
    else:
        if salvaged:
            out.print(salvaged, style="bold yellow", markup=False, highlight=False)
        out.print(render_table(dataclasses.replace(result, status=detail)))
        if calibrated is not None:
            out.print(sfcal.render_calibrated(calibrated))
            for w in calibrated.warnings:
                out.print(f"[bold yellow]warning:[/] {escape(w)}")
        for p in written:
            out.print(f"figure: {p}")


def _analyze_study(out_dir: Path, json_out: bool, figures: Path | None) -> None:
    """`analyze DIR` on a study directory: the summary table (or results.csv's rows as JSON)."""
    from qmg_lab.study.results import collect_rows, summary_table, write_figures

    try:
        columns, rows = collect_rows(out_dir)
    except (FileNotFoundError, ValueError, KeyError) as exc:
        fail(EXIT_BAD_INPUT, f"{out_dir}: not a readable study directory ({exc})")
    if figures is not None and figures.resolve() != (out_dir / "figures").resolve():
        fail(EXIT_BAD_INPUT, f"a study's figures go to {out_dir / 'figures'}; --figures takes no other folder")
    written = write_figures(out_dir) if figures is not None else []
    if json_out:
        out.print_json(json.dumps({"columns": columns, "rows": rows, "figures": [str(p) for p in written]}))
    else:
        out.print(summary_table(out_dir))
        for p in written:
            out.print(f"figure: {p}")


# ====================================================================================== study
@app.command()
def study(
    study_file: Annotated[Path, typer.Argument(help="study file (TOML): base, seeds, axes", show_default=False)],
    output: Annotated[
        Path | None, typer.Option("-o", "--output", help="study directory (default studies-out/NAME)")
    ] = None,
    workers: Annotated[
        int | None, typer.Option("--workers", min=1, help="local Dask workers (default: one per core)")
    ] = None,
    scheduler: Annotated[
        str | None, typer.Option("--scheduler", help="address of a running Dask scheduler, e.g. tcp://host:8786")
    ] = None,
    resume: Annotated[bool, typer.Option("--resume", help="run only the points without a result in -o")] = False,
    quiet: Annotated[bool, typer.Option("--quiet", "-q", help="no progress bar")] = False,
    dashboard_address: Annotated[
        str | None,
        typer.Option(
            "--dashboard-address",
            help="local cluster: where its Dask dashboard listens (default 127.0.0.1 on a free port: this machine "
            "only; '0.0.0.0:8787' opens it to the network on purpose)",
            show_default=False,
        ),
    ] = None,
) -> None:
    """Run a design study: every point of the grid (axes x seeds) as a simulated campaign on Dask, then
    DIR/results.csv, DIR/figures/ and a summary table."""
    from qmg_lab.study.results import summary_table, write_figures, write_results
    from qmg_lab.study.runner import StudyDirError, run_study
    from qmg_lab.study.spec import StudyError, load_study

    if workers is not None and scheduler is not None:
        fail(EXIT_BAD_INPUT, "--workers and --scheduler exclude each other (the scheduler's cluster has its workers)")
    try:
        spec = load_study(study_file)
    except StudyError as exc:
        fail(EXIT_BAD_INPUT, str(exc))
    out_dir = output or Path("studies-out") / spec.spec.study.name
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        fail(EXIT_BAD_INPUT, f"cannot create the study directory: {exc}")
    console.print(
        f"study {spec.spec.study.name}: {len(spec.points)} points ({len(spec.points) // len(spec.spec.study.seeds)} "
        f"grid cells x {len(spec.spec.study.seeds)} seeds), every configuration valid; results in {out_dir}",
        highlight=False,
    )
    try:
        report = run_study(
            spec,
            out_dir,
            workers=workers,
            scheduler=scheduler,
            resume=resume,
            console=None if quiet else console,
            dashboard_address=dashboard_address,
        )
    except StudyDirError as exc:
        fail(EXIT_BAD_INPUT, str(exc))
    except OSError as exc:
        fail(EXIT_BAD_INPUT, f"cannot reach the Dask scheduler {scheduler}: {exc}")
    written = write_results(out_dir)
    written += write_figures(out_dir)
    out.print(summary_table(out_dir))
    console.print(
        f"{report.ran} points run ({report.failed} failed), {report.already_done} were already done; "
        f"{written[0]} and {len(written) - 1} more files",
        highlight=False,
    )


# ====================================================================================== budget
@app.command()
def budget(
    config: ConfigArg,
    json_out: JsonOpt = False,
    sim: Annotated[
        bool, flag("--sim", help="the twins' block length (lockin.sim_poll_interval_s) sets the loop delay")
    ] = False,
    sf_characterisation: Annotated[
        Path | None,
        typer.Option(
            "--sf-characterisation",
            help="the characterisation run's configuration: also the calibrated SF's residual, term by term",
        ),
    ] = None,
) -> None:
    """Predict from the configuration the CLSF Allan deviation (1-3000 s), each noise source and the total, and
    the accuracy and linearity terms of a temperature sweep."""
    from qmg_lab.budget.noise import noise_budget
    from qmg_lab.budget.table import budget_table

    cfg, _ = load(config, sim=False)
    result = noise_budget(cfg, sim_blocks=sim)
    calibrated = None
    if sf_characterisation is not None:
        from qmg_lab.budget.calibrated import calibrated_accuracy

        calibrated = calibrated_accuracy(cfg, load(sf_characterisation, sim=False)[0])
    if json_out:
        data = result.to_json()
        if calibrated is not None:
            data["calibrated_accuracy"] = calibrated.to_json()
        out.print_json(json.dumps(data, default=float))
        return
    out.print(budget_table(result, out.width))
    acc = result.accuracy
    out.print(
        f"temperature sweep (qmg_lab/budget/sweep.py): CLSF accuracy {acc.total_ppm:.0f} ppm RMS "
        f"({acc.total_mean_removed_ppm:.0f} ppm mean removed), dominated by {acc.dominant_accuracy_source}: "
        + ", ".join(f"{k} {v:.1f}" for k, v in acc.terms_ppm.items())
        + f" ppm; linearity {acc.nonlinearity_rms_pct_fs:.2g} % FS RMS, dominated by {acc.dominant_nonlinearity_source}"
    )
    if calibrated is not None:
        out.print(
            f"whole-SF calibration (qmg_lab/budget/calibrated.py, model from {sf_characterisation}): residual "
            f"{calibrated.total_ppm:.1f} ppm RMS against the table steps (CLSF alone {calibrated.clsf_total_ppm:.0f}): "
            + ", ".join(f"{k} {v:.1f}" for k, v in calibrated.terms_ppm.items())
            + f" ppm; fitted front-end lag {calibrated.lag_tau_s:.0f} s"
        )
    out.print(f"dominant at 60 s: {result.dominant(60.0)}. The values and their origins:")
    for s in result.sources:
        out.print(f"  {s.name} = {s.value:.3g} {s.unit}: {s.origin}")
    for note in result.notes:
        out.print(f"note: {note}")


@app.command()
def version() -> None:
    """Print the version."""
    out.print(f"qmg-lab {__version__}")


# the bring-up, device, file, run-list and watch commands, after this module's own (the order of `--help`)
for _commands in (bench, device, files, runs, sfcal, watch):
    _commands.register(app)


def main() -> None:  # pragma: no cover - console entry
    heap.quiet_start()  # no cyclic collection while the command starts (qmg_lab.cli.heap)
    tolerant_streams()  # no UnicodeEncodeError on a cp1252 console or redirect (qmg_lab.cli.common)
    from qmg_lab.campaign.interrupts import StopRequested, exit_code

    try:
        app()
    except StopRequested as exc:  # a second stop signal outside the campaign (e.g. after the file was closed)
        sys.exit(exit_code(exc.signum))
    except KeyboardInterrupt:
        sys.exit(EXIT_INTERRUPTED)
    finally:
        settle_streams()  # a dead terminal or a full stdout must not change the exit code
        heap.quiet_exit()
