"""One line per run file of a folder (`qmg-lab runs DIR`): what it is, how far it got, what it found.

Reads only the root attributes, /steps, /events and the tail of each group's time and of /clsf (SWMR,
read-only): cheap on files of hours, and usable on a file a campaign is writing.

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

import h5py
import numpy as np

from qmg_lab.clsf.moving_mean import last_window_mean
from qmg_lab.storage.layout import FORMAT, RUN_CONTEXT_ATTRS, StorageError

TAIL_ROWS = 4096  # CLSF rows read from the end: >= 60 s at any dither frequency below 68 Hz
GROUPS_WITH_TIME = ("lockin", "clsf", "table", "chamber", "truth")


def _last(h5: h5py.File, path: str) -> float:
    if path not in h5 or h5[path].shape[0] == 0:
        return math.nan
    return float(h5[path][h5[path].shape[0] - 1])


def _tail(h5: h5py.File, group: str, cols: tuple[str, ...]) -> dict[str, np.ndarray]:
    if group not in h5 or any(c not in h5[group] for c in cols):
        return {c: np.zeros(0) for c in cols}
    n = min(h5[group][c].shape[0] for c in cols)
    i0 = max(0, n - TAIL_ROWS)
    return {c: h5[group][c][i0:n] for c in cols}


def summarize(path: Path) -> dict[str, Any]:
    """The run list's row for one file (keys: file, status, name, kind, clsf_mode, created, duration_s,
    steps_completed, steps_planned, resume_count, faults, sf_change_60s_ppm, gain_correction, chamber_c).
    Raises StorageError for a file that is not a readable qmg-lab/1 run file."""
    from qmg_lab.storage.reader import read_run
    from qmg_lab.storage.resume import status_detail

    try:
        h5 = h5py.File(path, "r", swmr=True, libver="latest")
    except OSError as exc:
        raise StorageError(f"{path}: HDF5 cannot open it: {exc}") from None
    with h5:
        attrs = {k: (v.decode() if isinstance(v, bytes) else v) for k, v in h5.attrs.items()}
        if attrs.get("format") != FORMAT:
            raise StorageError(f"{path}: not a {FORMAT} run file")
        try:
            cfg = tomllib.loads(str(attrs.get("config_toml", "")))
        except tomllib.TOMLDecodeError:
            cfg = {}
        ends = [x for x in (_last(h5, f"{g}/time") for g in GROUPS_WITH_TIME) if not math.isnan(x)]
        duration = max(ends, default=math.nan)
        clsf = _tail(h5, "clsf", ("time", "sf_change_estimate", "gain_correction"))
        chamber = _tail(h5, "chamber", ("time", "temperature"))
        faults = 0
        if "events" in h5 and "kind" in h5["events"]:
            faults = int(np.count_nonzero(h5["events/kind"][:] == b"fault"))
    t = clsf["time"]
    sf_60 = last_window_mean(t, clsf["sf_change_estimate"]) * 1e6
    return {
        "file": str(path),
        "status": status_detail(read_run(path, select=())),
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
        try:
            rows.append(summarize(p))
        except StorageError as exc:
            rows.append({"file": str(p), "status": f"unreadable: {exc}"})
    return rows


def json_rows(rows: list[dict[str, Any]]) -> str:
    """The rows as JSON (NaN as null)."""
    clean = [{k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in r.items()} for r in rows]
    return json.dumps({"runs": clean})
