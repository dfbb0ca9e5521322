"""Whole chunks for HDF5's shuffle + deflate filters, compressed here by ISA-L instead of inside HDF5.

A chunk of a dataset created with `shuffle=True, compression="gzip"` is stored as

    deflate(shuffle(rows))

* shuffle (HDF5's H5Z_FILTER_SHUFFLE): the n elements of s bytes are rewritten byte plane by byte plane, all the
  first bytes, then all the second bytes, ..., so that the slowly varying high bytes of neighbouring values sit
  together: for a C-contiguous (n,) array, `rows.view(uint8).reshape(n, s).T` flattened;
* deflate (H5Z_FILTER_DEFLATE): a zlib stream (RFC 1950: 2-byte header, RFC 1951 deflate data, Adler-32), which
  HDF5 inflates with zlib whatever produced it.

An edge chunk is always stored at its full size; HDF5 fills the rows past the dataset's extent with the fill
value (0), and so does `shuffled_deflate`. A chunk built here and written with `write_direct_chunk` (filter mask
0: every filter applied) is therefore read back by any HDF5 reader — plain h5py included — exactly as if HDF5 had
compressed it, and HDF5's own pipeline can later extend it (a resumed run appending into it).

Why: ISA-L's deflate (the `isal` package, Intel's Intelligent Storage Acceleration Library) at its level 1
compresses the twins' noise-dominated float64 columns about 9x faster than zlib's level 1 for ~6 % more bytes
(benchmarks/storage_speed.py), and compression was the writer thread's whole cost at full logging.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from isal import isal_zlib

#: ISA-L compression level of every directly written chunk (0-3; 1 is within ~6 % of zlib's level 1 on the twins'
#: columns, 2 and 3 gain under 1 % for 1-4x the time)
ISAL_LEVEL = 1


def shuffled_deflate(rows: np.ndarray | Sequence[np.ndarray], chunk_rows: int, level: int = ISAL_LEVEL) -> bytes:
    """One stored chunk of a 1-D shuffle + deflate dataset: `rows` (at most `chunk_rows`; one array, or the
    consecutive pieces the chunk's rows arrived in) padded with zeros to `chunk_rows`, byte-shuffled, deflated into
    a zlib stream. Pieces are joined inside the shuffle (each piece's bytes go straight to their planes): no
    joined copy of the rows is made."""
    pieces = [rows] if isinstance(rows, np.ndarray) else list(rows)
    one_column = bool(pieces) and all(p.ndim == 1 and p.dtype == pieces[0].dtype for p in pieces)
    n = sum(p.shape[0] for p in pieces) if one_column else 0
    if not 0 < n <= chunk_rows:
        shapes = [p.shape for p in pieces]
        raise ValueError(f"a chunk holds 1 to {chunk_rows} rows of a 1-D column of one dtype, got pieces {shapes}")
    size = pieces[0].dtype.itemsize
    planes = np.empty((size, chunk_rows), dtype=np.uint8)  # plane k: byte k of every element
    planes[:, n:] = 0  # the edge chunk's padding: float zeros are zero bytes
    start = 0
    for p in pieces:
        m = p.shape[0]
        planes[:, start : start + m] = np.ascontiguousarray(p).view(np.uint8).reshape(m, size).T
        start += m
    return isal_zlib.compress(planes, level)
