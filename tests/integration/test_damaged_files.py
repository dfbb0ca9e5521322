"""Damaged run files are answered, not hung on: `qmg-lab analyze` on copies of a real run file cut at 100 B,
4 KiB, 1 %, 50 % and size - 4 KiB exits 2 with a message saying the file is cut short (and what still reads), no
traceback, and `qmg-lab run --resume` of them exits 2 without changing them. Before this, the SWMR open of such
a file retried for minutes; the subprocess timeout here only guards the suite against that hang (the time each
takes is measured by `python benchmarks/faults.py`, part 5, not asserted here).

A file whose bytes do not decode (a deflate chunk of /lockin/rate_output overwritten) is named: exit 2, the
dataset's name, what still reads; `qmg-lab salvage` copies the rows that read into a new file that `analyze`
reads.

The superblock parser (qmg_lab/storage/superblock.py) is checked against HDF5's own truncation check: for
superblock versions 0 (libver "earliest") and 3 (libver "latest"), a file one byte short is refused by both.
"""

from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path

import h5py
import numpy as np
import pytest

from qmg_lab.storage.layout import DamagedFileError
from qmg_lab.storage.reader import read_run
from qmg_lab.storage.superblock import check_file_end, read_superblock
from tests.support.campaigns import config_text, qmg

HANG_GUARD_S = 120  # a hang would have lasted minutes; the message comes in well under a second


@pytest.fixture(scope="module")
def run_file(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A completed short campaign on the twins, written by the CLI (gzip: the twins' compressed chunks)."""
    tmp = tmp_path_factory.mktemp("damaged")
    cfg = tmp / "short.toml"
    cfg.write_text(config_text())
    path = tmp / "run.h5"
    done = subprocess.run(qmg("run", str(cfg), "-o", str(path), "-q"), capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    return path


def _cut_copy(src: Path, dst: Path, size: int) -> Path:
    with open(src, "rb") as fh:
        dst.write_bytes(fh.read(size))
    return dst


CUTS = {
    "100 B": lambda n: 100,
    "4 KiB": lambda n: 4096,
    "1 %": lambda n: n // 100,
    "50 %": lambda n: n // 2,
    "size - 4 KiB": lambda n: n - 4096,
}


@pytest.mark.parametrize("cut", list(CUTS))
def test_analyze_of_a_file_cut_short_exits_2_without_a_traceback(run_file: Path, tmp_path: Path, cut: str) -> None:
    size = os.path.getsize(run_file)
    copy = _cut_copy(run_file, tmp_path / "cut.h5", CUTS[cut](size))
    done = subprocess.run(qmg("analyze", str(copy)), capture_output=True, text=True, timeout=HANG_GUARD_S)
    assert done.returncode == 2, done.stderr
    assert "Traceback" not in done.stderr
    said = " ".join(done.stderr.split())
    assert "cut short" in said
    assert str(size) not in said or "bytes" in said  # the sizes are named in bytes
    # nor does a --resume of it hang: answered before any SWMR open, the copy unchanged
    cfg = run_file.with_name("short.toml")
    before = copy.read_bytes()
    done = subprocess.run(
        qmg("run", str(cfg), "--resume", str(copy), "-q"), capture_output=True, text=True, timeout=HANG_GUARD_S
    )
    assert done.returncode == 2, done.stderr
    assert "Traceback" not in done.stderr
    assert copy.read_bytes() == before


def _damage_a_chunk(src: Path, dst: Path, dataset: str, chunk: int) -> None:
    shutil.copyfile(src, dst)
    with h5py.File(src, "r", swmr=True, libver="latest") as h5:
        info = h5[dataset].id.get_chunk_info(chunk)
    with open(dst, "r+b") as fh:
        fh.seek(info.byte_offset + 16)
        fh.write(b"\xa5" * 64)  # a deflate stream this breaks no longer decodes


def test_a_dataset_that_does_not_decode_is_named_and_salvaged(run_file: Path, tmp_path: Path) -> None:
    damaged = tmp_path / "damaged.h5"
    _damage_a_chunk(run_file, damaged, "lockin/rate_output", 2)
    with h5py.File(run_file, "r", swmr=True, libver="latest") as h5:
        chunk_rows = h5["lockin/rate_output"].chunks[0]
        assert h5["lockin/rate_output"].compression == "gzip"
        assert h5["lockin/time"].shape[0] > 3 * chunk_rows
    with pytest.raises(DamagedFileError, match="/lockin/rate_output"):
        read_run(damaged)
    done = subprocess.run(qmg("analyze", str(damaged)), capture_output=True, text=True, timeout=HANG_GUARD_S)
    assert done.returncode == 2, done.stderr
    said = " ".join(done.stderr.split())
    assert "/lockin/rate_output" in said and "Traceback" not in said
    assert f"/lockin/rate_output: {2 * chunk_rows} of" in said  # what still reads: the two chunks before
    assert "/clsf/time:" in said  # and the rest, whole

    new = tmp_path / "salvaged.h5"
    done = subprocess.run(qmg("salvage", str(damaged), "-o", str(new)), capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    run = read_run(new)
    # /lockin keeps its whole rows: the rows before the damaged chunk, with the original values
    assert run.groups["lockin"]["time"].shape[0] == 2 * chunk_rows
    original = read_run(run_file)
    for c in ("time", "rate_output", "x_sense"):
        assert np.array_equal(run.groups["lockin"][c], original.groups["lockin"][c][: 2 * chunk_rows])
    assert np.array_equal(run.groups["clsf"]["eta"], original.groups["clsf"]["eta"])
    assert run.attrs["salvaged_from"] == str(damaged)
    done = subprocess.run(qmg("analyze", str(new)), capture_output=True, text=True, timeout=HANG_GUARD_S)
    assert "Traceback" not in done.stderr


@pytest.mark.parametrize("libver", ["earliest", "latest"])
def test_the_superblock_end_of_file_matches_hdf5s_own_check(tmp_path: Path, libver: str) -> None:
    path = tmp_path / f"{libver}.h5"
    with h5py.File(path, "w", libver=libver) as h5:
        h5.create_dataset("x", data=np.arange(50000.0), chunks=(1000,))
    sb = read_superblock(path)
    assert sb.version == (0 if libver == "earliest" else 3)
    assert sb.eof_address == os.path.getsize(path)  # a closed file ends exactly at its recorded end
    check_file_end(path)
    short = _cut_copy(path, tmp_path / "short.h5", os.path.getsize(path) - 1)
    with pytest.raises(OSError, match="truncated file"):
        h5py.File(short, "r")
    with pytest.raises(DamagedFileError, match="1 bytes missing"):
        check_file_end(short)
