"""One HDF5 column of a run file as xarray's lazily indexed array (qmg_lab/data/run.py `Run.to_xarray`).

A module of its own so that xarray is imported only when a tree is asked for (`import qmg_lab` stays light), and
so that the array class pickles by name (dask's distributed scheduler sends it to its workers; the file it reads
through pickles as its path, run.py `_RunFile`). Each read takes the file from `_RunFile.reading()`: the Run's
held handle inside `with open_run(...)`, else one opened for that read and closed after it, so that a tree kept
alive holds no file open between reads.

Indexing: xarray hands basic keys (an int or a slice, `IndexingSupport.BASIC`) and does the rest in memory; a
slice is clipped to the column's valid rows, so a read never reaches the fill rows past them.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from xarray.backends import BackendArray
from xarray.core import indexing


class H5Column(BackendArray):
    """Rows [0, n) of /group/name read through `file.reading()` (run.py `_RunFile`); with t0_unix, the UTC
    datetime64[ns] t0_unix + time of each row instead of the time (s)."""

    def __init__(self, file: Any, group: str, name: str, n: int, dtype: Any, t0_unix: float | None = None) -> None:
        self.file, self.group, self.name, self.n, self.t0_unix = file, group, name, n, t0_unix
        self.shape = (n,)
        self.dtype = np.dtype("datetime64[ns]") if t0_unix is not None else np.dtype(dtype)

    def __getitem__(self, key: Any) -> np.ndarray:
        return indexing.explicit_indexing_adapter(key, self.shape, indexing.IndexingSupport.BASIC, self._read)

    def _read(self, key: tuple[Any, ...]) -> np.ndarray:
        (k,) = key
        n = self.n
        if isinstance(k, slice):
            k = slice(*k.indices(n))
        elif not -n <= int(k) < n:
            raise IndexError(f"row {k} of /{self.group}/{self.name} is outside its {n} rows")
        else:
            k = int(k) % n
        with self.file.reading() as run:
            values = np.asarray(run.h5[self.group][self.name][k])
        if self.t0_unix is None:
            return values
        ns = np.round(values * 1e9).astype(np.int64)
        return np.datetime64(round(self.t0_unix * 1e9), "ns") + ns.astype("timedelta64[ns]")


def lazy_column(file: Any, group: str, name: str, n: int, dtype: Any, t0_unix: float | None = None) -> Any:
    """The column as xarray's LazilyIndexedArray over an `H5Column`."""
    return indexing.LazilyIndexedArray(H5Column(file, group, name, n, dtype, t0_unix))
