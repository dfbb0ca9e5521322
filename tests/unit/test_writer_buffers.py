"""The run writer's buffers (qmg_lab/storage/writer.py): rows appended one by one, blocks handed over as pieces,
and the checks on every append, against the rows the file must end up holding."""

from __future__ import annotations

from pathlib import Path

import h5py
import numpy as np
import pytest

from qmg_lab.storage.writer import RunWriter, StorageError, _append_pieces, read_run

FS = 1800.0


def _writer(path: Path, flush_interval_s: float = 1.0) -> RunWriter:
    return RunWriter.create(
        path,
        config_text="",
        config_sha256="0" * 64,
        mode="sim",
        software_version="test",
        t0_unix=0.0,
        truth=False,
        flush_interval_s=flush_interval_s,
    )


def _lockin(k: int, n: int) -> dict[str, np.ndarray]:
    """Block k of n samples, every column a distinct known function of the sample index."""
    i = k * n + np.arange(n)
    return {
        "time": i / FS,
        "x_sense": np.sin(0.01 * i),
        "y_sense": np.cos(0.02 * i),
        "rate_output": 0.3 + 1e-6 * i,
        "drive_amplitude": 0.5 + 1e-9 * i * i,
        "drive_frequency": 2200.0 + 1e-3 * np.sqrt(i),
        "dither": np.sign(np.sin(2 * np.pi * 7 * i / FS)),
        "table_encoder": np.floor(i / 9) % 4,
        "pll_locked": (i % 5 != 0).astype(np.uint8),
    }


def test_rows_appended_one_by_one_land_in_order_between_blocks(tmp_path: Path) -> None:
    """append_row gives the same rows as append with one-element columns, in the order of the calls, whether
    rows and blocks alternate or rows alone are flushed."""
    path = tmp_path / "run.h5"
    w = _writer(path)
    w.append_row("table", time=0.5, rate_command=5.0, rate_measured=4.999, position=1.0)
    w.append_row("table", time=1.0, rate_command=5.0, rate_measured=5.001, position=3.5)
    w.append("table", time=[1.5, 2.0], rate_command=[-5.0, -5.0], rate_measured=[-4.9, -5.0], position=[6.0, 8.5])
    w.append_row("table", time=2.0, rate_command=0.0, rate_measured=np.float64(0.25), position=359.75)
    w.append_row("chamber", time=2.0, setpoint=25.0, temperature=24.98)
    w.flush()
    w.append_row("chamber", time=4.0, setpoint=25.5, temperature=25.01)
    w.close()
    g = read_run(path).groups
    assert g["table"]["time"].tolist() == [0.5, 1.0, 1.5, 2.0, 2.0]
    assert g["table"]["rate_command"].tolist() == [5.0, 5.0, -5.0, -5.0, 0.0]
    assert g["table"]["rate_measured"].tolist() == [4.999, 5.001, -4.9, -5.0, 0.25]
    assert g["table"]["position"].tolist() == [1.0, 3.5, 6.0, 8.5, 359.75]
    assert g["chamber"]["setpoint"].tolist() == [25.0, 25.5]
    assert g["chamber"]["temperature"].tolist() == [24.98, 25.01]


def test_a_bad_row_is_refused_with_the_rule_it_breaks(tmp_path: Path) -> None:
    w = _writer(tmp_path / "run.h5")
    w.append_row("chamber", time=10.0, setpoint=25.0, temperature=25.0)
    with pytest.raises(StorageError, match=r"must not decrease \(last stored 10.000000 s, this block starts at 9.5"):
        w.append_row("chamber", time=9.5, setpoint=25.0, temperature=25.0)
    with pytest.raises(StorageError, match="NaN or infinite"):
        w.append_row("chamber", time=float("nan"), setpoint=25.0, temperature=25.0)
    with pytest.raises(StorageError, match=r"missing \['temperature'\]"):
        w.append_row("chamber", time=11.0, setpoint=25.0)
    with pytest.raises(StorageError, match="a number for every column"):
        w.append_row("chamber", **{"time": 11.0, "setpoint": "warm", "temperature": 25.0})
    with pytest.raises(StorageError, match="unknown group 'foo'"):
        w.append_row("foo", time=11.0)
    with pytest.raises(StorageError, match="no /truth group"):
        w.append_row("truth", time=11.0, scale_factor=0.06, temperature=25.0, rate=0.0)
    w.append_row("chamber", time=10.0, setpoint=25.0, temperature=float("nan"))  # only time must be finite
    w.close()


@pytest.mark.parametrize(
    ("time", "message"),
    [
        ([0.0, np.nan, 2.0], "NaN or infinite"),  # a NaN inside finite ends
        ([0.0, np.inf, np.inf], "NaN or infinite"),
        ([-np.inf, 0.0, 1.0], "NaN or infinite"),
        ([0.0, 2.0, 1.0, 3.0], "must not decrease"),  # a step down inside the block
        ([0.5, 0.6], "must not decrease"),  # starts before the last stored time (1.0)
        ([1.0, 1.0, 1.0], None),  # equal times are allowed, also equal to the last stored one
    ],
)
def test_every_value_of_a_time_column_is_checked(tmp_path: Path, time: list[float], message: str | None) -> None:
    w = _writer(tmp_path / "run.h5")
    w.append("clsf", time=[1.0], eta=[0.0], sf_change_estimate=[0.0], gain_correction=[1.0], rate_output_mean=[0.3])
    n = len(time)
    cols = {"time": time, "eta": [0.0] * n, "sf_change_estimate": [0.0] * n, "gain_correction": [1.0] * n}
    if message is None:
        w.append("clsf", **cols, rate_output_mean=[0.3] * n)
    else:
        with pytest.raises(StorageError, match=message):
            w.append("clsf", **cols, rate_output_mean=[0.3] * n)
    w.close()


def test_blocks_handed_over_in_pieces_read_back_exactly(tmp_path: Path) -> None:
    """The twins' layout writes /lockin in whole compressed chunks built from the appended blocks (a chunk spans
    several blocks, a block two chunks) and keeps the partial chunk until close: every row reads back as
    appended, with plain h5py."""
    path = tmp_path / "run.h5"
    w = _writer(path, flush_interval_s=1e-9)
    chunk = w._h5["lockin/time"].chunks[0]
    n = 3600  # not a divisor of the chunk rows
    blocks = [_lockin(k, n) for k in range(2 * chunk // n + 3)]
    for b in blocks:
        w.append("lockin", **b)
        w.maybe_flush()  # hands over the whole chunks at every block
    w.drain()
    assert w._h5["lockin/time"].shape[0] % chunk == 0  # whole chunks only until close
    w.close()
    with h5py.File(path, "r") as h5:
        for c in blocks[0]:
            np.testing.assert_array_equal(h5["lockin"][c][:], np.concatenate([b[c] for b in blocks]))


def test_pieces_fill_a_stored_partial_chunk_then_whole_chunks(tmp_path: Path) -> None:
    """_append_pieces after a resume: the first rows fill the stored partial chunk through HDF5's filters, the rest
    are whole chunks from pieces that do not start or end on chunk boundaries."""
    chunk = 64
    rng = np.random.default_rng(4)
    first = rng.standard_normal(chunk + 10)
    pieces = [rng.standard_normal(m) for m in (5, 100, 1, 70)]
    path = tmp_path / "p.h5"
    with h5py.File(path, "w") as h5:
        ds = h5.create_dataset(
            "x", shape=(0,), maxshape=(None,), dtype=np.float64, chunks=(chunk,), shuffle=True, compression="gzip"
        )
        _append_pieces(ds, [first], chunk)
        _append_pieces(ds, pieces, chunk)
        _append_pieces(ds, [], chunk)  # nothing to add: nothing changes
    with h5py.File(path, "r") as h5:
        np.testing.assert_array_equal(h5["x"][:], np.concatenate([first, *pieces]))
