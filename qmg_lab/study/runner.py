"""Runs a design study's points as tasks on Dask distributed (docs/studies.md).

* By default a `distributed.LocalCluster` with one single-threaded worker process per core (the campaign is
  CPU-bound Python and numba: processes, not threads). Its worker processes exit at once if the driver dies
  (distributed's parent-alive pipe), so a killed `qmg-lab study` leaves no campaign running. The cluster's
  scheduler and its dashboard listen on this machine only (127.0.0.1; the dashboard on a free port, printed),
  unless `dashboard_address` says otherwise (`--dashboard-address 0.0.0.0:8787` opens it to the network on
  purpose). Its scratch space (the workers' local_directory and dask's temporary-directory: spilled data,
  worker files) is DIR/dask-scratch/, removed at the end: never the system's temporary folder, which may be small
  or shared.
* With `scheduler` an existing cluster (`dask scheduler` + `dask worker` on each machine, or dask-jobqueue):
  the workers need qmg-lab installed and DIR at the same path (a shared filesystem), since each task writes its
  point's record there; the driver also writes a record a task returned if it is missing (no shared filesystem).

Each point is one task (qmg_lab/study/task.py: run_point); the driver waits for them as they complete, advances
a rich progress bar, and records a task that died with its worker as a "lost" point (its error kept; `--resume`
runs it again).
"""

from __future__ import annotations

import json
import os
import shutil
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

from qmg_lab.study.spec import Point, Study
from qmg_lab.study.task import point_complete, points_dir, read_record, record_path, run_point, write_atomic

STUDY_JSON = "study.json"
DEFAULT_DASHBOARD = "127.0.0.1:0"  # the local cluster's dashboard: this machine only, on a free port
SCRATCH_DIR = "dask-scratch"  # under the study directory


class StudyDirError(ValueError):
    """The output directory cannot take this study (exists without --resume, or holds another study)."""


@dataclass
class StudyRunReport:
    planned: int
    already_done: int
    ran: int
    failed: int
    workers: int
    dashboard: str = ""  # the local cluster's dashboard (http://...), "" on an external scheduler


def prepare_dir(study: Study, out_dir: Path, resume: bool, write: bool = True) -> list[Point]:
    """Check DIR and (write=True) create its study.json and points/; return the points still to run (all of them
    for a new study).

    DIR/study.json names the study and its fingerprint: --resume refuses a directory of another study (or of this
    study file after an edit that changes any point), and a new study refuses a directory that has results."""
    meta = {
        "study_file": str(study.path.resolve()),
        "name": study.spec.study.name,
        "fingerprint": study.fingerprint(),
        "axes": study.axis_names,
        "seeds": study.spec.study.seeds,
        "points": [{"id": p.id, "index": p.index, "seed": p.seed, "axes": p.axes} for p in study.points],
    }
    meta_path = out_dir / STUDY_JSON
    if meta_path.exists():
        old = json.loads(meta_path.read_text(encoding="utf-8"))
        if not resume:
            raise StudyDirError(f"{out_dir} already holds a study: continue it with --resume, or choose another -o")
        if old.get("fingerprint") != meta["fingerprint"]:
            raise StudyDirError(
                f"{out_dir} holds a different study ({old.get('study_file')}, or this file before an edit that "
                "changed its points): choose another -o"
            )
    elif resume:
        raise StudyDirError(f"{out_dir}: no study to resume there ({STUDY_JSON} missing)")
    if write:
        points_dir(out_dir).mkdir(parents=True, exist_ok=True)
        if not meta_path.exists():
            write_atomic(meta_path, json.dumps(meta, indent=1))
    return [p for p in study.points if not point_complete(out_dir, p.id)]


def _task_args(point: Point) -> dict[str, Any]:
    return {
        "id": point.id,
        "index": point.index,
        "seed": point.seed,
        "axes": point.axes,
        "config_text": point.config_text,
    }


def run_study(
    study: Study,
    out_dir: Path,
    *,
    workers: int | None = None,
    scheduler: str | None = None,
    resume: bool = False,
    console: Console | None = None,
    on_done: Callable[[dict[str, Any]], None] | None = None,
    dashboard_address: str | None = None,
) -> StudyRunReport:
    """Run every point of `study` that has no record in out_dir yet, on Dask; see the module docstring."""
    from distributed import Client, as_completed

    pending = prepare_dir(study, out_dir, resume, write=False)  # refuse a wrong DIR before starting a cluster
    done_before = len(study.points) - len(pending)
    report = StudyRunReport(len(study.points), done_before, 0, 0, 0)
    if not pending:
        return report
    cluster = None
    if scheduler is not None:
        client = Client(scheduler)
    else:
        n = workers or os.cpu_count() or 1
        cluster = local_cluster(n, out_dir, DEFAULT_DASHBOARD if dashboard_address is None else dashboard_address)
        client = Client(cluster)
    try:
        prepare_dir(study, out_dir, resume)  # the cluster answered: only now does DIR change
        report.dashboard = client.dashboard_link if cluster is not None else ""
        if console is not None and report.dashboard:
            console.print(f"Dask dashboard: {report.dashboard}", highlight=False)
        report.workers = len(client.scheduler_info(n_workers=-1)["workers"]) or (workers or 0)
        keep = study.spec.study.keep_run_files
        futures = {
            client.submit(
                run_point,
                _task_args(p),
                str(out_dir.resolve()),
                keep,
                key=f"qmg-point-{p.id}",
                pure=False,
            ): p
            for p in pending
        }
        columns = (
            TextColumn("[bold]{task.description}"),
            BarColumn(),
            MofNCompleteColumn(),
            TextColumn("{task.fields[failed]} failed"),
            TimeElapsedColumn(),
            TimeRemainingColumn(),
        )
        with Progress(*columns, console=console, disable=console is None) as bar:
            task = bar.add_task(study.spec.study.name, total=len(study.points), completed=done_before, failed=0)
            for future in as_completed(futures):
                point = futures[future]
                try:
                    record = future.result()
                except Exception as exc:
                    record = {
                        "point": point.id,
                        "index": point.index,
                        "seed": point.seed,
                        "axes": point.axes,
                        "status": "lost",
                        "error": f"task lost: {type(exc).__name__}: {exc}",
                        "simulated_s": None,
                        "wall_s": None,
                        "metrics": {},
                    }
                path = record_path(out_dir, point.id)
                if not path.exists():  # the worker's filesystem is not ours, or the task never ran
                    write_atomic(path, json.dumps(record, indent=1, default=str))
                record = read_record(path)
                report.ran += 1
                report.failed += record["status"] != "ok"
                bar.update(task, advance=1, failed=report.failed)
                if on_done is not None:
                    on_done(record)
    finally:
        client.close()
        if cluster is not None:
            cluster.close()
            shutil.rmtree(out_dir / SCRATCH_DIR, ignore_errors=True)
    return report


def local_cluster(n_workers: int, out_dir: Path, dashboard_address: str = DEFAULT_DASHBOARD) -> Any:
    """A distributed.LocalCluster of `n_workers` single-threaded processes: scheduler on 127.0.0.1, the dashboard
    at `dashboard_address` (host:port), scratch space under out_dir/dask-scratch (module docstring)."""
    import dask
    from distributed import LocalCluster

    scratch = (out_dir / SCRATCH_DIR).resolve()
    scratch.mkdir(parents=True, exist_ok=True)
    # the workers are spawned with the driver's dask configuration: their temporary-directory is the scratch too
    with dask.config.set({"temporary-directory": str(scratch)}):
        return LocalCluster(
            n_workers=n_workers,
            threads_per_worker=1,
            processes=True,
            host="127.0.0.1",
            dashboard_address=dashboard_address,
            local_directory=str(scratch),
            silence_logs=40,
        )
