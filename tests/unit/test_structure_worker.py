"""The worker process that walks run files' structure for `open_run_file` (qmg_lab/storage/runfile.py step 3,
qmg_lab/storage/probe.py): one worker serves a process's files one after another; a walk over its time limit
kills it and is answered in words; a worker that ended between two files is replaced without blaming the next
file; a worker whose input closes ends by itself; it runs in a process group of its own, so that a Ctrl-C
meant for the campaign does not reach it."""

from __future__ import annotations

import os
import select
import signal
from collections.abc import Iterator
from pathlib import Path

import h5py
import numpy as np
import pytest

from qmg_lab.storage import runfile
from qmg_lab.storage.layout import DamagedFileError


def _small_file(path: Path) -> Path:
    """An HDF5 file laid out like a run file's data group: chunked, extensible, with attributes."""
    with h5py.File(path, "w", libver="latest") as h5:
        h5.attrs["format"] = "qmg-lab/2"
        grp = h5.create_group("lockin")
        ds = grp.create_dataset("time", data=np.arange(5000.0), chunks=(1024,), maxshape=(None,))
        ds.attrs["units"] = "s"
    return path


@pytest.fixture
def service() -> Iterator[runfile._ProbeService]:
    """A service of its own, closed at the end (the module's one service is the process's)."""
    svc = runfile._ProbeService()
    yield svc
    svc.close()


def test_one_worker_walks_file_after_file(tmp_path: Path, service: runfile._ProbeService) -> None:
    files = [_small_file(tmp_path / f"f{i}.h5") for i in range(3)]
    service.walk(files[0], runfile.PROBE_TIMEOUT_S)
    assert service.worker is not None
    pid = service.worker.proc.pid
    for f in files[1:]:
        service.walk(f, runfile.PROBE_TIMEOUT_S)
    assert service.worker.proc.pid == pid


def test_a_walk_over_its_limit_is_answered_and_its_worker_replaced(
    tmp_path: Path, service: runfile._ProbeService
) -> None:
    """A limit shorter than any walk stands for HDF5 looping in its C code: the worker is killed, the file is
    called damaged in words, and the next file gets a new worker that walks it."""
    f = _small_file(tmp_path / "f.h5")
    service.walk(f, runfile.PROBE_TIMEOUT_S)
    assert service.worker is not None
    first = service.worker.proc
    with pytest.raises(DamagedFileError, match=r"did not finish reading the file's structure within 1e-06 s"):
        service.walk(f, 1e-6)
    assert first.poll() is not None  # killed, not left walking
    service.walk(f, runfile.PROBE_TIMEOUT_S)
    assert service.worker is not None and service.worker.proc.pid != first.pid


def test_a_walk_that_fails_names_the_file_and_the_error(tmp_path: Path, service: runfile._ProbeService) -> None:
    """Bytes that are not HDF5 past a valid superblock: HDF5's error comes back in words with the file's name."""
    f = _small_file(tmp_path / "f.h5")
    raw = bytearray(f.read_bytes())
    at = raw.index(b"OHDR", 64)
    raw[at : at + 64] = b"\xa5" * 64
    f.write_bytes(bytes(raw))
    with pytest.raises(DamagedFileError, match=rf"{f.name}: its structure does not read \(the file is damaged\): "):
        service.walk(f, runfile.PROBE_TIMEOUT_S)
    assert service.worker is None  # a worker that met damaged metadata is not reused


def test_a_worker_ended_between_files_is_replaced_without_blame(tmp_path: Path, service: runfile._ProbeService) -> None:
    f = _small_file(tmp_path / "f.h5")
    service.walk(f, runfile.PROBE_TIMEOUT_S)
    assert service.worker is not None
    service.worker.proc.kill()  # a signal meant for it, or its watchdog
    service.worker.proc.wait()
    service.walk(f, runfile.PROBE_TIMEOUT_S)  # no DamagedFileError: the file is whole
    assert service.worker is not None and service.worker.proc.poll() is None


def test_a_worker_whose_input_closes_ends_by_itself(tmp_path: Path, service: runfile._ProbeService) -> None:
    """The parent's death closes the worker's input: it ends (exit 0), it is not left running."""
    service.walk(_small_file(tmp_path / "f.h5"), runfile.PROBE_TIMEOUT_S)
    worker = service.worker
    assert worker is not None and worker.proc.stdin is not None
    worker.proc.stdin.close()
    assert worker.proc.wait(timeout=runfile.WORKER_STOP_S * 10) == 0


@pytest.mark.skipif(os.name == "nt", reason="process groups are POSIX; Windows uses CREATE_NEW_PROCESS_GROUP")
def test_the_worker_has_a_process_group_of_its_own(tmp_path: Path, service: runfile._ProbeService) -> None:
    """A terminal's Ctrl-C or hang-up goes to the foreground process group: the campaign's, not the worker's."""
    service.walk(_small_file(tmp_path / "f.h5"), runfile.PROBE_TIMEOUT_S)
    assert service.worker is not None
    assert os.getpgid(service.worker.proc.pid) != os.getpgid(0)


def test_a_worker_started_ahead_serves_the_next_walk(tmp_path: Path, service: runfile._ProbeService) -> None:
    """`start_structure_worker` (a campaign, for its read-back): the worker started before any file is the one
    that walks the first file."""
    service.start()
    assert service.worker is not None
    pid = service.worker.proc.pid
    service.walk(_small_file(tmp_path / "f.h5"), runfile.PROBE_TIMEOUT_S)
    assert service.worker.proc.pid == pid


@pytest.mark.skipif(not hasattr(os, "fork"), reason="fork() is POSIX")
def test_a_forked_child_walks_with_a_worker_of_its_own(tmp_path: Path) -> None:
    """A process that forks after its first file (multiprocessing's default on Linux), while another of its
    threads is in a walk (the service's lock held): the child's walk starts its own worker instead of waiting
    for ever on a lock no thread of the child will release, and the parent's worker keeps serving the parent."""
    f = _small_file(tmp_path / "f.h5")
    runfile.forget_walks()
    runfile._probe_in_child(f, runfile.PROBE_TIMEOUT_S)
    parent_worker = runfile._PROBE_SERVICE.worker
    assert parent_worker is not None
    r, w = os.pipe()
    with runfile._PROBE_SERVICE.lock:  # as a walk in another thread holds it
        pid = os.fork()
        if pid == 0:  # the child: report its worker's pid (0 if its walk failed), then leave at once
            os.close(r)
            try:
                runfile._probe_in_child(f, runfile.PROBE_TIMEOUT_S)
                worker = runfile._PROBE_SERVICE.worker
                said = str(worker.proc.pid if worker is not None else 0)
            except BaseException as exc:
                said = f"error {exc}"
            os.write(w, said.encode())
            os._exit(0)
    os.close(w)
    ready, _, _ = select.select([r], [], [], 60.0)
    if not ready:
        os.kill(pid, signal.SIGKILL)
    os.waitpid(pid, 0)
    with os.fdopen(r) as fh:
        said = fh.read() if ready else "the child's walk hung (the lock it inherited was held)"
    assert said.isdigit() and int(said) not in (0, parent_worker.proc.pid), said
    runfile._probe_in_child(_small_file(tmp_path / "g.h5"), runfile.PROBE_TIMEOUT_S)
    assert runfile._PROBE_SERVICE.worker is parent_worker  # the parent's worker still serves the parent
