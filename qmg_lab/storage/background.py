"""One worker thread that runs a run file's HDF5 writes, in submission order, beside the campaign.

h5py releases the GIL inside HDF5's own calls (the dataset write, the filters that compress a chunk, the file
flush), so while the worker writes and compresses one batch of rows the campaign's thread simulates, estimates and
buffers the next: on a machine with a free core the write cost leaves the campaign's critical path. h5py's global
lock still lets only one thread into HDF5 at a time, so the campaign's own small HDF5 calls (attributes, /events
rows) stay correct; they just wait for the write in progress.

Protocol:

* `submit(job)` queues a callable; at most `max_pending` jobs wait (the caller blocks beyond that), so the rows
  in flight, and the memory they hold, stay bounded whatever the campaign's length.
* `drain()` returns once every submitted job has run: what a checkpoint (a /steps row, a status, `flush`) needs.
* A job that raises stops the worker from running later jobs (their rows would follow a hole); the exception is
  re-raised in the caller's thread by the next `submit`, `drain` or `raise_error`.
* `close()` runs what is queued, then ends the thread. A killed process loses the queued rows, exactly as it
  loses rows still buffered in memory: the file on disk is the consistent snapshot of the last HDF5 flush.
"""

from __future__ import annotations

import queue
import threading
from collections.abc import Callable

Job = Callable[[], None]


class BackgroundWrites:
    """A single daemon worker thread executing submitted jobs in order (see the module docstring)."""

    def __init__(self, name: str, max_pending: int = 2) -> None:
        if max_pending < 1:
            raise ValueError(f"max_pending must be >= 1, got {max_pending}")
        self._queue: queue.Queue[Job | None] = queue.Queue(maxsize=max_pending)
        self._error: BaseException | None = None
        self._failed = False  # a job raised: later jobs are skipped (set by the worker, never cleared)
        self._closed = False
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while True:
            job = self._queue.get()
            try:
                if job is None:
                    return
                if not self._failed:  # after a failure, later rows would follow a hole: skip them
                    job()
            except BaseException as exc:
                self._failed = True
                self._error = exc
            finally:
                self._queue.task_done()

    def raise_error(self) -> None:
        """Re-raise, in the caller's thread, the exception a job raised (once)."""
        if self._error is not None:
            exc, self._error = self._error, None
            raise exc

    def submit(self, job: Job) -> None:
        """Queue `job` (blocks while `max_pending` jobs wait)."""
        if self._closed:
            raise RuntimeError("BackgroundWrites is closed")
        self.raise_error()
        self._queue.put(job)

    def drain(self) -> None:
        """Wait until every submitted job has run; re-raise a job's exception."""
        if not self._closed:
            self._queue.join()
        self.raise_error()

    def close(self) -> None:
        """Run what is queued, end the thread (idempotent). A job's exception is left for `raise_error`."""
        if self._closed:
            return
        self._closed = True
        self._queue.put(None)
        self._thread.join()
