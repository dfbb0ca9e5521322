"""HDF5 superblock consistency flags: what `h5clear -s` does, so a run file whose writer was killed can be resumed.

HDF5 marks a file opened for (SWMR) writing in the superblock's consistency flags; after a crash they stay set
and HDF5 refuses to open the file for writing. `clear_superblock_flags` resets them and rewrites the superblock's
Jenkins lookup3 checksum; `writer_flags_set` tells whether a file was left open by a writer.
"""

from __future__ import annotations

import os
import struct
from pathlib import Path

from qmg_lab.storage.layout import StorageError


def _lookup3(data: bytes, initval: int = 0) -> int:
    """Bob Jenkins' lookup3 `hashlittle` (public domain), the checksum HDF5 puts on superblock v2/v3.

    Three 32-bit lanes a, b, c start at 0xdeadbeef + len + initval; each 12-byte block is added little-endian
    and mixed, the last (1..12 byte, zero-padded) block is added and put through the final avalanche; the hash
    is c. A zero-length key returns c unmixed.
    """
    m = 0xFFFFFFFF

    def rot(x: int, k: int) -> int:
        return ((x << k) | (x >> (32 - k))) & m

    n = len(data)
    a = b = c = (0xDEADBEEF + n + initval) & m
    if n == 0:
        return c
    pos = 0
    while n - pos > 12:
        x, y, z = struct.unpack_from("<III", data, pos)
        a, b, c = (a + x) & m, (b + y) & m, (c + z) & m
        a = ((a - c) & m) ^ rot(c, 4)
        c = (c + b) & m
        b = ((b - a) & m) ^ rot(a, 6)
        a = (a + c) & m
        c = ((c - b) & m) ^ rot(b, 8)
        b = (b + a) & m
        a = ((a - c) & m) ^ rot(c, 16)
        c = (c + b) & m
        b = ((b - a) & m) ^ rot(a, 19)
        a = (a + c) & m
        c = ((c - b) & m) ^ rot(b, 4)
        b = (b + a) & m
        pos += 12
    x, y, z = struct.unpack("<III", data[pos:].ljust(12, b"\0"))
    a, b, c = (a + x) & m, (b + y) & m, (c + z) & m
    c = (c ^ b) - rot(b, 14) & m
    a = (a ^ c) - rot(c, 11) & m
    b = (b ^ a) - rot(a, 25) & m
    c = (c ^ b) - rot(b, 16) & m
    a = (a ^ c) - rot(c, 4) & m
    b = (b ^ a) - rot(a, 14) & m
    c = (c ^ b) - rot(b, 24) & m
    return c


_SIGNATURE = b"\x89HDF\r\n\x1a\n"


def _superblock(path: Path) -> tuple[bytes, int]:
    """Read a v2/v3 superblock at offset 0: (its bytes without the checksum, its length with the checksum)."""
    with open(path, "rb") as fh:
        head = fh.read(96)
    if len(head) < 12:
        raise StorageError(f"{path}: the HDF5 superblock is cut off (the file is {len(head)} bytes)")
    if head[:8] != _SIGNATURE:
        raise StorageError(f"{path}: not an HDF5 file (no HDF5 signature at offset 0)")
    version = head[8]
    if version not in (2, 3):
        raise StorageError(
            f"{path}: HDF5 superblock version {version}; qmg-lab files use version 3 "
            f"(libver='latest'); this file was not written by qmg-lab"
        )
    size_offsets = head[9]
    if size_offsets not in (2, 4, 8, 16):
        raise StorageError(f"{path}: HDF5 superblock: size of offsets {size_offsets} is not 2, 4, 8 or 16: damaged")
    length = 12 + 4 * size_offsets + 4  # signature..flags, 4 addresses, checksum
    if len(head) < length:
        raise StorageError(f"{path}: the HDF5 superblock is cut off (the file is {len(head)} bytes)")
    body = head[: length - 4]
    (stored,) = struct.unpack_from("<I", head, length - 4)
    if _lookup3(body) != stored:
        raise StorageError(f"{path}: HDF5 superblock checksum mismatch: the file is damaged")
    return body, length


def superblock_bytes(path: str | Path) -> bytes:
    """A v2/v3 superblock at offset 0 without its checksum, checked (StorageError if it is not one or its
    checksum fails)."""
    return _superblock(Path(path))[0]


def superblock_checksum(body: bytes) -> int:
    """The lookup3 checksum HDF5 stores after a v2/v3 superblock's `body`."""
    return _lookup3(body)


def writer_flags_set(path: str | Path) -> bool:
    """True if the superblock says a writer opened the file and never closed it (killed, or still running)."""
    body, _ = _superblock(Path(path))
    return body[11] != 0


#: the superblock's file-consistency flags (HDF5 file format specification, version 3 superblock; H5Fpkg.h):
#: opened for writing, and opened for SWMR writing
WRITE_ACCESS, SWMR_WRITE_ACCESS = 0x01, 0x04


def left_open_without_swmr(path: str | Path) -> bool:
    """True if a writer opened the file for writing and never switched it to SWMR nor closed it: killed between
    its open and its `swmr_mode = True` (no reader, SWMR or not, can open such a file until the flags are
    cleared)."""
    body, _ = _superblock(Path(path))
    return bool(body[11] & WRITE_ACCESS) and not body[11] & SWMR_WRITE_ACCESS


def clear_superblock_flags(path: Path) -> None:
    """Zero the superblock's file-consistency flags and rewrite its checksum (h5clear -s)."""
    body, _ = _superblock(path)
    if body[11] == 0:
        return
    new = body[:11] + b"\0" + body[12:]
    with open(path, "r+b") as fh:
        fh.seek(0)
        fh.write(new + struct.pack("<I", _lookup3(new)))
        fh.flush()
        os.fsync(fh.fileno())
