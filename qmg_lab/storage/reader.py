"""Reading run files, complete or cut short by a crash (`read_run`, `read_window`)."""

from __future__ import annotations

import json
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from qmg_lab.storage.layout import (
    GROUP_UNITS,
    H5_ERRORS,
    OPTIONAL_COLUMNS,
    DamagedFileError,
    StorageError,
    group_columns,
)
from qmg_lab.storage.runfile import attr_value, open_run_file, valid_rows

__all__ = ["RunData", "attr_value", "read_run", "read_window", "valid_rows"]


@dataclass
class RunData:
    """A run file read into memory.

    attrs: root attributes (strings decoded, numbers as Python scalars); groups: group -> column -> array, each
    group cut to its shortest column (whole rows only); steps: /steps columns (kind and status as str arrays);
    units: "group/column" -> units; writer_open: the superblock says a writer never closed the file (it was
    killed, or is still writing); rows_cut: "group" -> rows dropped to make the columns equal.
    """

    path: Path
    attrs: dict[str, Any]
    groups: dict[str, dict[str, np.ndarray]]
    steps: dict[str, np.ndarray]
    units: dict[str, str] = field(default_factory=dict)
    writer_open: bool = False
    rows_cut: dict[str, int] = field(default_factory=dict)

    @property
    def status(self) -> str:
        return str(self.attrs.get("status", ""))

    @property
    def has_truth(self) -> bool:
        return "truth" in self.groups

    @property
    def planned_step_kinds(self) -> list[str]:
        try:
            return [str(k) for k in json.loads(self.attrs.get("planned_step_kinds", "[]"))]
        except (TypeError, ValueError):
            return []


def read_run(path: str | Path, select: Iterable[str] | None = None) -> RunData:
    """Read a run file (qmg-lab/1 or /2) — complete, still being written, or left by a killed process.

    select: what to load, as group names ("lockin") or columns ("lockin/rate_output"); default everything.
    /steps is always loaded. Opened by `open_run_file` (the superblock check, a bounded first open, whole valid
    rows: fill rows are never data); raises StorageError naming the file and the problem for anything else.
    """
    wanted: dict[str, set[str] | None] | None = None
    if select is not None:
        wanted = {}
        for item in select:
            g, _, c = str(item).strip("/").partition("/")
            if c:
                chosen = wanted.get(g, set())
                if chosen is not None:
                    chosen.add(c)
                    wanted[g] = chosen
            else:
                wanted[g] = None
    with open_run_file(path) as run:
        p, h5 = run.path, run.h5
        if "steps" not in h5:
            raise StorageError(f"{p}: the /steps group is missing")
        units: dict[str, str] = {}
        groups: dict[str, dict[str, np.ndarray]] = {}
        rows_cut: dict[str, int] = {}
        for g in [*GROUP_UNITS, "steps"]:
            if g not in h5:
                if g != "truth":
                    raise StorageError(f"{p}: the /{g} group is missing")
                continue
            grp = h5[g]
            optional = OPTIONAL_COLUMNS.get(g, ())  # columns a file written before them lacks
            cols = [c for c in group_columns(g, run.format) if c in grp or c not in optional]
            absent = [c for c in cols if c not in grp]
            if absent:
                raise StorageError(f"{p}: /{g} lacks the datasets {absent}")
            for c in cols:
                units[f"{g}/{c}"] = attr_value(grp[c].attrs.get("units", ""))
            found = max(grp[c].shape[0] for c in cols)
            if g != "steps" and wanted is not None:
                if g not in wanted:
                    rows_cut[g] = found - min(grp[c].shape[0] for c in cols)  # not read: shortest column only
                    continue
                sel = wanted[g]
                if sel is not None:
                    unknown = sorted(sel - set(cols) - set(optional))
                    if unknown:
                        raise StorageError(f"{p}: /{g} has no columns {unknown}")
                    cols = [c for c in cols if c in sel or c == "time"]
            groups[g] = run.read(g, cols)
            rows_cut[g] = found - (next(iter(groups[g].values())).shape[0] if groups[g] else 0)
        attrs, writer_open = run.attrs, run.writer_open
    steps = groups.pop("steps")
    for c in ("kind", "status"):
        steps[c] = np.array([s.decode("utf-8", "replace") for s in steps[c]], dtype=str)
    return RunData(
        path=Path(path),
        attrs=attrs,
        groups=groups,
        steps=steps,
        units=units,
        writer_open=writer_open,
        rows_cut=rows_cut,
    )


def read_window(
    path: str | Path, group: str, t_start: float, t_end: float, columns: Iterable[str] | None = None
) -> dict[str, np.ndarray]:
    """Rows of one group with t_start <= time <= t_end, read by bisection (no full-column read).

    For figures and spot checks on long files. Opened by `open_run_file`, like `read_run`; the bisection runs
    over the group's whole valid rows.
    """
    with open_run_file(path) as run:
        p, h5 = run.path, run.h5
        if group not in h5 or "time" not in h5[group]:
            raise StorageError(f"{p}: has no /{group}/time")
        grp = h5[group]
        cols = list(columns) if columns is not None else run.columns(group)
        unknown = [c for c in cols if c not in grp]
        if unknown:
            raise StorageError(f"{p}: /{group} has no columns {unknown}")
        n = run.rows(group, sorted(set(cols) | {"time"}))
        t = grp["time"]

        def bisect(x: float, right: bool) -> int:
            lo, hi = 0, n
            while lo < hi:
                mid = (lo + hi) // 2
                v = float(t[mid])
                if v < x or (right and v == x):
                    lo = mid + 1
                else:
                    hi = mid
            return lo

        try:
            i0, i1 = bisect(t_start, False), bisect(t_end, True)
            out = {c: grp[c][i0:i1] for c in cols}
            out.setdefault("time", t[i0:i1])
        except H5_ERRORS as exc:
            raise DamagedFileError(f"{p}: /{group} cannot be read between {t_start:g} and {t_end:g} s: {exc}") from None
        return out
