"""The HDF5 superblock's end-of-file address: a file that ends before it is answered at once, before any SWMR open.

HDF5 opened with `swmr=True` retries a metadata read that fails its checksum (a reader may have caught the
writer half-way): on a file cut short (a copy that stopped, a disk that filled) that retry loop lasts minutes.
A non-SWMR open fails at once ("truncated file: eof = ..., stored_eof = ..."), but SWMR is how run files are read.
So every reader here first compares the file's size with the end-of-file address its superblock records.

The superblock (HDF5 File Format Specification, section II.A, "Disk Format: Level 0A - Format Signature and
Superblock") starts with the 8-byte signature 0x89 'HDF' CR LF 0x1A LF at offset 0, 512, 1024, 2048, ... (a user
block may come first), then its version byte:

* versions 0 and 1: byte 13 = size of offsets O (bytes per address), byte 14 = size of lengths; then group leaf
  and internal node K (2 + 2 bytes) and the file consistency flags (4 bytes); version 1 adds the indexed storage
  internal node K (2) and 2 reserved bytes. The four addresses follow at byte 24 (version 0) or 28 (version 1):
  base address, free-space info address, **end of file address**, driver information block address.
* versions 2 and 3 (what `libver="latest"` writes, so every qmg-lab file): byte 9 = size of offsets O, byte 10
  = size of lengths, byte 11 = file consistency flags; at byte 12 the base address, superblock extension
  address, **end of file address**, root group object header address (O bytes each, little-endian), then a
  4-byte lookup3 checksum (qmg_lab/storage/h5clear.py checks and rewrites it).

The end of file address is the first byte past all HDF5 data (HDF5 allocates up to it and, at every flush,
extends the file to it); HDF5's own check (H5Fsuper.c) refuses a file whose size is below it. An address of all
0xFF bytes is "undefined" and not checked.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

from qmg_lab.storage.layout import DamagedFileError, StorageError

SIGNATURE = b"\x89HDF\r\n\x1a\n"
#: where the superblock may start: 0, then 512 doubled (a user block of 512, 1024, 2048, ... bytes before it)
_MAX_USER_BLOCK_SEARCH = 1 << 30


@dataclass(frozen=True)
class Superblock:
    """What a file's superblock says about its extent."""

    offset: int  # where the superblock starts (the user block's size)
    version: int
    size_of_offsets: int
    base_address: int
    eof_address: int | None  # None: undefined (all 0xFF)


def _address(raw: bytes, size: int) -> int | None:
    value = int.from_bytes(raw[:size], "little")
    return None if value == (1 << (8 * size)) - 1 else value


def read_superblock(path: str | Path) -> Superblock:
    """Parse the superblock (versions 0-3) of an HDF5 file; StorageError if there is none or it is cut off."""
    p = Path(path)
    try:
        size = os.path.getsize(p)
        with open(p, "rb") as fh:
            offset = 0
            while offset < min(size, _MAX_USER_BLOCK_SEARCH):
                fh.seek(offset)
                head = fh.read(96)
                if head[:8] == SIGNATURE:
                    return _parse(p, offset, head)
                offset = 512 if offset == 0 else offset * 2
    except OSError as exc:
        raise StorageError(f"{p}: cannot read it: {exc}") from None
    raise StorageError(f"{p}: not an HDF5 file (no HDF5 signature; {size} bytes)")


def _parse(p: Path, offset: int, head: bytes) -> Superblock:
    if len(head) < 9:
        raise StorageError(
            f"{p}: the HDF5 superblock is cut off: the file ends {len(head)} bytes after its signature "
            f"(the file is {offset + len(head)} bytes)"
        )
    version = head[8]
    if version in (0, 1):
        if len(head) < 16:
            raise StorageError(f"{p}: the HDF5 superblock is cut off (the file is {offset + len(head)} bytes)")
        o = head[13]
        start = 24 if version == 0 else 28
    elif version in (2, 3):
        if len(head) < 12:
            raise StorageError(f"{p}: the HDF5 superblock is cut off (the file is {offset + len(head)} bytes)")
        o = head[9]
        start = 12
    else:
        raise StorageError(f"{p}: unknown HDF5 superblock version {version}")
    if o not in (2, 4, 8, 16):
        raise StorageError(f"{p}: HDF5 superblock: size of offsets {o} is not 2, 4, 8 or 16: the file is damaged")
    need = start + 3 * o
    if len(head) < need:
        raise StorageError(f"{p}: the HDF5 superblock is cut off (the file is {offset + len(head)} bytes)")
    base = _address(head[start:], o) or 0
    eof = _address(head[start + 2 * o :], o)
    return Superblock(offset=offset, version=version, size_of_offsets=o, base_address=base, eof_address=eof)


def check_file_end(path: str | Path) -> Superblock:
    """Refuse (StorageError, at once) a file that ends before the end-of-file address its superblock records:
    it was cut short, and HDF5's SWMR open would retry for minutes. Returns the superblock."""
    p = Path(path)
    sb = read_superblock(p)
    size = os.path.getsize(p)
    if sb.eof_address is not None and size < sb.eof_address:
        raise DamagedFileError(
            f"{p}: the file is cut short: it ends at {size} bytes, but its HDF5 superblock records data up to "
            f"{sb.eof_address} bytes ({sb.eof_address - size} bytes missing: an incomplete copy or a full disk). "
            f"Copy what still reads into a new file with `qmg-lab salvage {p} -o NEW.h5`"
        )
    return sb
