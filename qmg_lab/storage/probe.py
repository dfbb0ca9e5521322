"""The structure check's worker process: `python -m qmg_lab.storage.probe`, started by `open_run_file`
(qmg_lab/storage/runfile.py, step 3) and fed one file at a time.

Protocol, one JSON object a line, UTF-8, over the worker's stdin and stdout:
- the worker writes `{"ready": true}` once its imports are done (h5py loaded: what a Python start costs);
- the parent writes `{"path": "..."}`; the worker walks that file's structure (`probe_structure`) and writes
  `{"problem": ""}` if the walk went through, else `{"problem": "<the error>"}`;
- end of input (the parent closed the pipe, or died) ends the worker.

The parent enforces the time limit of each walk, and kills the worker if it is exceeded (HDF5 looping in its C
code on damaged metadata: only the end of the process stops it). If the parent is gone by then, a watchdog thread
here ends the worker after WORKER_WALK_LIMIT_S of one walk, so a looping walk never outlives its caller.
"""

from __future__ import annotations

import json
import os
import sys
import threading
import time
from pathlib import Path
from typing import IO

import h5py

from qmg_lab.storage.layout import H5_ERRORS, StorageError
from qmg_lab.storage.view import ClearedView

#: a failed walk is tried again this often, this far apart (s): a live writer's flush caught half-way is whole a
#: moment later, a damaged block stays damaged
PROBE_RETRIES = 2
PROBE_PAUSE_S = 0.2
#: the worker's own bound on one walk, s: far above the parent's limit (which kills it first); it matters only
#: when no parent is left to do so
WORKER_WALK_LIMIT_S = 120.0
#: exit code of a worker ended by its watchdog
WATCHDOG_EXIT = 3


def walk_structure(group: h5py.Group) -> None:
    """Read every attribute, member, dataset header and chunk index below `group`."""
    for k in group.attrs:
        group.attrs[k]
    for name in group:
        obj = group[name]
        if isinstance(obj, h5py.Group):
            walk_structure(obj)
        elif isinstance(obj, h5py.Dataset):
            for k in obj.attrs:
                obj.attrs[k]
            if obj.chunks is not None and obj.shape and obj.shape[0]:
                obj.id.chunk_iter(lambda info: None)


def probe_structure(path: Path) -> str:
    """Walk the structure of `path` without SWMR, through ClearedView (nothing retries: a damaged metadata block
    fails at once); "" if the walk went through, else its error. A failed walk is tried again PROBE_RETRIES
    times PROBE_PAUSE_S apart."""
    problem = ""
    for attempt in range(1 + PROBE_RETRIES):
        if attempt:
            time.sleep(PROBE_PAUSE_S)
        try:
            with ClearedView(path) as view, h5py.File(view, "r") as h5:
                walk_structure(h5)
            return ""
        except (*H5_ERRORS, StorageError) as exc:
            problem = problem or f"{type(exc).__name__}: {exc}"
    return problem


def serve(requests: IO[str], replies: IO[str]) -> int:
    """The worker's loop (module docstring): answer each request line until end of input; 0 at the end."""
    replies.write(json.dumps({"ready": True}) + "\n")
    replies.flush()
    for line in requests:
        path = Path(json.loads(line)["path"])
        watchdog = threading.Timer(WORKER_WALK_LIMIT_S, os._exit, args=(WATCHDOG_EXIT,))
        watchdog.daemon = True
        watchdog.start()
        try:
            problem = probe_structure(path)
        finally:
            watchdog.cancel()
        replies.write(json.dumps({"problem": problem}) + "\n")
        replies.flush()
    return 0


def main() -> int:
    """Serve requests on this process's stdin and stdout, in UTF-8 whatever the console's code page."""
    requests = open(sys.stdin.fileno(), encoding="utf-8", closefd=False)  # noqa: SIM115 - the process's stdin
    replies = open(sys.stdout.fileno(), "w", encoding="utf-8", closefd=False)  # noqa: SIM115 - its stdout
    return serve(requests, replies)


if __name__ == "__main__":
    sys.exit(main())
