"""The run-file layout, format "qmg-lab/2" ("qmg-lab/1" files read too; docs/hdf5.md): groups, columns, units,
descriptions, dtypes, chunking.

Shared by the writer (qmg_lab/storage/writer.py) and the reader (qmg_lab/storage/reader.py); docs/hdf5.md explains it.
"""

from __future__ import annotations

from typing import Any

import numpy as np

#: the run-file format new files are written in (root attribute `format`; docs/hdf5.md, "Format versions")
FORMAT = "qmg-lab/2"
#: the formats every reader accepts (qmg_lab/storage/runfile.py check_format); /1 files lack what /2 added
READ_FORMATS = ("qmg-lab/1", "qmg-lab/2")
#: columns a format added: a file of an earlier format lacks them, and its readers do not ask for them
#: (docs/hdf5.md, "Format versions"; the campaign attributes and salvage attributes /2 added are optional anyway)
COLUMNS_ADDED: dict[str, dict[str, tuple[str, ...]]] = {"qmg-lab/2": {"lockin": ("table_encoder", "pll_locked")}}


def group_columns(group: str, fmt: str) -> list[str]:
    """The columns of a data group or /steps that a file of format `fmt` has (GROUP_UNITS, STEPS_UNITS less the
    columns later formats added)."""
    cols = list(GROUP_UNITS.get(group, STEPS_UNITS))
    later = READ_FORMATS[READ_FORMATS.index(fmt) + 1 :] if fmt in READ_FORMATS else ()
    added = {c for f in later for c in COLUMNS_ADDED.get(f, {}).get(group, ())}
    return [c for c in cols if c not in added]


LOCKIN_UNITS = {
    "time": "s",
    "x_sense": "V",
    "y_sense": "V",
    "rate_output": "V",
    "drive_amplitude": "V",
    "drive_frequency": "Hz",
    "dither": "V",
    "table_encoder": "1",
    "pll_locked": "1",
}
CLSF_UNITS = {"time": "s", "eta": "1", "sf_change_estimate": "1", "gain_correction": "1", "rate_output_mean": "V"}
TABLE_UNITS = {"time": "s", "rate_command": "deg/s", "rate_measured": "deg/s", "position": "deg"}
CHAMBER_UNITS = {"time": "s", "setpoint": "degC", "temperature": "degC"}
TRUTH_UNITS = {"time": "s", "scale_factor": "V/(deg/s)", "temperature": "degC", "rate": "deg/s"}
STEPS_UNITS = {
    "index": "1",
    "kind": "text",
    "t_start": "s",
    "t_end": "s",
    "table_rate": "deg/s",
    "chamber_setpoint": "degC",
    "status": "text",
}

#: group name -> column name -> units (the order is the column order in the file)
GROUP_UNITS: dict[str, dict[str, str]] = {
    "lockin": LOCKIN_UNITS,
    "clsf": CLSF_UNITS,
    "table": TABLE_UNITS,
    "chamber": CHAMBER_UNITS,
    "truth": TRUTH_UNITS,
}

DESCRIPTIONS: dict[str, str] = {
    "lockin/time": "sample time, s since the root attribute t0_unix",
    "lockin/x_sense": "sense demodulator in-phase component c_y (X), Vrms",
    "lockin/y_sense": "sense demodulator quadrature component s_y (Y), Vrms",
    "lockin/rate_output": "FTR rebalance command f_y (rate PID output, recorded on an AuxIn), V",
    "lockin/drive_amplitude": "drive pickoff amplitude R of the drive demodulator, Vrms",
    "lockin/drive_frequency": "PLL oscillator frequency, Hz",
    "lockin/dither": "the DS345 dither (virtual rate) as recorded on an AuxIn, V",
    "lockin/table_encoder": "HF2 DIO input word of the sample: the rate table encoder's A/B bits as cabled "
    "([table] encoder_a_dio_bit, encoder_b_dio_bit), an integer",
    "lockin/pll_locked": "1 if the drive PLL stayed locked through the sample's block (the driver's reading of "
    "the HF2's PLL lock), else 0; absent from files written before the column existed",
    "clsf/time": "end of the dither period the row describes, s since t0_unix",
    "clsf/eta": "CLSF demodulation level of the period relative to its reference: rho/rho_0 - 1 (forcer-path gain "
    "change seen by the dither)",
    "clsf/sf_change_estimate": "CLSF estimate of the scale-factor change SF/SF0 - 1 = 1/(1 + eta) - 1",
    "clsf/gain_correction": "CLSF gain correction g_c in force during the period (1.0 = none; correct mode only)",
    "clsf/rate_output_mean": "rate output averaged over the whole dither period (the dither cancels), V",
    "table/time": "reading time, s since t0_unix",
    "table/rate_command": "commanded table rate, deg/s",
    "table/rate_measured": "table rate reported by the controller, deg/s",
    "table/position": "table position, deg",
    "chamber/time": "reading time, s since t0_unix",
    "chamber/setpoint": "chamber controller setpoint, degC",
    "chamber/temperature": "chamber air temperature, degC",
    "truth/time": "sample time, s since t0_unix (twins only)",
    "truth/scale_factor": "true FTR scale factor of the simulated gyro, V per deg/s",
    "truth/temperature": "true gyro temperature, degC",
    "truth/rate": "true input rate (table rate seen by the gyro), deg/s",
    "steps/index": "step number in the plan, from 0",
    "steps/kind": "step kind: lock, dither, soak, rate, hold, sine:<f>Hz, level, return",
    "steps/t_start": "step start, s since t0_unix",
    "steps/t_end": "step end, s since t0_unix",
    "steps/table_rate": "table rate of the step (sine steps: amplitude), deg/s",
    "steps/chamber_setpoint": "chamber setpoint during the step, degC",
    "steps/status": "completed | aborted | started | skipped; only completed rows are checkpoints",
}

#: columns not stored as float64 (every other group column is float64 with NaN as its fill value)
COLUMN_DTYPES: dict[str, Any] = {"lockin/pll_locked": np.uint8}
#: columns that files written before they existed lack: readers and a resumed writer do without them
OPTIONAL_COLUMNS: dict[str, tuple[str, ...]] = {"lockin": ("table_encoder", "pll_locked")}


def column_dtype(group: str, column: str) -> Any:
    """The stored dtype of /group/column (float64 unless COLUMN_DTYPES says otherwise)."""
    return COLUMN_DTYPES.get(f"{group}/{column}", np.float64)


#: who ran a campaign, on which device and why: root attributes of every new file (empty when not given; files
#: written before they existed lack them, and read as empty). operator, device_serial, notes: the configuration's
#: [campaign] keys; run_note: `qmg-lab run --note`.
RUN_CONTEXT_ATTRS = ("operator", "device_serial", "notes", "run_note")


KIND_BYTES = 48
STATUS_BYTES = 16
STEPS_DTYPES: dict[str, Any] = {
    "index": np.int64,
    "kind": f"S{KIND_BYTES}",
    "t_start": np.float64,
    "t_end": np.float64,
    "table_rate": np.float64,
    "chamber_setpoint": np.float64,
    "status": f"S{STATUS_BYTES}",
}
#: rows per chunk, chosen for the write pattern and for readers who slice hours of data.
#: Under SWMR, HDF5 never reuses the space of a compressed chunk that is rewritten larger, so every flush that
#: ends inside a compressed chunk leaves one dead copy of that partial chunk behind. A writer faster than real
#: time (the twins: one flush carries minutes of data) writes whole chunks and can afford big ones: 16384 rows
#: (11.7 s at 1400 Sa/s, 128 KiB raw) keep an hour of one column to ~310 chunks for readers. A real-time writer
#: (hardware: a flush every flush_interval_s carries ~1400 rows) uses 2048 rows, about one flush, so the dead
#: copies stay small (benchmarks/storage_speed.py). Slow groups (a few rows per second) are never compressed:
#: their partial chunk is rewritten in place.
CHUNK_ROWS = {"lockin": 16384, "truth": 16384, "clsf": 1024, "table": 1024, "chamber": 1024, "steps": 64}
CHUNK_ROWS_REALTIME = {"lockin": 2048, "truth": 2048, "clsf": 256, "table": 256, "chamber": 256, "steps": 64}
#: columns stored with shuffle + the file's compression. Twins (a flush carries minutes of data, so chunks are
#: written whole): every /lockin and /truth column. Shuffle + deflate level 1 takes the three noise-dominated
#: lock-in columns (x_sense, y_sense, drive_amplitude) to 70-87 % and the rest to 3-54 %; the compression runs on
#: the writer thread (qmg_lab/storage/background.py), beside the campaign, chunk by chunk by ISA-L
#: (qmg_lab/storage/deflate.py). A real-time writer (hardware: a flush every second ends inside a chunk)
#: compresses only the columns that compress well: for the noisy ones the dead copies of their partial chunks
#: (see CHUNK_ROWS) outweigh what the filter saves.
COMPRESSED_COLUMNS = {
    "lockin": tuple(LOCKIN_UNITS),  # every /lockin column
    "truth": ("time", "scale_factor", "temperature", "rate"),
}
COMPRESSED_COLUMNS_REALTIME = {
    "lockin": ("time", "drive_frequency", "dither", "table_encoder", "pll_locked"),
    "truth": ("time", "scale_factor", "temperature", "rate"),
}
COMPRESSED_GROUPS = tuple(COMPRESSED_COLUMNS)


def whole_chunk_layout(h5: Any) -> bool:
    """The twins' layout (every /lockin column compressed): /lockin and /truth are written in whole chunks only,
    so a file cut by a kill ends on a chunk boundary, usually inside a lock-in block (docs/hdf5.md)."""
    return "lockin" in h5 and all(h5["lockin"][c].compression is not None for c in h5["lockin"])


COMPRESSIONS = ("none", "gzip", "lzf")
GZIP_LEVEL = 1
#: columns whose gzip level differs from GZIP_LEVEL: the time axes (a regular grid) shrink from 7.7 % to 5.5 % of
#: their raw size at level 6 for ~4 ns per byte more, where the noisy columns gain under 1 % for 2-10x the cost
GZIP_LEVELS = {"time": 6}
MODES = ("sim", "hardware")
STATUSES = ("running", "completed", "aborted")


#: what h5py raises for bytes that do not decode (a chunk, a B-tree node, an object header)
H5_ERRORS = (OSError, RuntimeError, KeyError, ValueError)


class StorageError(Exception):
    """A run file that cannot be created, read or resumed; the message names the file and what is wrong."""


class DamagedFileError(StorageError):
    """A run file whose bytes are damaged (cut short, a chunk or metadata that does not decode): what still reads
    can be listed and copied (qmg_lab/storage/salvage.py)."""


def _text(value: Any) -> str:
    return value.decode("utf-8", "replace") if isinstance(value, bytes) else str(value)
