"""A run file in one line: `qmg_lab.open_run(path)` (docs/working-with-runs.md; the layout: docs/hdf5.md).

    with qmg_lab.open_run("run.h5") as run:
        run.config["campaign"]["name"], run.status, run.steps, run.events
        run.to_xarray()["clsf"].sf_change_estimate.plot()

Every read opens the file read-only through the readers' one guarded open
(`qmg_lab.storage.runfile.open_run_file`: SWMR when a writer left it open; StorageError, never an h5py
exception), so a file that a campaign is still writing (or that a
killed writer left) reads as of the writer's last flush; nothing here ever writes. `Run` holds what is small (root
attributes, configuration, steps, events, snapshots) as read at `open_run`; the data groups are read when asked
for (`to_pandas`, `to_xarray`, `clsf_with_temperatures`), so they are current at that call. `run.reload()` reads
the small parts again. Inside `with open_run(...) as run:` the data reads (the lazy arrays of its trees too) share
one read-only file handle, opened at the first of them and closed on leaving `with` (or by `run.close()`,
`tree.close()`); outside it every read opens the file and closes it again, so that no Run or tree left alive (in
a notebook, or in a reference cycle awaiting the garbage collector) holds the file open: HDF5 refuses a writer
(`qmg-lab run --resume`) a file a reader holds open.

Whole valid rows only, as `qmg_lab.storage.reader.read_run` reads them: every group is cut to its shortest
column (a kill, or a reader between two column writes, may leave one column a block longer), and to the rows
whose time is data (`RunFile.rows`, the rule every reader applies: the fill rows a killed writer leaves at the end
hold a NaN or a 0.0 time), scanned in blocks so that it costs no memory on a long run.

`to_xarray()` returns an xarray DataTree rather than a dict of Datasets: the tree mirrors the file's groups
(`tree["clsf"]`, `tree["chamber"]`) with the root attributes on its root, each group keeps its own time axis
(the groups are sampled at different rates, so one shared Dataset would need a union of all times full of NaN),
and it is one object that `to_netcdf`/`to_zarr` write whole. It is lazy, as `xarray.open_dataset` is: nothing of
a column is read until its values are asked for (xarray's lazy indexing over the HDF5 dataset: a slice reads that
slice), `chunks=` as `open_dataset` spells it gives dask arrays instead, and `.load()` reads everything. A day of
/lockin is ~10^8 rows per column (GB): an index over the time of the stream groups (/lockin, /truth) would read
their whole time column, so those two keep `time` as a coordinate without an index (`.set_xindex("time")` builds
one, reading the column; `.isel` needs none). Every variable carries `long_name` and `units`, and every node a
`datetime` coordinate (UTC, datetime64[ns]) next to its run time `time` (s since the root attribute t0_unix).
"""

from __future__ import annotations

import json
import threading
import tomllib
from collections.abc import Iterable, Iterator, Sequence
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import TYPE_CHECKING, Any

import h5py
import numpy as np

from qmg_lab.clsf.moving_mean import SF_MEAN_WINDOW_S, trailing_mean
from qmg_lab.storage.layout import DESCRIPTIONS, GROUP_UNITS, StorageError
from qmg_lab.storage.runfile import RunFile, attr_value, open_run_file

if TYPE_CHECKING:  # pandas and xarray are imported when a table is asked for: `import qmg_lab` stays light
    import pandas as pd
    import xarray as xr

DATA_GROUPS = ("lockin", "clsf", "table", "chamber", "truth", "edges", "windows")
#: the groups sampled at the lock-in's rate: their time coordinate gets no index in `to_xarray` (module docstring)
STREAM_GROUPS = ("lockin", "truth")
TEXT_UNITS = "text"


@dataclass(frozen=True)
class Column:
    """One 1-D dataset of a group as read: its values (text decoded to str), units and description."""

    values: np.ndarray
    units: str
    description: str


class _RunFile:
    """The file handle of one `Run`'s data reads and of the lazy arrays of its trees (`open_run_file`).

    Held only while the user says so: between `Run.__enter__` and `close()` (leaving `with open_run(...)`, or
    `tree.close()`) one handle, opened at the first read, serves every read. Outside `with`, every read opens the
    file and closes it again (`reading`), so that a Run or a tree kept in a notebook, or waiting in a reference
    cycle for the garbage collector (an xarray DataTree is one: its nodes point at their parent), never keeps the
    file open: HDF5 refuses a writer (`qmg-lab run --resume`) a file that a reader holds open, in this process
    ("file is already open for read-only") and, through its file lock (flock on POSIX, LockFileEx on Windows), in
    another one (storage/holders.py).

    Pickles as its path (a dask worker in another process opens its own handles). h5py serialises its calls, so
    dask's threads may read through one handle."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self._stack: ExitStack | None = None
        self._run: RunFile | None = None
        self._held = False
        self._probed = False  # open_run_file walked the structure once: a growing file is not walked per read
        self._lock = threading.Lock()

    def probed(self) -> None:
        """The file's structure was walked (`open_run_file`'s child) by the caller: no read walks it again."""
        self._probed = True

    def hold(self) -> None:
        """Keep one handle open for the reads to come, until `close()`."""
        with self._lock:
            self._held = True

    @contextmanager
    def reading(self) -> Iterator[RunFile]:
        """`with file.reading() as run:` the open file for one read: the held handle, or one opened for this
        read alone and closed after it."""
        with self._lock:
            held = self._held
            if held and (self._run is None or not self._run.h5.id.valid):
                stack = ExitStack()
                self._run = stack.enter_context(open_run_file(self.path, probe=not self._probed))
                self._stack, self._probed = stack, True
            run = self._run
        if held and run is not None:
            yield run
            return
        with open_run_file(self.path, probe=not self._probed) as run:
            self._probed = True
            yield run

    def is_open(self) -> bool:
        """A handle is held open (between `hold()` and `close()`, after a read)."""
        return self._run is not None and self._run.h5.id.valid

    def close(self) -> None:
        """Close the held handle, if any; reads from now on open the file each for itself."""
        with self._lock:
            if self._stack is not None:
                self._stack.close()
            self._stack, self._run, self._held = None, None, False

    def __getstate__(self) -> dict[str, Any]:
        return {"path": self.path}

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__init__(state["path"])  # type: ignore[misc]


def _attrs_of(ds: h5py.Dataset, group: str, name: str) -> tuple[str, str]:
    """(units, description) of a column: its own attributes, else what storage/layout.py declares for it."""
    units = attr_value(ds.attrs.get("units", GROUP_UNITS.get(group, {}).get(name, "")))
    desc = attr_value(ds.attrs.get("description", DESCRIPTIONS.get(f"{group}/{name}", "")))
    return str(units), str(desc)


def read_group(run: RunFile, group: str, columns: Iterable[str] | None = None) -> dict[str, Column]:
    """Every 1-D column of /group (or those named, plus `time` when the group has one), whole valid rows only
    (`RunFile.read`, the rule every reader applies: fill rows are never data). Fixed-length byte columns (`kind`,
    `status`, `message`, ...) come back as str arrays."""
    if group == "snapshots" and columns is None:
        columns = [c for c in run.columns(group) if c != "json"]  # bytes of the documents: see Run.snapshots
    if columns is not None and not list(columns):
        return {}
    grp = run.h5[group]
    rows = run.read(group, columns)  # the named columns (StorageError for one the group lacks), plus `time`
    out: dict[str, Column] = {}
    for c, raw in rows.items():
        values = np.array([v.decode("utf-8", "replace") for v in raw], dtype=str) if raw.dtype.kind == "S" else raw
        out[c] = Column(values, *_attrs_of(grp[c], group, c))
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


@dataclass(repr=False)
class Run:
    """A qmg-lab run file (see the module docstring). attrs: root attributes (text decoded). A context manager:
    leaving `with` closes the file handle the data reads share (`close`)."""

    path: Path
    attrs: dict[str, Any]
    config: dict[str, Any]
    snapshots: list[dict[str, Any]]
    steps: pd.DataFrame
    events: pd.DataFrame
    groups: list[str] = field(default_factory=list)
    _file: _RunFile = field(init=False, compare=False)

    def __post_init__(self) -> None:
        self._file = _RunFile(self.path)

    def __enter__(self) -> Run:
        self._file.hold()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        """Close the file handle the data reads share inside `with` (a later read opens the file for itself)."""
        self._file.close()

    def __repr__(self) -> str:
        """Four lines: file, campaign and status; start and run time; steps; groups."""
        done = int((self.steps["status"] == "completed").sum()) if "status" in self.steps else 0
        ends = self.steps["t_end"].to_numpy(dtype=float) if "t_end" in self.steps else np.zeros(0)
        length = float(np.nanmax(ends)) if np.isfinite(ends).any() else 0.0
        start = (
            datetime.fromtimestamp(self.t0_unix, UTC).isoformat(timespec="seconds")
            if np.isfinite(self.t0_unix)
            else "?"
        )
        kind = self.config.get("campaign", {}).get("kind", "")
        return (
            f"<qmg_lab.Run {self.path.name}: {self.name} ({kind}), {self.status}>\n"
            f"  started {start}, {self.attrs.get('mode', '?')}, {length:.1f} s of run time\n"
            f"  steps: {done} of {len(self.steps)} completed, {len(self.events)} events\n"
            f"  groups: {', '.join(self.groups)}"
        )

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
        with self._file.reading() as run:
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

    def to_xarray(self, groups: Sequence[str] | None = None, chunks: Any = None) -> xr.DataTree:
        """The file as a lazy xarray DataTree (module docstring): one node per group (default every data group
        the file has, plus steps and events), each with its `time` (s since t0_unix) and `datetime` (UTC)
        coordinates (steps and events by row), `long_name` and `units` on every variable, the root attributes on
        the root. chunks: None (lazy indexing, no dask), or what `xarray.open_dataset` takes: `{}` (the file's
        own chunks), "auto", an int or a dict of dimension -> rows (dask arrays). `.load()` reads it all."""
        import xarray as xr

        wanted = list(groups) if groups is not None else [*self.groups, "steps", "events"]
        with self._file.reading() as run:
            nodes = {f"/{g}": self._node(run, g, chunks) for g in wanted}
        root = xr.Dataset(attrs={k: v for k, v in self.attrs.items() if k != "config_toml"})
        tree = xr.DataTree.from_dict({"/": root, **nodes})
        tree.set_close(self._file.close)  # the handle, not the Run: the tree must not keep the Run alive
        return tree

    def _node(self, run: RunFile, group: str, chunks: Any) -> xr.Dataset:
        """One group as a Dataset of lazily indexed columns (text columns, only in /steps and /events, are read)."""
        import xarray as xr

        from qmg_lab.data.lazy import lazy_column

        names = [c for c in run.columns(group) if not (group == "snapshots" and c == "json")]
        grp = run.h5[group]
        n = run.rows(group, names)
        dim = "time" if group in DATA_GROUPS else ("step" if group == "steps" else "event")
        variables: dict[str, xr.Variable] = {}
        for c in names:
            ds = grp[c]
            units, desc = _attrs_of(ds, group, c)
            attrs = {"long_name": desc or c, "units": units, "description": desc}
            if ds.dtype.kind == "S":
                values: Any = np.array([v.decode("utf-8", "replace") for v in ds[:n]], dtype=str)
            else:
                values = lazy_column(self._file, group, c, n, ds.dtype)
            variables[c] = xr.Variable(dim, values, attrs)
        coords: dict[str, xr.Variable] = {}
        if "time" in variables:
            coords["time"] = variables.pop("time")
            if np.isfinite(self.t0_unix):
                utc = lazy_column(self._file, group, "time", n, grp["time"].dtype, self.t0_unix)
                coords["datetime"] = xr.Variable(
                    dim,
                    utc,
                    {"long_name": f"UTC datetime of the row: t0_unix + {group} time"},
                    encoding={"units": "nanoseconds since 1970-01-01"},
                )
        indexed = dim == "time" and group not in STREAM_GROUPS  # "datetime" is never an index
        node = xr.Dataset(variables, coords=xr.Coordinates(coords) if indexed else xr.Coordinates(coords, indexes={}))
        if chunks is None:
            return node
        if not isinstance(chunks, dict):
            return node.chunk(chunks)
        on_disk = grp["time"].chunks if "time" in grp else None  # `{}` and unnamed dimensions: the file's chunks
        preferred = {d: on_disk[0] if d == "time" and on_disk else -1 for d in node.dims}
        return node.chunk({d: chunks.get(d, preferred[d]) for d in node.dims})

    def clsf_with_temperatures(self) -> pd.DataFrame:
        """The CLSF rows (indexed by /clsf/time) with the chamber air and the gyro temperature on that axis.

        Columns: sf_change_estimate, sf_change_estimate_60s (the trailing moving mean over SF_MEAN_WINDOW_S of
        run time, clsf/moving_mean.py), gain_correction, eta, chamber_temperature and chamber_setpoint (degC,
        /chamber linearly interpolated at each CLSF time), gyro_temperature (degC, the twins' /truth/temperature
        interpolated likewise; NaN on the bench, which has no truth). Outside a source's time span the value is
        NaN: nothing is extrapolated.
        """
        with self._file.reading() as run:
            clsf = read_group(run, "clsf")
            chamber = read_group(run, "chamber") if "chamber" in run.h5 else {}
            truth = read_group(run, "truth", ["temperature"]) if "truth" in run.h5 else {}
        df = _frame(clsf)
        t = np.asarray(df.index, dtype=float)
        df["sf_change_estimate_60s"] = trailing_mean(t, df["sf_change_estimate"].to_numpy(), SF_MEAN_WINDOW_S)
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


def open_run(path: str | Path) -> Run:
    """Open a qmg-lab run file (complete, running or left by a killed writer) read-only; see `Run`."""
    import pandas as pd

    p = Path(path)
    with open_run_file(p) as run:
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
    opened = Run(p, attrs, config, snapshots, steps, events, groups)
    opened._file.probed()  # walked just now: the reads to come skip the child walk, even of a growing file
    return opened
