"""Reading run files, complete or cut short by a crash (`read_run`, `read_window`)."""

from __future__ import annotations

import json
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from qmg_lab.storage.h5clear import writer_flags_set
from qmg_lab.storage.layout import (
    FORMAT,
    GROUP_UNITS,
    OPTIONAL_COLUMNS,
    STEPS_UNITS,
    DamagedFileError,
    StorageError,
)
from qmg_lab.storage.superblock import check_file_end


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


def attr_value(value: Any) -> Any:
    """An HDF5 attribute as a Python value: bytes decoded as UTF-8, numpy scalars as Python scalars."""
    if isinstance(value, bytes):
        return value.decode("utf-8", "replace")
    if isinstance(value, np.generic):
        return value.item()
    return value


def valid_rows(t: np.ndarray) -> int:
    """How many leading rows of a time column are data: the longest prefix that is finite and does not decrease,
    less a trailing run of exact 0.0 after the first row.

    Rows a killed writer (or a killed repair: shrinking a dataset writes fill values at once, its new extent only
    at the next flush) left allocated but unwritten hold the dataset's fill value: NaN in files from issue 27 on
    (not finite), 0.0 in older ones (a step back to 0.0, or 0.0 repeated after a first row at 0.0). A time of
    exactly 0.0 can only be a run's first row, so neither is ever taken as data.
    """
    n = int(t.shape[0])
    if n == 0:
        return 0
    bad = ~np.isfinite(t)
    bad[1:] |= t[1:] < t[:-1]
    k = int(np.argmax(bad)) if bad.any() else n
    while k > 1 and t[k - 1] == 0.0:
        k -= 1
    return k


def read_run(path: str | Path, select: Iterable[str] | None = None) -> RunData:
    """Read a qmg-lab/1 run file — complete, still being written, or left by a killed process.

    select: what to load, as group names ("lockin") or columns ("lockin/rate_output"); default everything.
    /steps is always loaded. Raises StorageError naming the file and the problem for anything else.
    """
    p = Path(path)
    if not p.is_file():
        raise StorageError(f"{p}: no such run file")
    check_file_end(p)  # a file cut short is answered now, not after minutes of SWMR retries
    writer_open = writer_flags_set(p)
    try:
        h5 = h5py.File(p, "r", swmr=True, libver="latest")
    except OSError as exc:
        raise DamagedFileError(f"{p}: HDF5 cannot open it: {exc}") from None
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
    with h5:
        attrs = {k: attr_value(v) for k, v in h5.attrs.items()}
        if attrs.get("format") != FORMAT:
            raise StorageError(f"{p}: not a {FORMAT} run file (root attribute format = {attrs.get('format')!r})")
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
            optional = OPTIONAL_COLUMNS.get(g, ())  # an older file lacks them: read without
            cols = [c for c in GROUP_UNITS.get(g, STEPS_UNITS) if c in grp or c not in optional]
            absent = [c for c in cols if c not in grp]
            if absent:
                raise StorageError(f"{p}: /{g} lacks the datasets {absent}")
            for c in cols:
                units[f"{g}/{c}"] = attr_value(grp[c].attrs.get("units", ""))
            n = min(grp[c].shape[0] for c in cols)
            rows_cut[g] = max(grp[c].shape[0] for c in cols) - n
            if g != "steps" and wanted is not None:
                if g not in wanted:
                    continue
                sel = wanted[g]
                if sel is not None:
                    unknown = sorted(sel - set(cols))
                    if unknown:
                        raise StorageError(f"{p}: /{g} has no columns {unknown}")
                    cols = [c for c in cols if c in sel or c == "time"]
            data: dict[str, np.ndarray] = {}
            if "time" in cols:  # fill values a kill left at the end are not rows (valid_rows)
                t = _read(p, grp["time"], n)
                rows_cut[g] += n - valid_rows(t)
                n = valid_rows(t)
                data["time"] = t[:n]
            groups[g] = {c: data[c] if c in data else _read(p, grp[c], n) for c in cols}
    steps = groups.pop("steps")
    for c in ("kind", "status"):
        steps[c] = np.array([s.decode("utf-8", "replace") for s in steps[c]], dtype=str)
    return RunData(
        path=p, attrs=attrs, groups=groups, steps=steps, units=units, writer_open=writer_open, rows_cut=rows_cut
    )


def _read(path: Path, ds: h5py.Dataset, n: int) -> np.ndarray:
    """The first n rows of a dataset; a dataset that cannot be read (a damaged chunk) is named (StorageError)."""
    try:
        return np.asarray(ds[:n])
    except (OSError, RuntimeError, ValueError) as exc:
        raise DamagedFileError(f"{path}: the dataset {ds.name} cannot be read (the file is damaged): {exc}") from None


def read_window(
    path: str | Path, group: str, t_start: float, t_end: float, columns: Iterable[str] | None = None
) -> dict[str, np.ndarray]:
    """Rows of one group with t_start <= time <= t_end, read by bisection (no full-column read).

    For figures and spot checks on long files. Opens the file like `read_run` (SWMR, partial files allowed).
    """
    p = Path(path)
    if not p.is_file():
        raise StorageError(f"{p}: no such run file")
    check_file_end(p)
    try:
        h5 = h5py.File(p, "r", swmr=True, libver="latest")
    except OSError as exc:
        raise DamagedFileError(f"{p}: HDF5 cannot open it: {exc}") from None
    with h5:
        if group not in h5 or "time" not in h5[group]:
            raise StorageError(f"{p}: has no /{group}/time")
        grp = h5[group]
        cols = list(columns) if columns is not None else list(grp)
        unknown = [c for c in cols if c not in grp]
        if unknown:
            raise StorageError(f"{p}: /{group} has no columns {unknown}")
        n = min(grp[c].shape[0] for c in set(cols) | {"time"})
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
        except (OSError, RuntimeError, ValueError) as exc:
            raise DamagedFileError(f"{p}: /{group} cannot be read between {t_start:g} and {t_end:g} s: {exc}") from None
        return out
