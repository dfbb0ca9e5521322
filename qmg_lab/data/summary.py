"""One line per run file of a folder (`qmg-lab runs DIR`): what it is, how far it got, what it found.

Reads only the root attributes, /steps, /events and the tail of each group's time and of /clsf, whole valid rows
(opened by `open_run_file`: read-only, SWMR where a writer left the file open): cheap on files of hours, and
usable on a file a campaign is writing. A file that cannot be read is one row "unreadable: <why>".

Headline results (the figures a run list can give without the full analysis, `qmg-lab analyze`):
    sf_change_60s_ppm   the CLSF SF-change estimate, mean of its last 60 s of run time (clsf/moving_mean.py), in ppm
    gain_correction     the last CLSF gain correction g_c in force (1.0 = none; correct mode)
    chamber_c           the last chamber air temperature, degC
    faults              the number of `fault` events
    operator, device_serial, notes, run_note: who ran it, on which device, why (storage.layout.RUN_CONTEXT_ATTRS)
"""

from __future__ import annotations

import json
import math
import tomllib
from pathlib import Path
from typing import Any

import numpy as np

from qmg_lab.clsf.moving_mean import last_window_mean
from qmg_lab.storage.layout import RUN_CONTEXT_ATTRS, StorageError
from qmg_lab.storage.runfile import RunFile, open_run_file

TAIL_ROWS = 4096  # CLSF rows read from the end: >= 60 s at any dither frequency below 68 Hz
GROUPS_WITH_TIME = ("lockin", "clsf", "table", "chamber", "truth")


def _tail(run: RunFile, group: str, cols: tuple[str, ...]) -> dict[str, np.ndarray]:
    """The last TAIL_ROWS whole rows of a group (`RunFile.tail`: fill rows are never data); empty if absent."""
    if group not in run.h5 or any(c not in run.h5[group] for c in cols):
        return {c: np.zeros(0) for c in cols}
    return run.tail(group, cols, TAIL_ROWS)


def summarize(path: Path) -> dict[str, Any]:
    """The run list's row for one file (keys: file, status, name, kind, clsf_mode, created, duration_s,
    steps_completed, steps_planned, resume_count, faults, sf_change_60s_ppm, gain_correction, chamber_c).
    Raises StorageError for a file that is not a readable run file (`open_run_file`)."""
    from qmg_lab.storage.reader import RunData
    from qmg_lab.storage.resume import status_detail

    with open_run_file(path) as run:
        h5, attrs, writer_open = run.h5, run.attrs, run.writer_open
        try:
            cfg = tomllib.loads(str(attrs.get("config_toml", "")))
        except tomllib.TOMLDecodeError:
            cfg = {}
        ends = [_tail(run, g, ("time",))["time"] for g in GROUPS_WITH_TIME]
        duration = max((float(t[-1]) for t in ends if t.shape[0]), default=math.nan)
        clsf = _tail(run, "clsf", ("time", "sf_change_estimate", "gain_correction"))
        chamber = _tail(run, "chamber", ("time", "temperature"))
        faults = 0
        if "events" in h5 and "kind" in h5["events"]:
            faults = int(np.count_nonzero(run.read("events", ["kind"])["kind"] == b"fault"))
    t = clsf["time"]
    sf_60 = last_window_mean(t, clsf["sf_change_estimate"]) * 1e6
    return {
        "file": str(path),
        "status": status_detail(RunData(path, attrs, {}, {}, writer_open=writer_open))
        + (", salvaged" if attrs.get("salvaged_from") else ""),
        "name": str(cfg.get("campaign", {}).get("name", "campaign")),  # the schema's default name
        "kind": str(cfg.get("campaign", {}).get("kind", "")),
        "clsf_mode": str(cfg.get("clsf", {}).get("mode", "")),
        "created": str(attrs.get("created", "")),
        "duration_s": duration,
        "steps_completed": int(attrs.get("completed_steps", 0)),
        "steps_planned": int(attrs.get("planned_steps", -1)),
        "resume_count": int(attrs.get("resume_count", 0)),
        "faults": faults,
        "sf_change_60s_ppm": sf_60,
        "gain_correction": float(clsf["gain_correction"][-1]) if t.shape[0] else math.nan,
        "chamber_c": float(chamber["temperature"][-1]) if chamber["time"].shape[0] else math.nan,
        **{k: str(attrs.get(k, "")) for k in RUN_CONTEXT_ATTRS},
    }


def list_runs(folder: Path) -> list[dict[str, Any]]:
    """A row per *.h5 file of the folder (not its subfolders), in name order; a file that is not a readable
    run file gets a row with status "unreadable: <why>" and nothing else."""
    rows = []
    for p in sorted(folder.glob("*.h5")):
        rows.append(summarize_or_say_why(p))
    return rows


def summarize_or_say_why(path: Path) -> dict[str, Any]:
    """`summarize`, or for a file that cannot be summarized the row {"file", "status": "unreadable: <why>"}:
    one bad file is one row, never a lost listing (whatever it raises: a damaged file may fail in ways no
    reader foresaw; the open itself is bounded in time by `open_run_file`)."""
    try:
        return summarize(path)
    except StorageError as exc:
        return {"file": str(path), "status": f"unreadable: {exc}"}
    except Exception as exc:  # isolation: any failure of one file becomes that file's row
        return {"file": str(path), "status": f"unreadable: {path}: {type(exc).__name__}: {exc}"}


def json_rows(rows: list[dict[str, Any]]) -> str:
    """The rows as JSON (NaN as null)."""
    clean = [{k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in r.items()} for r in rows]
    return json.dumps({"runs": clean})
