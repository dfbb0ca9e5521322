"""One point of a design study, as a Dask task: a simulated campaign, its analysis, and the point's result file.

Exactly-once protocol (docs/studies.md), in the study directory DIR:

1. The task takes an exclusive lock on DIR/points/<id>.lock (the `filelock` package: flock on POSIX, a
   msvcrt byte-range lock on Windows, both released by the OS when the process dies; blocking). Two tasks of one
   point, e.g. a worker orphaned by a killed driver and the task of the resumed study, never run at the same time.
2. Holding the lock it looks for DIR/points/<id>.json: if it exists the point is done and the task returns that
   record without running anything.
3. Otherwise it logs "start" to DIR/runlog.jsonl, runs the campaign (twins only) and `analyze`, writes the record
   to a temporary file, fsyncs it and renames it to DIR/points/<id>.json (atomic: the file is either absent or
   whole), and logs "done".

The record, not the log, is the truth: a kill between the rename and the "done" line leaves a complete point
without one. A point is therefore complete exactly when its record exists; `--resume` runs the points without one, and a
point killed before its rename runs again from the start (its partial campaign counts for nothing). A point
whose campaign or analysis raises is recorded with status "failed" and the error: it is complete, and the study
goes on.
"""

from __future__ import annotations

import json
import os
import socket
import tempfile
import time
import traceback
from collections.abc import Iterator
from contextlib import contextmanager
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from filelock import FileLock

from qmg_lab.config.schema import parse_config

#: analyze --json keys that are not results (the point's run file lives in a temporary directory)
NOT_METRICS = ("file",)


def points_dir(out_dir: Path) -> Path:
    return out_dir / "points"


def record_path(out_dir: Path, point_id: str) -> Path:
    return points_dir(out_dir) / f"{point_id}.json"


def read_record(path: Path) -> dict[str, Any]:
    return dict(json.loads(path.read_text(encoding="utf-8")))


def point_complete(out_dir: Path, point_id: str) -> bool:
    """The point has a record that is final: "ok" or "failed" (a "lost" task, whose worker died, is run again)."""
    path = record_path(out_dir, point_id)
    return path.exists() and read_record(path).get("status") != "lost"


def write_atomic(path: Path, text: str) -> None:
    """Write `text` to `path` so that a reader (or a kill at any instant) sees either no file or the whole file."""
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    if os.name != "posix":  # Windows has no directory fsync (a directory is not opened as a file): the rename is
        return  # as durable as the file system's metadata journal makes it
    dir_fd = os.open(path.parent, os.O_RDONLY)
    try:
        os.fsync(dir_fd)  # the rename itself survives a power cut
    finally:
        os.close(dir_fd)


def log_event(out_dir: Path, event: str, point_id: str, **extra: Any) -> None:
    """One line of DIR/runlog.jsonl (O_APPEND: lines from concurrent workers do not interleave)."""
    line = {
        "utc": datetime.now(UTC).isoformat(timespec="milliseconds"),
        "event": event,
        "point": point_id,
        "host": socket.gethostname(),
        "pid": os.getpid(),
        **extra,
    }
    fd = os.open(out_dir / "runlog.jsonl", os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
    try:
        os.write(fd, (json.dumps(line) + "\n").encode("utf-8"))
    finally:
        os.close(fd)


@contextmanager
def point_lock(out_dir: Path, point_id: str) -> Iterator[None]:
    """Exclusive lock on DIR/points/<id>.lock for the whole run of one point (released if the process dies)."""
    with FileLock(points_dir(out_dir) / f"{point_id}.lock"):
        yield


def metrics_of(result: dict[str, Any]) -> dict[str, Any]:
    """The scalars of `analyze --json`: top-level numbers, strings, booleans and nulls, and one level of dicts of
    scalars as "key.sub" (e.g. linearity.asymmetry_ppm); lists (pairs, adev rows, notes) are left out."""
    out: dict[str, Any] = {}
    for k, v in result.items():
        if k in NOT_METRICS:
            continue
        if v is None or isinstance(v, (bool, int, float, str)):
            out[k] = v
        elif isinstance(v, dict):
            out.update({f"{k}.{s}": x for s, x in v.items() if x is None or isinstance(x, (bool, int, float, str))})
    return out


def run_campaign(config_text: str, run_file: Path) -> tuple[dict[str, Any], float]:
    """Run the point's campaign on the twins into run_file and analyse it: (analyze --json, simulated s)."""
    from qmg_lab.analysis.compute import analyze
    from qmg_lab.campaign.pipeline import run_campaign as run_into
    from qmg_lab.storage.writer import read_run, status_detail

    cfg = parse_config(config_text, "point configuration")
    end = run_into(cfg, config_text, run_file)  # the plan is checked before any twin is built
    if end.summary is None:  # refused or never started: no run file to analyse
        raise RuntimeError(end.message)
    result = analyze(run_file).to_json()
    result["status_detail"] = status_detail(read_run(run_file, select=()))
    return result, end.summary.simulated_s


def run_point(point: dict[str, Any], out_dir: str, keep_run_files: bool = False) -> dict[str, Any]:
    """The Dask task of one point (the module docstring's protocol). `point`: id, index, seed, axes, config_text.
    Returns the point's record (also in DIR/points/<id>.json)."""
    out = Path(out_dir)
    points_dir(out).mkdir(parents=True, exist_ok=True)
    pid = str(point["id"])
    path = record_path(out, pid)
    with point_lock(out, pid):
        if point_complete(out, pid):
            log_event(out, "skip", pid, reason="already complete")
            return read_record(path)
        log_event(out, "start", pid)
        t0 = time.perf_counter()
        record: dict[str, Any] = {
            "point": pid,
            "index": point["index"],
            "seed": point["seed"],
            "axes": point["axes"],
            "status": "ok",
            "error": "",
            "simulated_s": None,
            "metrics": {},
        }
        with tempfile.TemporaryDirectory(prefix="qmg-study-") as tmp:
            run_file = (out / "runs" / f"{pid}.h5") if keep_run_files else Path(tmp) / f"{pid}.h5"
            run_file.parent.mkdir(parents=True, exist_ok=True)
            run_file.unlink(missing_ok=True)  # left by a run of this point that was killed
            try:
                result, simulated_s = run_campaign(str(point["config_text"]), run_file)
                record["metrics"] = metrics_of(result)
                record["simulated_s"] = simulated_s
                if result.get("status") != "completed":
                    record["status"] = "failed"
                    record["error"] = f"campaign {result.get('status')}: {result.get('abort_reason', '')}"
            except Exception as exc:
                record["status"] = "failed"
                record["error"] = f"{type(exc).__name__}: {exc}"
                record["traceback"] = traceback.format_exc(limit=8)
        record["wall_s"] = time.perf_counter() - t0
        record["host"] = socket.gethostname()
        write_atomic(path, json.dumps(record, indent=1, allow_nan=False, default=str))
        log_event(out, "done", pid, status=record["status"], wall_s=round(record["wall_s"], 3))
        return record
