"""A run file in one line: `qmg_lab.open_run(path)` (docs/working-with-runs.md; the layout: docs/hdf5.md).

    run = qmg_lab.open_run("run.h5")
    run.config["campaign"]["name"], run.status, run.steps, run.events
    run.to_xarray()["clsf"].sf_change_estimate.plot()

Every read opens the file read-only (qmg_lab.storage.runfile.open_run_file: through HDF5 SWMR when a writer
left it open) and closes it again, so a file that a campaign is still writing (or that a killed writer left)
reads as of the writer's last flush; nothing here ever writes. `Run` holds what is small (root attributes,
configuration, steps, events, snapshots) as read at `open_run`; the data groups are read when asked for
(`to_pandas`, `to_xarray`, `clsf_with_temperatures`), so they are current at that call. `run.reload()` reads the
small parts again. A file that cannot be read raises StorageError (DamagedFileError for damaged bytes).

Whole valid rows only, by the one rule every reader applies (`RunFile.read`): every group is cut to its shortest
column (a kill, or a reader between two column writes, may leave one column a block longer), and rows never
written (the fill value NaN, left by a kill or a full disk) are not data.

`to_xarray()` returns an xarray DataTree rather than a dict of Datasets: the tree mirrors the file's groups
(`tree["clsf"]`, `tree["chamber"]`) with the root attributes on its root, each group keeps its own time axis
(the groups are sampled at different rates, so one shared Dataset would need a union of all times full of NaN),
and it is one object that `to_netcdf`/`to_zarr` write whole. `tree["clsf"].to_dataset()` is the Dataset of one group.
"""

from __future__ import annotations

import json
import tomllib
from collections.abc import Iterable, Sequence
from contextlib import AbstractContextManager
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from qmg_lab.storage.layout import StorageError
from qmg_lab.storage.runfile import RunFile, attr_value, open_run_file

if TYPE_CHECKING:  # pandas and xarray are imported when a table is asked for: `import qmg_lab` stays light
    import pandas as pd
    import xarray as xr

DATA_GROUPS = ("lockin", "clsf", "table", "chamber", "truth", "edges", "windows")
TEXT_UNITS = "text"
MOVING_MEAN_S = 60.0


@dataclass(frozen=True)
class Column:
    """One 1-D dataset of a group as read: its values (text decoded to str), units and description."""

    values: np.ndarray
    units: str
    description: str


def _open(path: Path) -> AbstractContextManager[RunFile]:
    """The file, read-only (`open_run_file`: also a running or a killed writer's file; StorageError, never an
    h5py exception, for anything else)."""
    return open_run_file(path)


def read_group(run: RunFile, group: str, columns: Iterable[str] | None = None) -> dict[str, Column]:
    """Every 1-D column of /group (or those named, plus `time` when the group has one), whole valid rows only
    (`RunFile.read`: fill rows are never data).

    Fixed-length byte columns (`kind`, `status`, `message`, ...) come back as str arrays."""
    names = run.columns(group)
    if columns is not None:
        wanted = list(columns)
        unknown = sorted(set(wanted) - set(names))
        if unknown:
            raise StorageError(f"{run.path}: /{group} has no columns {unknown}")
        names = [c for c in names if c in wanted or c == "time"]
    if group == "snapshots":
        names = [c for c in names if c != "json"]  # bytes of the documents, not rows: see Run.snapshots
    if not names:
        return {}
    grp = run.h5[group]
    rows = run.read(group, names)
    out: dict[str, Column] = {}
    for c in names:
        ds = grp[c]
        values = rows[c]
        if values.dtype.kind == "S":
            values = np.array([v.decode("utf-8", "replace") for v in values], dtype=str)
        out[c] = Column(
            values, str(attr_value(ds.attrs.get("units", ""))), str(attr_value(ds.attrs.get("description", "")))
        )
    return out


def _snapshots(run: RunFile) -> list[dict[str, Any]]:
    if "snapshots" not in run.h5:
        return []
    rows = read_group(run, "snapshots")
    blob = run.h5["snapshots/json"][:].tobytes()
    docs = []
    for i in range(rows["time"].values.shape[0]):
        o, k = int(rows["offset"].values[i]), int(rows["length"].values[i])
        docs.append(
            {
                "time": float(rows["time"].values[i]),
                "instrument": str(rows["instrument"].values[i]),
                "occasion": str(rows["occasion"].values[i]),
                "document": json.loads(blob[o : o + k].decode("utf-8")),
            }
        )
    return docs


def _frame(cols: dict[str, Column], index: str | None = "time") -> pd.DataFrame:
    import pandas as pd

    df = pd.DataFrame({c: col.values for c, col in cols.items()})
    df.attrs["units"] = {c: col.units for c, col in cols.items()}
    df.attrs["description"] = {c: col.description for c, col in cols.items()}
    if index is not None and index in df.columns:
        df = df.set_index(index)
    return df


@dataclass
class Run:
    """A run file, qmg-lab/1 or /2 (see the module docstring). attrs: root attributes (text decoded)."""

    path: Path
    attrs: dict[str, Any]
    config: dict[str, Any]
    snapshots: list[dict[str, Any]]
    steps: pd.DataFrame
    events: pd.DataFrame
    groups: list[str] = field(default_factory=list)

    @property
    def status(self) -> str:
        """The file's status attribute: "running" | "completed" | "aborted" (see `status_detail`)."""
        return str(self.attrs.get("status", ""))

    @property
    def status_detail(self) -> str:
        """The status as an operator reads it: a "running" file whose writer died is "interrupted ..."."""
        from qmg_lab.storage.reader import read_run
        from qmg_lab.storage.resume import status_detail

        return status_detail(read_run(self.path, select=()))

    @property
    def name(self) -> str:
        """The configuration's campaign name (the schema's default "campaign" if the stored text sets none)."""
        return str(self.config.get("campaign", {}).get("name", "campaign"))

    @property
    def t0_unix(self) -> float:
        return float(self.attrs.get("t0_unix", float("nan")))

    def reload(self) -> Run:
        """The same file read again (a running file has grown since)."""
        return open_run(self.path)

    def columns(self, group: str, columns: Iterable[str] | None = None) -> dict[str, Column]:
        """The columns of one group with their units and descriptions, read now."""
        with _open(self.path) as run:
            return read_group(run, group, columns)

    def to_pandas(self, group: str, columns: Iterable[str] | None = None) -> pd.DataFrame:
        """One group as a DataFrame indexed by run time (s since t0_unix); units and descriptions in
        `df.attrs["units"]` and `df.attrs["description"]` (column -> text). /steps and /events: see `steps`,
        `events` (indexed by row)."""
        if group == "steps":
            return self.reload().steps
        if group == "events":
            return self.reload().events
        return _frame(self.columns(group, columns))

    def to_xarray(self, groups: Sequence[str] | None = None) -> xr.DataTree:
        """The file as an xarray DataTree: one node per group (default every data group the file has, plus
        steps and events), each with its own `time` coordinate (s since t0_unix; steps and events by row),
        units and description of every variable in its attrs, the root attributes on the root."""
        import xarray as xr

        wanted = list(groups) if groups is not None else [*self.groups, "steps", "events"]
        nodes: dict[str, xr.Dataset] = {}
        with _open(self.path) as run:
            for g in wanted:
                cols = read_group(run, g)
                dim = "time" if g in DATA_GROUPS else ("step" if g == "steps" else "event")
                data_vars = {
                    c: xr.Variable(dim, col.values, {"units": col.units, "description": col.description})
                    for c, col in cols.items()
                    if not (dim == "time" and c == "time")
                }
                coords = {}
                if dim == "time" and "time" in cols:
                    t = cols["time"]
                    coords["time"] = xr.Variable("time", t.values, {"units": t.units, "description": t.description})
                nodes[g] = xr.Dataset(data_vars, coords=coords)
        root = xr.Dataset(attrs={k: v for k, v in self.attrs.items() if k != "config_toml"})
        return xr.DataTree.from_dict({"/": root, **{f"/{g}": ds for g, ds in nodes.items()}})

    def clsf_with_temperatures(self) -> pd.DataFrame:
        """The CLSF rows (indexed by /clsf/time) with the chamber air and the gyro temperature on that axis.

        Columns: sf_change_estimate, sf_change_estimate_60s (the trailing moving mean over MOVING_MEAN_S of run
        time), gain_correction, eta, chamber_temperature and chamber_setpoint (degC, /chamber linearly
        interpolated at each CLSF time), gyro_temperature (degC, the twins' /truth/temperature interpolated
        likewise; NaN on the bench, which has no truth). Outside a source's time span the value is NaN: nothing
        is extrapolated.
        """
        with _open(self.path) as run:
            clsf = read_group(run, "clsf")
            chamber = read_group(run, "chamber") if "chamber" in run.h5 else {}
            truth = read_group(run, "truth", ["temperature"]) if "truth" in run.h5 else {}
        df = _frame(clsf)
        t = np.asarray(df.index, dtype=float)
        df["sf_change_estimate_60s"] = trailing_mean(t, df["sf_change_estimate"].to_numpy(), MOVING_MEAN_S)
        for col, src, name in (
            ("chamber_temperature", chamber, "temperature"),
            ("chamber_setpoint", chamber, "setpoint"),
            ("gyro_temperature", truth, "temperature"),
        ):
            df[col] = interpolate(t, src["time"].values, src[name].values) if src else np.full(t.shape, np.nan)
        df.attrs["units"].update(
            sf_change_estimate_60s="1", chamber_temperature="degC", chamber_setpoint="degC", gyro_temperature="degC"
        )
        return df


def interpolate(t: np.ndarray, t_src: np.ndarray, y_src: np.ndarray) -> np.ndarray:
    """y_src(t_src) linearly interpolated at t; NaN outside [t_src[0], t_src[-1]] (and everywhere if empty)."""
    if t_src.shape[0] == 0:
        return np.full(t.shape, np.nan)
    return np.interp(t, t_src, y_src, left=np.nan, right=np.nan)


def trailing_mean(t: np.ndarray, y: np.ndarray, window_s: float) -> np.ndarray:
    """Moving mean of y over the trailing window (t_i - window_s, t_i] of each sample (t increasing): what a
    live display can show, at the price of a lag of about window_s / 2 on a trend."""
    return window_mean(t, y, t - window_s, t)


def centred_mean(t: np.ndarray, y: np.ndarray, window_s: float) -> np.ndarray:
    """Moving mean of y over the centred window (t_i - window_s / 2, t_i + window_s / 2]: no lag on a trend,
    for a finished record (figures)."""
    return window_mean(t, y, t - 0.5 * window_s, t + 0.5 * window_s)


def window_mean(t: np.ndarray, y: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Mean of the rows with lo_i < t <= hi_i (each window holds row i): sums from one cumulative sum, O(n)."""
    if t.shape[0] == 0:
        return np.zeros(0)
    c = np.concatenate(([0.0], np.cumsum(y)))
    first = np.searchsorted(t, lo, side="right")
    last = np.searchsorted(t, hi, side="right")
    return (c[last] - c[first]) / (last - first)


def open_run(path: str | Path) -> Run:
    """Open a run file (qmg-lab/1 or /2; complete, running or left by a killed writer) read-only; see `Run`.

    Raises StorageError (qmg_lab.storage.layout; DamagedFileError for damaged bytes) naming the file and what is
    wrong, never an h5py exception: the file is opened by qmg_lab.storage.runfile.open_run_file."""
    import pandas as pd

    p = Path(path)
    with _open(p) as run:
        h5 = run.h5
        attrs = dict(run.attrs)
        try:
            config = tomllib.loads(str(attrs.get("config_toml", "")))
        except tomllib.TOMLDecodeError as exc:
            raise StorageError(f"{p}: the stored configuration (config_toml) is not TOML: {exc}") from None
        steps = _frame(read_group(run, "steps"), index=None) if "steps" in h5 else pd.DataFrame()
        events = _frame(read_group(run, "events"), index=None) if "events" in h5 else pd.DataFrame()
        snapshots = _snapshots(run)
        groups = [g for g in DATA_GROUPS if g in h5]
    return Run(p, attrs, config, snapshots, steps, events, groups)
