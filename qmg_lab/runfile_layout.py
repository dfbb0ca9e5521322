"""The "qmg-lab/1" run-file layout (DESIGN.md section 5): groups, columns, units, descriptions, dtypes, chunking.

Shared by the writer (qmg_lab/storage.py) and the reader (qmg_lab/runfile_reader.py); docs/hdf5.md explains it.
"""

from __future__ import annotations

from typing import Any

import numpy as np

FORMAT = "qmg-lab/1"

LOCKIN_UNITS = {"time": "s", "x_sense": "V", "y_sense": "V", "rate_output": "V", "drive_amplitude": "V",
                "drive_frequency": "Hz", "dither": "V"}
CLSF_UNITS = {"time": "s", "eta": "1", "sf_change_estimate": "1", "gain_correction": "1", "rate_output_mean": "V"}
TABLE_UNITS = {"time": "s", "rate_command": "deg/s", "rate_measured": "deg/s", "position": "deg"}
CHAMBER_UNITS = {"time": "s", "setpoint": "degC", "temperature": "degC"}
TRUTH_UNITS = {"time": "s", "scale_factor": "V/(deg/s)", "temperature": "degC", "rate": "deg/s"}
STEPS_UNITS = {"index": "1", "kind": "text", "t_start": "s", "t_end": "s", "table_rate": "deg/s",
               "chamber_setpoint": "degC", "status": "text"}

#: group name -> column name -> units (the order is the column order in the file)
GROUP_UNITS: dict[str, dict[str, str]] = {"lockin": LOCKIN_UNITS, "clsf": CLSF_UNITS, "table": TABLE_UNITS,
                                          "chamber": CHAMBER_UNITS, "truth": TRUTH_UNITS}

DESCRIPTIONS: dict[str, str] = {
    "lockin/time": "sample time, s since the root attribute t0_unix",
    "lockin/x_sense": "sense demodulator in-phase component c_y (X), Vrms",
    "lockin/y_sense": "sense demodulator quadrature component s_y (Y), Vrms",
    "lockin/rate_output": "FTR rebalance command f_y (rate PID output, recorded on an AuxIn), V",
    "lockin/drive_amplitude": "drive pickoff amplitude R of the drive demodulator, Vrms",
    "lockin/drive_frequency": "PLL oscillator frequency, Hz",
    "lockin/dither": "the DS345 dither (virtual rate) as recorded on an AuxIn, V",
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

KIND_BYTES = 48
STATUS_BYTES = 16
STEPS_DTYPES: dict[str, Any] = {"index": np.int64, "kind": f"S{KIND_BYTES}", "t_start": np.float64,
                                "t_end": np.float64, "table_rate": np.float64, "chamber_setpoint": np.float64,
                                "status": f"S{STATUS_BYTES}"}
#: rows per chunk. A flush rewrites the last, partial chunk of every dataset; a compressed chunk that grew is
#: written elsewhere and its old space is not reused, so small chunks keep that waste small (benchmarks/
#: storage_speed.py: 512 rows = 0.37 s at 1400 Sa/s). Only the fast groups are compressed; the slow ones (a few
#: rows per second, < 1 MB per hour) are stored plain, where a partial chunk is rewritten in place.
CHUNK_ROWS = {"lockin": 512, "clsf": 256, "table": 256, "chamber": 256, "truth": 512, "steps": 64}
COMPRESSED_GROUPS = ("lockin", "truth")
COMPRESSIONS = ("none", "gzip", "lzf")
GZIP_LEVEL = 1
MODES = ("sim", "hardware")
STATUSES = ("running", "completed", "aborted")


class StorageError(Exception):
    """A run file that cannot be created, read or resumed; the message names the file and what is wrong."""


def _text(value: Any) -> str:
    return value.decode("utf-8", "replace") if isinstance(value, bytes) else str(value)
