"""What a campaign records of each lock-in block, and into which run-file columns (docs/hdf5.md).

The runner hands the recorder what a block produced; the recorder owns the mapping to the "qmg-lab/1" groups:

    /lockin   every streamed sample: the fields the LockInBlock declares (LockInBlock.FIELDS), at file time t, and
              pll_locked, the block's LockInBlock.pll_locked (1 locked, 0 not) repeated on each of its samples
    /clsf     one row per completed dither period: the fields of ClsfPeriods
    /table    one row per block: the commanded rate, and the TableReading's measured rate and position
    /chamber  one row per block: the ChamberReading's setpoint and air temperature
    /truth    the twin's truth (scale factor, gyro temperature, applied rate) at exactly the /lockin samples
    clsf_reference (root attribute): the CLSF reference level, so that a resumed run keeps it

Rows of one block are appended together (the caller defers Ctrl-C around `record`), so a file cut short by a
crash holds whole blocks.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from qmg_lab.clsf.estimator import ClsfPeriods
from qmg_lab.instruments import ChamberReading, LockInBlock, TableReading, TruthBlock
from qmg_lab.storage.writer import RunWriter

CLSF_COLUMNS = tuple(f.name for f in dataclasses.fields(ClsfPeriods))
"""/clsf columns: time, eta, sf_change_estimate, gain_correction, rate_output_mean."""


class BlockRecorder:
    """Appends one lock-in block's rows to the run file, group by group."""

    def __init__(self, writer: RunWriter) -> None:
        self.writer = writer
        self._stored_reference: float | None = None

    def record(
        self,
        t: np.ndarray,
        block: LockInBlock,
        periods: ClsfPeriods,
        table: TableReading | None,
        table_command_dps: float,
        chamber: ChamberReading | None,
        truth: TruthBlock | None,
        dt_s: float,
        clsf_reference: float | None = None,
    ) -> None:
        """The block's rows: lock-in samples at file times `t`; CLSF periods; the table and chamber readings
        (None: not read this block) stamped at the block's last sample; the twin's truth aligned with `t`; the
        CLSF reference level rho_0 (root attribute clsf_reference) once it is formed or whenever it changes."""
        locked = np.full(t.shape[0], 1 if block.pll_locked else 0, dtype=np.uint8)  # the block's flag, per sample
        self.writer.append(
            "lockin", time=t, pll_locked=locked, **{f: getattr(block, f) for f in LockInBlock.FIELDS[1:]}
        )
        if len(periods):
            self.writer.append("clsf", **{c: getattr(periods, c) for c in CLSF_COLUMNS})
        t_end = float(t[-1])
        if table is not None:
            self.writer.append_row(
                "table",
                time=t_end,
                rate_command=table_command_dps,
                rate_measured=table.rate_dps,
                position=table.position_deg,
            )
        if chamber is not None:
            self.writer.append_row(
                "chamber", time=t_end, setpoint=chamber.setpoint_c, temperature=chamber.temperature_c
            )
        if truth is not None and len(truth.time):
            self.writer.append("truth", **aligned_truth(truth, t, dt_s))
        if clsf_reference is not None and clsf_reference != self._stored_reference:
            self.writer.set_clsf_reference(clsf_reference)
            self._stored_reference = clsf_reference
        self.writer.maybe_flush()


def aligned_truth(truth: TruthBlock, t: np.ndarray, dt: float) -> dict[str, np.ndarray]:
    """The twin's truth rows of exactly the lock-in samples of a block, at their file times `t`.

    The truth source records every simulated sample (on the world's clock); the lock-in block holds those the
    stream delivered (fewer if samples were lost), on the stream's clock. Both end on the same sample, the last
    of the block (the HF2 twin drops lost samples inside a block, never its last one), so samples are matched by
    their distance from it in sample periods: /truth gets the rows of the delivered samples only, with /lockin's
    time values, and stays aligned sample for sample.
    """
    if len(truth.time) == len(t) and abs((truth.time[-1] - truth.time[0]) - (t[-1] - t[0])) < 0.5 * dt:
        # the same samples (the usual case: every simulated sample delivered): row for row
        return {"time": t, "scale_factor": truth.scale_factor, "temperature": truth.temperature, "rate": truth.rate}
    if len(truth.time) > 1:  # the stream's true sample period (the configured rate may have been rounded)
        dt = float(truth.time[-1] - truth.time[0]) / (len(truth.time) - 1)
    k_truth = np.rint((truth.time[-1] - truth.time) / dt).astype(np.int64)
    k_lock = np.rint((t[-1] - t) / dt).astype(np.int64)
    _, i_truth, i_lock = np.intersect1d(k_truth, k_lock, assume_unique=True, return_indices=True)
    order = np.argsort(i_lock)
    i_truth, i_lock = i_truth[order], i_lock[order]
    return {
        "time": t[i_lock],
        "scale_factor": truth.scale_factor[i_truth],
        "temperature": truth.temperature[i_truth],
        "rate": truth.rate[i_truth],
    }
