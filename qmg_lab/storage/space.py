"""The disk space a run still needs, and whether its disk has it (checked before a run starts and after every step).

    needed = MARGIN * bytes_per_s * run_time_left_s + RESERVE_BYTES

bytes_per_s is what the writer itself wrote per second of run time (the run file's size over the run time it
holds) once a run holds MEASURE_AFTER_S of run time: measured, so it includes the compression the file actually
reached, HDF5's own metadata and the chunk copies a flush leaves (docs/hdf5.md). Before that it is the layout's
raw rate, `raw_bytes_per_s` (8 bytes per float64 value, no compression: the twins' layout compresses to
about a half, a hardware run's noise may not compress at all, so only the raw rate is sure to be enough). Before
MEASURE_AFTER_S the file's size is mostly its layout and its first allocated chunks, not a rate.

MARGIN covers what a run writes beyond its plan's run time: the resumed run's new lock wait and dither start (the
loops are closed again in a new process), the partial chunks rewritten after a resume, the events and snapshots.
RESERVE_BYTES covers HDF5's allocation ahead of a flush (a whole chunk of every column at once) and the file's
last close. The figure asked of the operator is this `needed`, the same formula the checks use: once that much is
free, the resume's own check passes.
"""

from __future__ import annotations

import math
import re
import shutil
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from qmg_lab.storage.layout import GROUP_UNITS, column_dtype

MARGIN = 1.5
MEASURE_AFTER_S = 60.0
RESERVE_BYTES = 4 << 20


def raw_bytes_per_s(rows_per_s: Mapping[str, float]) -> float:
    """Bytes per second of run time of the groups' columns stored without compression: rows per second of each
    group (GROUP_UNITS names; a group left out writes nothing) times the bytes of one row: each column's stored
    dtype (8 bytes for float64, layout.column_dtype)."""
    return sum(
        rate * sum(np.dtype(column_dtype(g, c)).itemsize for c in GROUP_UNITS[g]) for g, rate in rows_per_s.items()
    )


def measured_bytes_per_s(path: Path, run_time_s: float) -> float | None:
    """The run file's size over the run time it holds, bytes per s; None before it holds MEASURE_AFTER_S."""
    if run_time_s < MEASURE_AFTER_S:
        return None
    try:
        return Path(path).stat().st_size / run_time_s
    except OSError:
        return None


def free_bytes(path: Path) -> int | None:
    """Free bytes on the disk that holds `path` (its folder if it does not exist yet); None if it cannot be asked."""
    p = Path(path)
    folder = p if p.is_dir() else p.parent
    try:
        return shutil.disk_usage(folder).free
    except OSError:
        return None


@dataclass(frozen=True)
class SpaceNeed:
    """The space a run still needs on its disk and what is free there, bytes."""

    needed: int
    free: int | None
    bytes_per_s: float
    left_s: float
    measured: bool  # bytes_per_s measured from the file (else the layout's raw rate)

    @property
    def enough(self) -> bool:
        return self.free is None or self.free >= self.needed

    def words(self) -> str:
        """The figure for the operator: what the run needs, at which rate, and what is free."""
        how = "as written so far" if self.measured else "uncompressed, the most it can write"
        # the figure asked is rounded up and what is free down: freeing what it says is always enough
        free = "unknown" if self.free is None else f"{math.floor(self.free / 1e5) / 10:.1f} MB"
        asked = math.ceil(self.needed / 1e5) / 10
        return (
            f"The run needs about {asked:.1f} MB more on its disk for its remaining {self.left_s:.0f} s of run time "
            f"({self.bytes_per_s * 3600 / 1e6:.0f} MB per hour of run time, {how}, x{MARGIN:g} "
            f"+ {RESERVE_BYTES / 1e6:.1f} MB); {free} are free"
        )


#: `SpaceNeed.words()` in a message (from "The run needs about" to "are free")
WORDS_PATTERN = re.compile(r"The run needs about [0-9.]+ MB more .*? (?:MB|unknown) are free", re.DOTALL)


def space_need(path: Path, *, bytes_per_s: float, left_s: float, measured: bool) -> SpaceNeed:
    """What the run at `path` still needs (the module docstring's formula) and what its disk has free."""
    needed = int(MARGIN * bytes_per_s * max(left_s, 0.0)) + RESERVE_BYTES
    return SpaceNeed(needed, free_bytes(path), bytes_per_s, max(left_s, 0.0), measured)
