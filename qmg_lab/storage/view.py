"""A run file as HDF5 would see it after `h5clear -s` and a pad to its recorded end, without writing anything.

HDF5 refuses a plain (non-SWMR) open of a file whose superblock still carries a writer's consistency flags (a
writer that was killed, or is still writing), and any open of a file shorter than the end-of-file address its
superblock records (qmg_lab/storage/superblock.py). A SWMR open accepts the flags but retries every metadata
read that fails its checksum, for minutes on a damaged file; a plain open fails such a read at once.

`ClearedView` is a read-only file object (what h5py opens through its "fileobj" driver): the file's own bytes,
with the superblock's consistency-flag byte read as 0 and its lookup3 checksum recomputed (the superblock is
versions 2/3, what `libver="latest"` writes: qmg_lab/storage/h5clear.py), and zero bytes from the file's end
up to the recorded end of file (metadata that lay in the lost tail then reads as damaged, never as data). HDF5
then opens it without SWMR: every read is bounded by the bytes on disk.
"""

from __future__ import annotations

import io
import os
import struct
from pathlib import Path

from qmg_lab.storage.h5clear import superblock_bytes, superblock_checksum
from qmg_lab.storage.superblock import read_superblock


class ClearedView(io.RawIOBase):
    """Read-only bytes of `path`: superblock flags cleared (checksum rewritten), zero-padded to its recorded end
    of file (module docstring). Nothing is ever written to the file."""

    def __init__(self, path: str | Path) -> None:
        super().__init__()
        self.path = Path(path)
        sb = read_superblock(self.path)
        self._real = os.path.getsize(self.path)
        self.size = max(self._real, sb.eof_address or 0)
        self._patch = b""
        self._patch_at = sb.offset
        if sb.version in (2, 3) and sb.offset == 0:
            body = bytearray(superblock_bytes(self.path))
            body[11] = 0
            self._patch = bytes(body) + struct.pack("<I", superblock_checksum(bytes(body)))
        self._fh = open(self.path, "rb")  # noqa: SIM115 - closed by close(), the view's whole life
        self._pos = 0

    def readable(self) -> bool:
        return True

    def seekable(self) -> bool:
        return True

    def seek(self, offset: int, whence: int = io.SEEK_SET) -> int:
        base = {io.SEEK_SET: 0, io.SEEK_CUR: self._pos, io.SEEK_END: self.size}[whence]
        self._pos = max(0, base + offset)
        return self._pos

    def tell(self) -> int:
        return self._pos

    def readinto(self, buffer: bytearray | memoryview) -> int:  # type: ignore[override]
        out = memoryview(buffer).cast("B")
        n = min(len(out), max(0, self.size - self._pos))
        got = 0
        if self._pos < self._real:
            self._fh.seek(self._pos)
            got = self._fh.readinto(out[: min(n, self._real - self._pos)]) or 0
        out[got:n] = bytes(n - got)  # past the file's real end: zeros up to the recorded end
        lo = max(self._pos, self._patch_at)
        hi = min(self._pos + n, self._patch_at + len(self._patch))
        if lo < hi:
            out[lo - self._pos : hi - self._pos] = self._patch[lo - self._patch_at : hi - self._patch_at]
        self._pos += n
        return n

    def close(self) -> None:
        if not self.closed:
            self._fh.close()
        super().close()
