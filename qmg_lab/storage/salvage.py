"""What still reads in a damaged run file (`scan`), and a copy of it into a new file (`salvage`).

A run file can be damaged in two ways a kill cannot: cut short (an incomplete copy, a disk that filled: it ends
before the end-of-file address its superblock records) or with bytes that no longer decode (a chunk whose
deflate stream or checksum fails). `scan` reads every dataset chunk by chunk and reports, for each, how many
leading rows read and the error that stopped it; `qmg-lab analyze` shows that when the analysis cannot read a
file. `salvage` copies what reads into a new file of the same layout (`qmg-lab salvage RUN.h5 -o NEW.h5`):

1. the damaged file is copied to a hidden temporary name next to the new one (the original is never written),
   padded with zero bytes up to its recorded end-of-file address if it was cut short (HDF5 refuses a short
   file; metadata that lay in the lost tail reads as damaged, not as data), and its superblock's writer flags are
   cleared (what `h5clear -s` does) so that HDF5 opens it without SWMR: a SWMR open retries a damaged metadata
   read for minutes, a plain one fails at once;
2. every group and dataset is created in the new file with the same dtype, chunks, filters and attributes, and
   filled with the leading rows that read (chunk by chunk, up to the first failure);
3. every group with a `time` column is cut to its shortest column and to the rows `valid_rows` takes as data;
4. the root attributes are copied; `salvaged_from` (the damaged file's path) and `salvage_report` (JSON: per
   dataset, the rows kept of the rows recorded and the error) are added. `status` is kept: a salvaged run is
   analysed as it is (`--resume` of it is possible when it was not completed).
"""

from __future__ import annotations

import json
import os
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from qmg_lab.storage.h5clear import clear_superblock_flags
from qmg_lab.storage.layout import StorageError
from qmg_lab.storage.reader import valid_rows
from qmg_lab.storage.superblock import read_superblock

#: what h5py raises for bytes that do not decode (a chunk, a B-tree node, an object header)
H5_ERRORS = (OSError, RuntimeError, KeyError, ValueError)


@dataclass(frozen=True)
class DatasetScan:
    """One dataset: rows that read (from the start), rows recorded, and the error that stopped the reading."""

    name: str
    rows_read: int
    rows: int
    error: str = ""

    @property
    def complete(self) -> bool:
        return not self.error and self.rows_read == self.rows


def readable_rows(ds: h5py.Dataset, n: int) -> int:
    """How many of the first n rows of a dataset read (chunk by chunk, up to the first that does not)."""
    step = int(ds.chunks[0]) if ds.chunks else max(n, 1)
    for start in range(0, n, step):
        try:
            ds[start : min(start + step, n)]
        except H5_ERRORS:
            return start
    return n


def _read_prefix(ds: h5py.Dataset) -> tuple[np.ndarray, str]:
    """The leading rows of a 1-D dataset that read, chunk by chunk; the error at the first chunk that does not."""
    try:
        n = int(ds.shape[0]) if ds.shape else 0
        step = int(ds.chunks[0]) if ds.chunks else max(n, 1)
    except H5_ERRORS as exc:
        return np.empty(0), f"its layout does not read: {exc}"
    parts: list[np.ndarray] = []
    for start in range(0, n, step):
        try:
            parts.append(np.asarray(ds[start : min(start + step, n)]))
        except H5_ERRORS as exc:
            return (np.concatenate(parts) if parts else np.empty(0, dtype=ds.dtype)), f"rows {start}..: {exc}"
    return (np.concatenate(parts) if parts else np.empty(0, dtype=ds.dtype)), ""


def _datasets(h5: h5py.File, unreadable: list[DatasetScan] | None = None) -> list[h5py.Dataset]:
    """The 1-D datasets of the file's top-level groups (and the root) that HDF5 can open; a group or dataset
    whose metadata does not decode is added to `unreadable`."""
    found: list[h5py.Dataset] = []
    skipped = unreadable if unreadable is not None else []

    def members(group: h5py.Group) -> list[str]:
        try:
            return list(group.keys())
        except H5_ERRORS as exc:
            skipped.append(DatasetScan(group.name, 0, 0, f"its member list does not read: {exc}"))
            return []

    def member(group: h5py.Group, name: str) -> Any:
        try:
            return group[name]
        except H5_ERRORS as exc:
            skipped.append(DatasetScan(f"{group.name.rstrip('/')}/{name}", 0, 0, f"does not open: {exc}"))
            return None

    for obj in (member(h5, name) for name in members(h5)):
        if isinstance(obj, h5py.Group):
            found += [ds for ds in (member(obj, col) for col in members(obj)) if isinstance(ds, h5py.Dataset)]
        elif isinstance(obj, h5py.Dataset):
            found.append(obj)
    return [ds for ds in found if ds.ndim == 1]


def scan(path: str | Path) -> list[DatasetScan]:
    """Every 1-D dataset of a run file that opens: rows that read and the first error (nothing is written).
    Opens a padded, flag-cleared temporary copy without SWMR when the file is cut short or was left open by a
    writer (see the module docstring); StorageError if HDF5 cannot open it at all."""
    p = Path(path)
    with _OpenableCopy(p, p.with_name(f".{p.name}.{os.getpid()}.scan")) as h5:
        unreadable: list[DatasetScan] = []
        return [_scan_one(ds)[1] for ds in _datasets(h5, unreadable)] + unreadable


def _scan_one(ds: h5py.Dataset) -> tuple[np.ndarray, DatasetScan]:
    data, error = _read_prefix(ds)
    return data, DatasetScan(ds.name, int(data.shape[0]), int(ds.shape[0]), error)


def padded_copy(path: Path, tmp: Path) -> None:
    """Copy `path` to `tmp`, extended with zero bytes to the end-of-file address its superblock records if it is
    shorter, with its superblock's writer flags cleared: a file HDF5 opens at once, with or without SWMR."""
    sb = read_superblock(path)
    shutil.copyfile(path, tmp)
    if sb.eof_address is not None and os.path.getsize(tmp) < sb.eof_address:
        os.truncate(tmp, sb.eof_address)
    if sb.version in (2, 3):
        clear_superblock_flags(tmp)


class _OpenableCopy:
    """The file opened read-only without SWMR; a damaged one (cut short, or its writer flags set) through a
    temporary copy, padded to its recorded end and its flags cleared, deleted on exit."""

    def __init__(self, path: Path, tmp: Path) -> None:
        self.path, self.tmp, self.h5 = path, tmp, None

    def __enter__(self) -> h5py.File:
        sb = read_superblock(self.path)
        size = os.path.getsize(self.path)
        source = self.path
        short = sb.eof_address is not None and size < sb.eof_address
        try:
            if short or _flags_set(self.path, sb.version):
                padded_copy(self.path, self.tmp)
                source = self.tmp
            self.h5 = h5py.File(source, "r")
        except (*H5_ERRORS, StorageError) as exc:
            self.tmp.unlink(missing_ok=True)
            raise StorageError(f"{self.path}: HDF5 cannot open it at all, nothing can be read: {exc}") from None
        return self.h5

    def __exit__(self, *exc: object) -> None:
        if self.h5 is not None:
            self.h5.close()
        self.tmp.unlink(missing_ok=True)


def _flags_set(path: Path, version: int) -> bool:
    if version not in (2, 3):
        return False
    with open(path, "rb") as fh:
        head = fh.read(12)
    return len(head) == 12 and head[11] != 0


def salvage(source: str | Path, target: str | Path) -> list[DatasetScan]:
    """Copy what reads of a damaged run file into a new file (module docstring); returns the scan. Refuses
    (StorageError) an existing target and a source HDF5 cannot open at all."""
    src, dst = Path(source), Path(target)
    if dst.exists():
        raise StorageError(f"{dst}: already exists; choose another -o")
    if src.resolve() == dst.resolve():
        raise StorageError(f"{dst}: the copy must be a new file, not the damaged one")
    tmp_out = dst.with_name(f".{dst.name}.{os.getpid()}.salvaging")
    report: list[DatasetScan] = []
    with _OpenableCopy(src, dst.with_name(f".{dst.name}.{os.getpid()}.source")) as h5:
        try:
            with h5py.File(tmp_out, "w", libver="latest") as out:
                data: dict[str, np.ndarray] = {}
                unreadable: list[DatasetScan] = []
                datasets = _datasets(h5, unreadable)
                for ds in datasets:
                    values, row = _scan_one(ds)
                    report.append(row)
                    data[ds.name] = values
                _cut_groups(data)
                for ds in datasets:
                    _copy_dataset(ds, out, data[ds.name])
                _copy_attrs(h5.attrs, out.attrs)
                report += unreadable
                out.attrs["salvaged_from"] = str(src)
                out.attrs["salvage_report"] = json.dumps(
                    [{**r.__dict__, "rows_kept": int(data[r.name].shape[0]) if r.name in data else 0} for r in report]
                )
            os.replace(tmp_out, dst)  # closed: nothing is renamed while open
        except BaseException:
            tmp_out.unlink(missing_ok=True)
            raise
    return report


def _cut_groups(data: dict[str, np.ndarray]) -> None:
    """Whole rows only: every group with a `time` column cut to its shortest column and its valid time rows."""
    groups: dict[str, list[str]] = {}
    for name in data:
        groups.setdefault(name.rsplit("/", 1)[0], []).append(name)
    for g, names in groups.items():
        n = min(data[c].shape[0] for c in names)
        time = f"{g}/time"
        if time in data:
            n = valid_rows(data[time][:n])
        if g == "/steps" or time in data:
            for c in names:
                data[c] = data[c][:n]


def _copy_dataset(ds: h5py.Dataset, out: h5py.File, values: np.ndarray) -> None:
    filters: dict[str, Any] = {}
    if ds.compression is not None:
        filters = {"compression": ds.compression, "compression_opts": ds.compression_opts}
    new = out.create_dataset(
        ds.name,
        data=values,
        maxshape=(None,),
        chunks=ds.chunks or True,
        shuffle=bool(ds.shuffle),
        fillvalue=ds.fillvalue,
        **filters,
    )
    _copy_attrs(ds.attrs, new.attrs)


def _copy_attrs(source: h5py.AttributeManager, target: h5py.AttributeManager) -> None:
    """Every attribute that reads (a damaged one is left out)."""
    try:
        names = list(source.keys())
    except H5_ERRORS:
        return
    for k in names:
        try:
            target[k] = source[k]
        except H5_ERRORS:
            continue
