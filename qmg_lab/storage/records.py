"""Snapshots and the event log of a run file: /snapshots and /events (docs/hdf5.md, "Snapshots and events").

Like QCoDeS's station snapshot, every run records, at its start and at each resume, each instrument's
identity, firmware, settings and state as one JSON document; and it keeps a log of every fault, reconnect,
recovery, suspension, abort and safe state with its run time.

The run file is in HDF5 SWMR mode while it is written, where no group, dataset or attribute can be created:
`create_groups(h5)` lays both groups out before SWMR starts (RunWriter.create, and RunWriter.reopen for files
from before this layout), and `RunRecords` only appends rows to the existing extendable datasets.

/snapshots: one row per instrument and occasion
    time (s since t0_unix), instrument (text), occasion ("start" | "resume"), offset, length (bytes into json)
    json: uint8, the UTF-8 JSON documents one after another; row i is json[offset[i] : offset[i] + length[i]]
/events: one row per event
    time (s since t0_unix), kind (text), instrument (text, "" for the campaign), message (UTF-8 text, at most
    EVENT_MESSAGE_BYTES; longer messages are cut and end in "...")
"""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

import h5py
import numpy as np

log = logging.getLogger(__name__)

NAME_BYTES = 16
EVENT_MESSAGE_BYTES = 400
EVENT_KINDS = (
    "fault",
    "reconnect",
    "recovered",
    "suspended",
    "resumed",
    "abort",
    "interrupted",
    "safe_state",
    "completed",
    "started",
    "salvaged",
)
CHUNK = 64
JSON_CHUNK = 16384

SNAPSHOT_COLUMNS: dict[str, tuple[Any, str, str]] = {
    "time": (np.float64, "s", "run time of the snapshot, s since the root attribute t0_unix"),
    "instrument": (f"S{NAME_BYTES}", "text", "lockin | generator | table | chamber"),
    "occasion": (f"S{NAME_BYTES}", "text", "start (a new run) | resume (each --resume)"),
    "offset": (np.int64, "byte", "start of this snapshot's JSON document in /snapshots/json"),
    "length": (np.int64, "byte", "length of this snapshot's JSON document in /snapshots/json"),
}
EVENT_COLUMNS: dict[str, tuple[Any, str, str]] = {
    "time": (np.float64, "s", "run time of the event, s since the root attribute t0_unix"),
    "kind": (f"S{NAME_BYTES}", "text", " | ".join(EVENT_KINDS)),
    "instrument": (f"S{NAME_BYTES}", "text", "the instrument concerned; empty for the campaign as a whole"),
    "message": (f"S{EVENT_MESSAGE_BYTES}", "text", "what happened (UTF-8)"),
}


def create_groups(h5: h5py.File) -> None:
    """Create /snapshots and /events (if absent). Must run before the file enters SWMR mode."""
    if "snapshots" not in h5:
        g = h5.create_group("snapshots")
        for col, (dtype, units, desc) in SNAPSHOT_COLUMNS.items():
            ds = g.create_dataset(col, shape=(0,), maxshape=(None,), dtype=dtype, chunks=(CHUNK,))
            ds.attrs["units"], ds.attrs["description"] = units, desc
        ds = g.create_dataset("json", shape=(0,), maxshape=(None,), dtype=np.uint8, chunks=(JSON_CHUNK,))
        ds.attrs["units"] = "byte"
        ds.attrs["description"] = "UTF-8 JSON snapshot documents, one after another (see offset and length)"
    if "events" not in h5:
        g = h5.create_group("events")
        for col, (dtype, units, desc) in EVENT_COLUMNS.items():
            ds = g.create_dataset(col, shape=(0,), maxshape=(None,), dtype=dtype, chunks=(CHUNK,))
            ds.attrs["units"], ds.attrs["description"] = units, desc


def _text(value: str, size: int) -> bytes:
    data = value.encode("utf-8")
    if len(data) <= size:
        return data
    return data[: size - 3].decode("utf-8", "ignore").encode("utf-8") + b"..."


def _append(group: h5py.Group, row: dict[str, Any]) -> None:
    n = group["time"].shape[0]
    for col, value in row.items():
        group[col].resize((n + 1,))
        group[col][n] = value


class RunRecords:
    """Appends snapshots and events to an open run file (SWMR-safe: rows only). Each call flushes the file."""

    def __init__(self, h5: h5py.File, path: Path) -> None:
        self._h5 = h5
        self.path = path
        self.available = "snapshots" in h5 and "events" in h5

    def snapshot(self, time_s: float, instrument: str, occasion: str, document: dict[str, Any]) -> None:
        if not self.available:
            return
        g = self._h5["snapshots"]
        data = np.frombuffer(json.dumps(document, default=str, sort_keys=True).encode("utf-8"), dtype=np.uint8)
        blob = g["json"]
        offset = blob.shape[0]
        blob.resize((offset + data.shape[0],))
        blob[offset:] = data
        _append(
            g,
            {
                "time": float(time_s),
                "instrument": _text(instrument, NAME_BYTES),
                "occasion": _text(occasion, NAME_BYTES),
                "offset": offset,
                "length": int(data.shape[0]),
            },
        )
        self._h5.flush()

    def event(self, time_s: float, kind: str, instrument: str, message: str) -> None:
        if not self.available:
            return
        _append(
            self._h5["events"],
            {
                "time": float(time_s),
                "kind": _text(kind, NAME_BYTES),
                "instrument": _text(instrument, NAME_BYTES),
                "message": _text(message, EVENT_MESSAGE_BYTES),
            },
        )
        self._h5.flush()


def read_snapshots(h5: h5py.File) -> list[dict[str, Any]]:
    """Every snapshot row of an open run file: time, instrument, occasion and the parsed JSON document."""
    if "snapshots" not in h5:
        return []
    g = h5["snapshots"]
    n = min(g[c].shape[0] for c in SNAPSHOT_COLUMNS)
    blob = g["json"][:].tobytes()
    rows = []
    for i in range(n):
        o, k = int(g["offset"][i]), int(g["length"][i])
        rows.append(
            {
                "time": float(g["time"][i]),
                "instrument": g["instrument"][i].decode(),
                "occasion": g["occasion"][i].decode(),
                "document": json.loads(blob[o : o + k].decode("utf-8")),
            }
        )
    return rows


def read_events(h5: h5py.File) -> list[dict[str, Any]]:
    """Every /events row of an open run file as a dict time, kind, instrument, message."""
    if "events" not in h5:
        return []
    g = h5["events"]
    n = min(g[c].shape[0] for c in EVENT_COLUMNS)
    return [
        {
            "time": float(g["time"][i]),
            "kind": g["kind"][i].decode(),
            "instrument": g["instrument"][i].decode(),
            "message": g["message"][i].decode("utf-8", "replace"),
        }
        for i in range(n)
    ]
