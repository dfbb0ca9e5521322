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

Every reader opens through `open_run_file` (qmg_lab/storage/runfile.py), and `h5py.File(` appears only in
qmg_lab/storage/. A fast, deterministic subset of the damaged-file soak (benchmarks/damaged_files.py): the
8-byte file (the HDF5 signature alone), a flipped byte in a chunk index and a zeroed 4 KiB metadata block, each
in a file closed cleanly and in one whose writer flags are set (as a killed writer leaves it), are answered by
every reader with a StorageError in words (never an h5py exception or a traceback), and `runs` lists the
intact file beside them. Fill rows (NaN) are never returned as data. Salvage keeps each group's own prefix and
says what it dropped.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import struct
import subprocess
from pathlib import Path

import h5py
import numpy as np
import pytest

import qmg_lab
from qmg_lab.data.summary import list_runs
from qmg_lab.storage.h5clear import superblock_bytes, superblock_checksum
from qmg_lab.storage.layout import DamagedFileError, StorageError
from qmg_lab.storage.reader import read_run
from qmg_lab.storage.resume import check_resumable
from qmg_lab.storage.salvage import scan, scan_isolated
from qmg_lab.storage.superblock import check_file_end, read_superblock
from qmg_lab.watch.follow import RunFollower
from tests.support.campaigns import config_text, qmg

ROOT = Path(__file__).resolve().parents[2]

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
    # per group, not per file: what did not lose a chunk is whole, and what was dropped is recorded
    assert run.groups["truth"]["time"].shape[0] == original.groups["truth"]["time"].shape[0]
    groups = json.loads(run.attrs["salvage_groups"])
    found = original.groups["lockin"]["time"].shape[0]
    assert groups["lockin"]["rows_kept"] == 2 * chunk_rows and groups["lockin"]["rows_found"] == found
    assert "rate_output" in groups["lockin"]["why"]
    assert groups["clsf"]["rows_kept"] == groups["clsf"]["rows_found"]
    # only the steps whose data survived: those that end by the last /lockin time kept
    t_kept = float(run.groups["lockin"]["time"][-1])
    ends = original.steps["t_end"][original.steps["status"] == "completed"]
    survived = int(np.count_nonzero(ends <= t_kept))
    assert 0 < survived < ends.shape[0]
    assert int(np.count_nonzero(run.steps["status"] == "completed")) == survived
    assert json.loads(run.attrs["salvage_steps"])["dropped"] == [
        int(i) for i, t in zip(original.steps["index"], original.steps["t_end"], strict=True) if t > t_kept
    ]
    with h5py.File(new, "r") as h5:
        kinds = [k.decode() for k in h5["events/kind"][:]]
        messages = [m.decode() for m in h5["events/message"][:]]
    said = [m for k, m in zip(kinds, messages, strict=True) if k == "salvaged"]
    assert any(f"/lockin kept {2 * chunk_rows} of {found} rows" in m for m in said), said
    assert any("/steps kept" in m for m in said), said
    done = subprocess.run(qmg("analyze", str(new), "--json"), capture_output=True, text=True, timeout=HANG_GUARD_S)
    assert done.returncode == 0 and "Traceback" not in done.stderr, done.stderr
    result = json.loads(done.stdout)
    assert result["salvaged"].startswith(f"SALVAGED from {damaged}")
    assert result["steps_completed"] == survived  # no claim for a step whose samples are gone
    done = subprocess.run(qmg("analyze", str(new)), capture_output=True, text=True, timeout=HANG_GUARD_S)
    assert done.stdout.lstrip().startswith("SALVAGED"), done.stdout[:300]  # said first, before the results


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


def test_h5py_files_are_opened_only_in_storage() -> None:
    """Every reader goes through open_run_file (qmg_lab/storage/runfile.py): no `h5py.File(` elsewhere."""
    outside = [
        f"{p.relative_to(ROOT)}:{i}"
        for p in sorted((ROOT / "qmg_lab").rglob("*.py"))
        if "storage" not in p.relative_to(ROOT / "qmg_lab").parts[:1]
        for i, line in enumerate(p.read_text(encoding="utf-8").splitlines(), 1)
        if "h5py.File(" in line
    ]
    assert outside == []


def _flagged(src: Path, dst: Path) -> Path:
    """A copy of src whose superblock says a writer still has it open (flags 0x05, checksum rewritten): what a
    killed writer leaves, read through SWMR after a child-process walk."""
    shutil.copyfile(src, dst)
    body = bytearray(superblock_bytes(dst))
    body[11] = 0x05
    with open(dst, "r+b") as fh:
        fh.write(bytes(body) + struct.pack("<I", superblock_checksum(bytes(body))))
    return dst


def _every_reader_says_why(path: Path, intact: Path, folder: Path) -> list[str]:
    """Each in-process reader on a damaged file: the StorageError it raised (never another exception)."""
    said = []
    for read in (
        lambda: read_run(path),
        lambda: qmg_lab.open_run(path).to_pandas("lockin"),
        lambda: check_resumable(path, config_sha256="0" * 64),
    ):
        with pytest.raises(StorageError) as exc:
            read()
        said.append(str(exc.value))
    assert RunFollower(path).poll().problem
    folder.mkdir()
    shutil.copyfile(path, folder / "bad.h5")
    shutil.copyfile(intact, folder / "good.h5")
    rows = {Path(r["file"]).name: r for r in list_runs(folder)}
    assert rows["bad.h5"]["status"].startswith("unreadable: ")
    assert rows["good.h5"]["status"] == "completed"  # one bad file never loses the listing
    return said


def test_the_8_byte_file_is_answered_in_words(run_file: Path, tmp_path: Path) -> None:
    eight = _cut_copy(run_file, tmp_path / "eight.h5", 8)
    for said in _every_reader_says_why(eight, run_file, tmp_path / "dir"):
        assert "superblock is cut off" in said
    with pytest.raises(StorageError, match="superblock is cut off"):
        scan(eight)
    for argv in (("analyze", str(eight)), ("salvage", str(eight), "-o", str(tmp_path / "new.h5"))):
        done = subprocess.run(qmg(*argv), capture_output=True, text=True, timeout=HANG_GUARD_S)
        assert done.returncode == 2 and "Traceback" not in done.stderr, done.stderr
        assert "superblock is cut off" in " ".join(done.stderr.split())


def _signature_offset(path: Path, signature: bytes, after: int = 0) -> int:
    """Where the first HDF5 structure with this signature at or after byte `after` starts."""
    found = [m.start() for m in re.finditer(re.escape(signature), path.read_bytes()) if m.start() >= after]
    assert found, f"no {signature!r} in {path} after byte {after}"
    return found[0]


@pytest.mark.parametrize("flags", ["closed", "writer flags set"])
@pytest.mark.parametrize("damage", ["flipped chunk-index byte", "zeroed 4 KiB metadata block"])
def test_damaged_metadata_is_answered_in_words(run_file: Path, tmp_path: Path, flags: str, damage: str) -> None:
    """A chunk index block (extensible array data block, HDF5 signature EADB) with one byte inverted, or the
    4 KiB block holding the first object header (OHDR) past the superblock's block zeroed: every reader says
    the file is damaged."""
    bad = tmp_path / "bad.h5"
    shutil.copyfile(run_file, bad)
    raw = bytearray(bad.read_bytes())
    if damage == "flipped chunk-index byte":
        at = _signature_offset(bad, b"EADB") + 12
        raw[at] ^= 0xFF
    else:
        at = _signature_offset(bad, b"OHDR", after=4096) // 4096 * 4096  # past the superblock
        raw[at : at + 4096] = bytes(4096)
    bad.write_bytes(bytes(raw))
    if flags == "writer flags set":
        bad = _flagged(bad, tmp_path / "flagged.h5")
    said = _every_reader_says_why(bad, run_file, tmp_path / "dir")
    assert all(str(bad) in s for s in said)
    done = subprocess.run(qmg("analyze", str(bad)), capture_output=True, text=True, timeout=HANG_GUARD_S)
    assert done.returncode == 2 and "Traceback" not in done.stderr, done.stderr
    assert "damaged" in done.stderr


def test_fill_rows_are_never_data(run_file: Path, tmp_path: Path) -> None:
    """Rows whose time is valid but whose other columns hold the fill value (NaN), as two disk-full stops and
    resumes left in /truth/rate, and NaN rows at a group's end: read_run and open_run return neither."""
    path = tmp_path / "fill.h5"
    shutil.copyfile(run_file, path)
    with h5py.File(path, "r+", libver="latest") as h5:
        n = h5["truth/time"].shape[0]
        rate = h5["truth/rate"]
        rate[1000:1500] = np.nan  # time valid, rate never written
        for c in h5["clsf"]:  # the last 3 CLSF rows allocated, never written
            h5["clsf"][c][-3:] = np.nan
    run = read_run(path)
    assert run.groups["truth"]["rate"].shape[0] == n - 500
    assert np.isfinite(run.groups["truth"]["rate"]).all()
    clsf_rows = read_run(run_file).groups["clsf"]["time"].shape[0]
    assert run.groups["clsf"]["time"].shape[0] == clsf_rows - 3
    opened = qmg_lab.open_run(path)
    truth = opened.to_pandas("truth")
    assert truth.shape[0] == n - 500 and np.isfinite(truth.to_numpy()).all()
    assert opened.to_pandas("clsf").shape[0] == clsf_rows - 3


def test_both_format_versions_read(run_file: Path, tmp_path: Path) -> None:
    """A file that says qmg-lab/1 (written before /2, without the columns /2 added) still reads."""
    old = tmp_path / "old.h5"
    shutil.copyfile(run_file, old)
    with h5py.File(old, "r+", libver="latest") as h5:
        h5.attrs["format"] = "qmg-lab/1"
        if "pll_locked" in h5["lockin"]:
            del h5["lockin/pll_locked"]
    assert read_run(old).attrs["format"] == "qmg-lab/1"
    assert qmg_lab.open_run(old).attrs["format"] == "qmg-lab/1"
    assert read_run(run_file).attrs["format"] == "qmg-lab/2"


def test_a_scan_that_does_not_finish_is_stopped_in_words(run_file: Path, tmp_path: Path) -> None:
    """HDF5 can loop inside its C code on damaged metadata (benchmarks/damaged_files.py found killed files cut
    in their first 4 KiB whose zero-padded attribute heap does so), where no thread can stop it; so the scan and
    salvage run in a child process stopped when it reports no progress. A limit shorter than a Python start makes
    any file such a case: the child is stopped and the answer is a StorageError in words, not a hang."""
    cut = _cut_copy(run_file, tmp_path / "cut.h5", 3707)
    with pytest.raises(StorageError, match=r"did not start within 0\.01 s"):
        scan_isolated(cut, start_s=0.01)
