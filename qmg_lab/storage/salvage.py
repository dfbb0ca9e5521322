"""What still reads in a damaged run file (`scan`), and a copy of it into a new file (`salvage`).

A run file can be damaged in two ways a kill cannot: cut short (an incomplete copy, a disk that filled: it ends
before the end-of-file address its superblock records) or with bytes that no longer decode (a chunk whose
deflate stream or checksum fails, a header or index block overwritten). `scan` reads every dataset chunk by
chunk and reports, for each, how many leading rows read and the error that stopped it; `qmg-lab analyze` shows
that when the analysis cannot read a file. `salvage` copies what reads into a new file of the same layout
(`qmg-lab salvage RUN.h5 -o NEW.h5`):

1. the damaged file is opened by `open_run_file(..., damaged=True)` (qmg_lab/storage/runfile.py): through a
   read-only view padded with zero bytes up to its recorded end of file and with its superblock's writer flags
   read as cleared, without SWMR (a SWMR open retries a damaged metadata read for minutes, a plain one fails at
   once); the damaged file is never written;
2. every dataset's leading rows that read are taken (chunk by chunk, up to the first failure);
3. each group keeps its own longest valid prefix (not the file's): the rows every one of its columns read, in a
   data group (GROUP_UNITS) cut further to the rows `valid_rows` takes as data and before the first row holding
   the fill value (NaN) in any column. A damaged /lockin chunk cuts /lockin, not /clsf or /table;
4. /steps keeps only the steps whose data survived: where a data group was cut, its rows up to the first one
   that ends after the earliest cut group's last kept time (a step the analysis would otherwise claim without
   its samples). The root attribute completed_steps counts the completed steps kept;
5. every group and dataset is created in the new file with the same dtype, chunks, filters and attributes; the
   root attributes are copied, and what was dropped is recorded: root attributes `salvaged_from` (the damaged
   file's path), `salvage_groups` (JSON: per group, rows_kept, rows_found and why), `salvage_steps` (JSON: kept,
   found, dropped: the indices of completed steps dropped), `salvage_report` (JSON: per dataset, rows read of
   rows recorded and the error), and one /events row of kind "salvaged" per group cut. `status` is kept.

`salvage_summary` is what `qmg-lab analyze` prints at the top of a salvaged file's results.
"""

from __future__ import annotations

import json
import os
import queue
import shutil
import subprocess
import sys
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from qmg_lab.storage.h5clear import clear_superblock_flags
from qmg_lab.storage.layout import GROUP_UNITS, H5_ERRORS, DamagedFileError, StorageError
from qmg_lab.storage.runfile import child_env, open_run_file, valid_rows
from qmg_lab.storage.superblock import read_superblock

__all__ = [
    "H5_ERRORS",
    "DatasetScan",
    "padded_copy",
    "readable_rows",
    "salvage",
    "salvage_isolated",
    "salvage_summary",
    "scan",
    "scan_isolated",
]
#: columns that are not rows (the snapshots' JSON bytes, addressed by offset and length): kept whole
NOT_ROWS = ("/snapshots/json",)


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
        _beat()
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
        _beat()
        try:
            return list(group.keys())
        except H5_ERRORS as exc:
            skipped.append(DatasetScan(group.name, 0, 0, f"its member list does not read: {exc}"))
            return []

    def member(group: h5py.Group, name: str) -> Any:
        _beat()
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
    Opened as the module docstring says (step 1); StorageError if HDF5 cannot open it at all."""
    with open_run_file(path, damaged=True) as run:
        unreadable: list[DatasetScan] = []
        return [_scan_one(ds)[1] for ds in _datasets(run.h5, unreadable)] + unreadable


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
    with open_run_file(src, damaged=True) as run:
        h5 = run.h5
        try:
            with h5py.File(tmp_out, "w", libver="latest") as out:
                data: dict[str, np.ndarray] = {}
                unreadable: list[DatasetScan] = []
                datasets = _datasets(h5, unreadable)
                for ds in datasets:
                    values, row = _scan_one(ds)
                    report.append(row)
                    data[ds.name] = values
                report += unreadable
                groups = _cut_groups(data, report)
                steps = _cut_steps(data, groups)
                _add_events(data, groups)
                for ds in datasets:
                    _beat()
                    _copy_dataset(ds, out, data[ds.name])
                _copy_attrs(h5.attrs, out.attrs)
                if steps["kept"] < steps["found"]:
                    out.attrs["completed_steps"] = int(steps["completed_kept"])
                out.attrs["salvaged_from"] = str(src)
                out.attrs["salvage_groups"] = json.dumps(groups)
                out.attrs["salvage_steps"] = json.dumps({k: steps[k] for k in ("kept", "found", "dropped")})
                out.attrs["salvage_report"] = json.dumps(
                    [{**r.__dict__, "rows_kept": int(data[r.name].shape[0]) if r.name in data else 0} for r in report]
                )
            os.replace(tmp_out, dst)  # closed: nothing is renamed while open
        except BaseException:
            tmp_out.unlink(missing_ok=True)
            raise
    return report


def _cut_groups(data: dict[str, np.ndarray], report: list[DatasetScan]) -> dict[str, dict[str, Any]]:
    """Each group cut to its own longest valid prefix (module docstring, step 3); returns, per group, rows_kept,
    rows_found (its longest column) and why (the first reading error of its columns, or the rule that cut)."""
    errors = {r.name: r.error for r in report if r.error}
    members: dict[str, list[str]] = {}
    for name in data:
        if name not in NOT_ROWS:
            members.setdefault(name.rsplit("/", 1)[0] or "/", []).append(name)
    groups: dict[str, dict[str, Any]] = {}
    for g, names in members.items():
        if g == "/":
            continue
        found = max(int(data[c].shape[0]) for c in names)
        n = min(int(data[c].shape[0]) for c in names)
        why = [f"{c.rsplit('/', 1)[1]}: {errors[c]}" for c in names if c in errors]
        time = f"{g}/time"
        if n < found and not why:
            why.append("its columns end at different rows (whole rows only)")
        if time in data and g.strip("/") in GROUP_UNITS:
            k = valid_rows(data[time][:n])
            if k < n:
                why.append(f"rows from {k} on hold no valid time (fill values or a time that steps back)")
            n = k
        if time in data:
            fill = np.zeros(n, dtype=bool)
            for c in names:
                if data[c].dtype.kind == "f":
                    fill |= np.isnan(data[c][:n])
            if fill.any():
                n = int(np.argmax(fill))
                why.append(f"rows from {n} on hold the fill value (NaN): never written")
        for c in names:
            data[c] = data[c][:n]
        groups[g.strip("/")] = {"rows_kept": n, "rows_found": found, "why": "; ".join(why)}
    return groups


def _cut_steps(data: dict[str, np.ndarray], groups: dict[str, dict[str, Any]]) -> dict[str, Any]:
    """/steps cut to the steps whose data survived (module docstring, step 4)."""
    names = [c for c in data if c.startswith("/steps/")]
    found = min((int(data[c].shape[0]) for c in names), default=0)
    ends = []
    for g, row in groups.items():
        if g in GROUP_UNITS and row["rows_kept"] < row["rows_found"]:
            t = data.get(f"/{g}/time", np.empty(0))
            ends.append(float(t[-1]) if t.shape[0] else -np.inf)
    keep = found
    if ends and "/steps/t_end" in data:
        t_end = data["/steps/t_end"][:found]
        late = ~(t_end <= min(ends))
        keep = int(np.argmax(late)) if late.any() else found
    status = data.get("/steps/status", np.empty(0, dtype="S16"))[:found]
    index = data.get("/steps/index", np.arange(found))[:found]
    dropped = [int(index[i]) for i in range(keep, found) if status[i] == b"completed"]
    for c in names:
        data[c] = data[c][:keep]
    completed = int(np.count_nonzero(status[:keep] == b"completed"))
    if groups.get("steps") is not None:
        groups["steps"]["rows_kept"] = keep
        if keep < found:
            groups["steps"]["why"] = "; ".join(
                x for x in (groups["steps"]["why"], f"steps {dropped} end after the data that survived") if x
            )
    return {"kept": keep, "found": found, "dropped": dropped, "completed_kept": completed}


def _add_events(data: dict[str, np.ndarray], groups: dict[str, dict[str, Any]]) -> None:
    """One /events row of kind "salvaged" per group cut, at the latest time kept (if the file has /events)."""
    cols = ("/events/time", "/events/kind", "/events/instrument", "/events/message")
    if any(c not in data for c in cols):
        return
    times = [float(data[f"/{g}/time"][-1]) for g in groups if f"/{g}/time" in data and data[f"/{g}/time"].shape[0]]
    at = max(times, default=0.0)
    rows = [
        f"salvage: /{g} kept {r['rows_kept']} of {r['rows_found']} rows ({r['why']})"
        for g, r in groups.items()
        if r["rows_kept"] < r["rows_found"]
    ]
    if not rows:
        return
    width = {c: data[c].dtype.itemsize for c in cols[1:]}
    new = {
        "/events/time": np.full(len(rows), at),
        "/events/kind": np.array([b"salvaged"] * len(rows), dtype=f"S{width['/events/kind']}"),
        "/events/instrument": np.array([b""] * len(rows), dtype=f"S{width['/events/instrument']}"),
        "/events/message": np.array(
            [_fit(m, width["/events/message"]) for m in rows], dtype=f"S{width['/events/message']}"
        ),
    }
    for c in cols:
        data[c] = np.concatenate([data[c].astype(new[c].dtype), new[c]])


def _fit(text: str, size: int) -> bytes:
    raw = text.encode("utf-8")
    return raw if len(raw) <= size else raw[: size - 3].decode("utf-8", "ignore").encode("utf-8") + b"..."


def salvage_summary(attrs: dict[str, Any]) -> str:
    """What a salvaged file lost, in words, for the top of `qmg-lab analyze` ("" for a file never salvaged)."""
    source = attrs.get("salvaged_from")
    if not source:
        return ""
    lines = [f"SALVAGED from {source}: this file holds only what still read"]
    try:
        groups = json.loads(str(attrs.get("salvage_groups", "{}")))
        steps = json.loads(str(attrs.get("salvage_steps", "{}")))
    except ValueError:
        groups, steps = {}, {}
    for g, r in groups.items():
        if r.get("rows_kept", 0) < r.get("rows_found", 0):
            lines.append(f"  /{g}: {r['rows_kept']} of {r['rows_found']} rows kept ({r.get('why') or 'cut'})")
    if steps.get("dropped"):
        lines.append(f"  steps dropped (their data did not survive): {steps['dropped']}")
    if len(lines) == 1:
        lines.append("  every group whole")
    return "\n".join(lines)


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


#: how long the child of `scan_isolated` / `salvage_isolated` may go without reporting progress, s: it reports
#: before every member list, every dataset it opens and every chunk it reads or copies (milliseconds each on an
#: intact file), so a child silent this long is looping inside HDF5's C code on a damaged part of the file. A
#: limit on progress, not on the whole run, so that a long run's salvage (minutes of chunks) is not stopped, and a
#: damaged file is answered within the 5 s a reader has: the child's start + this
STALL_S = 3.0
#: how long the child may take to start (a Python with numpy and h5py, on a loaded machine) before it reports
START_S = 20.0
_STARTED, _BEAT = "started", "."


def _beat() -> None:
    """Progress, reported by the child (`_main` turns this on); a no-op in any other process."""
    if _REPORTING.is_set():
        sys.stdout.write(_BEAT + "\n")
        sys.stdout.flush()


_REPORTING = threading.Event()  # set in the child only


def _in_child(argv: list[str], what: str, path: Path, stall_s: float = STALL_S, start_s: float = START_S) -> str:
    """Run `python -m qmg_lab.storage.salvage ARGV` and stop it once it has reported no progress for `stall_s`
    (after its start, allowed `start_s`): HDF5 can loop inside its C code on bytes that decode as nonsense (a
    zero-filled attribute heap was seen to), where only a child can be stopped. Its reports are read by a thread
    into a queue (a pipe cannot be polled on Windows). Returns its result line; StorageError in words if it
    fails or stops progressing."""
    full = [sys.executable, "-m", "qmg_lab.storage.salvage", *argv]
    proc = subprocess.Popen(
        full, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=child_env(), stdin=subprocess.DEVNULL
    )
    lines: queue.Queue[str | None] = queue.Queue()
    said: list[str] = []

    def pump_stdout() -> None:
        assert proc.stdout is not None
        for line in proc.stdout:
            lines.put(line.rstrip("\n"))
        lines.put(None)

    def pump_stderr() -> None:
        assert proc.stderr is not None
        said.append(proc.stderr.read())

    readers = [threading.Thread(target=f, daemon=True) for f in (pump_stdout, pump_stderr)]
    for t in readers:
        t.start()
    result, limit, started = "", start_s, False
    try:
        while True:
            try:
                line = lines.get(timeout=limit)
            except queue.Empty:
                proc.kill()
                proc.wait()
                if not started:
                    raise DamagedFileError(
                        f"{path}: {what} did not start within {start_s:g} s (the machine is too busy?)"
                    ) from None
                raise DamagedFileError(
                    f"{path}: {what} did not finish: no progress within {stall_s:g} s, HDF5 loops on a damaged "
                    "part of the file"
                ) from None
            if line is None:
                break
            if line == _STARTED:
                started, limit = True, stall_s
            elif line == _BEAT:
                limit = stall_s
            else:
                result = line
    finally:
        if proc.poll() is None:
            proc.kill()
        proc.wait()
        for t in readers:
            t.join(timeout=5.0)
    if proc.returncode != 0:
        words = " ".join("".join(said).split()[-60:]) or f"exit {proc.returncode}"
        raise StorageError(f"{path}: {what} failed: {words}")
    return result


def scan_isolated(path: str | Path, stall_s: float = STALL_S, start_s: float = START_S) -> list[DatasetScan]:
    """`scan` in a child process stopped when it stops progressing (`_in_child`)."""
    out = _in_child(["scan", str(path)], "the scan of what still reads", Path(path), stall_s, start_s)
    return [DatasetScan(**row) for row in json.loads(out)]


def salvage_isolated(source: str | Path, target: str | Path) -> list[DatasetScan]:
    """`salvage` in a child process stopped when it stops progressing (`_in_child`); nothing is left at `target`
    if it fails."""
    dst = Path(target)
    try:
        out = _in_child(["salvage", str(source), str(target)], "salvage", Path(source))
    except StorageError:
        for partial in dst.parent.glob(f".{dst.name}.*.salvaging"):  # a stopped child's unfinished copy
            partial.unlink(missing_ok=True)
        raise
    return [DatasetScan(**row) for row in json.loads(out)]


def _main(argv: list[str]) -> int:
    """The child of `scan_isolated` / `salvage_isolated`: the scan as JSON on stdout; exit 1 with the words on
    stderr for a StorageError. Its progress goes to stdout too, one line per step (`_beat`)."""
    _REPORTING.set()
    print(_STARTED, flush=True)
    try:
        rows = scan(argv[1]) if argv[0] == "scan" else salvage(argv[1], argv[2])
    except StorageError as exc:
        print(str(exc), file=sys.stderr)
        return 1
    print(json.dumps([r.__dict__ for r in rows]))
    return 0


if __name__ == "__main__":
    sys.exit(_main(sys.argv[1:]))
