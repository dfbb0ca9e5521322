"""Chunks compressed outside HDF5 (qmg_lab/storage/deflate.py) against HDF5's own shuffle + deflate filters."""

from __future__ import annotations

import zlib
from pathlib import Path

import h5py
import numpy as np
import pytest

from qmg_lab.storage.deflate import shuffled_deflate
from qmg_lab.storage.writer import _append_pieces

CHUNK = 64


def _column(path: Path, name: str = "x") -> h5py.Dataset:
    h5 = h5py.File(path, "a")
    return h5.create_dataset(
        name, shape=(0,), maxshape=(None,), dtype=np.float64, chunks=(CHUNK,), shuffle=True, compression="gzip"
    )


def test_a_chunk_inflates_to_the_byte_planes_hdf5_itself_stores(tmp_path: Path) -> None:
    """The shuffle filter's definition: byte k of every element, k = 0..7, one plane after the other."""
    rows = np.random.default_rng(1).standard_normal(CHUNK)
    ds = _column(tmp_path / "a.h5")
    ds.resize((CHUNK,))
    ds[:] = rows  # compressed by HDF5's own pipeline
    _, hdf5_chunk = ds.id.read_direct_chunk((0,))
    ds.file.close()
    planes = np.frombuffer(rows.tobytes(), np.uint8).reshape(CHUNK, 8).T.tobytes()
    assert zlib.decompress(hdf5_chunk) == planes
    assert zlib.decompress(shuffled_deflate(rows, CHUNK)) == planes


def test_direct_chunks_read_back_exactly_by_plain_h5py_including_the_edge_chunk(tmp_path: Path) -> None:
    data = np.cumsum(np.random.default_rng(2).standard_normal(3 * CHUNK + 17))
    path = tmp_path / "b.h5"
    ds = _column(path)
    _append_pieces(ds, [data], CHUNK)
    ds.file.close()
    with h5py.File(path, "r") as h5:
        assert h5["x"].shape == data.shape
        np.testing.assert_array_equal(h5["x"][:], data)
        assert h5["x"].id.get_num_chunks() == 4


def test_an_append_into_a_stored_partial_chunk_goes_through_hdf5_then_whole_chunks_again(tmp_path: Path) -> None:
    """A resumed run appends after an edge chunk that close() wrote padded: its rows fill that chunk through
    HDF5's filters (which inflate the padded chunk), the rest are direct chunks."""
    rng = np.random.default_rng(3)
    first, second = rng.standard_normal(CHUNK + 10), rng.standard_normal(2 * CHUNK + 5)
    path = tmp_path / "c.h5"
    ds = _column(path)
    _append_pieces(ds, [first], CHUNK)
    _append_pieces(ds, [second], CHUNK)
    ds.file.close()
    with h5py.File(path, "r") as h5:
        np.testing.assert_array_equal(h5["x"][:], np.concatenate([first, second]))


def test_a_chunk_larger_than_the_chunk_size_is_refused() -> None:
    with pytest.raises(ValueError, match="1 to 64 rows"):
        shuffled_deflate(np.zeros(CHUNK + 1), CHUNK)


def test_a_chunk_from_pieces_is_the_chunk_of_the_joined_rows() -> None:
    """Pieces (a strided one among them) are joined inside the shuffle: the same planes, the same zlib stream."""
    rng = np.random.default_rng(5)
    strided = rng.standard_normal(40)[::2]
    pieces = [rng.standard_normal(7), strided, rng.standard_normal(1), rng.standard_normal(30)]
    joined = np.concatenate(pieces)
    planes = np.frombuffer(joined.tobytes() + bytes(8 * (CHUNK - joined.shape[0])), np.uint8).reshape(CHUNK, 8).T
    assert zlib.decompress(shuffled_deflate(pieces, CHUNK)) == planes.tobytes()
    assert shuffled_deflate(pieces, CHUNK) == shuffled_deflate(joined, CHUNK)


def test_pieces_of_another_shape_or_dtype_are_refused() -> None:
    with pytest.raises(ValueError, match="one dtype"):
        shuffled_deflate([np.zeros(3), np.zeros(3, dtype=np.float32)], CHUNK)
    with pytest.raises(ValueError, match="1 to 64 rows"):
        shuffled_deflate([np.zeros((2, 2))], CHUNK)
    with pytest.raises(ValueError, match="1 to 64 rows"):
        shuffled_deflate([], CHUNK)
