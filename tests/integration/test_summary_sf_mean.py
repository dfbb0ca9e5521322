"""The run's summary states the CLSF SF-change estimate as its mean over the last 60 s of run time, not one dither
period's estimate (one period scatters by several hundred ppm). Its value is the mean of the file's own
/clsf/sf_change_estimate rows whose period ended in the last 60 s before the last one."""

from __future__ import annotations

import math
from pathlib import Path

import h5py
import numpy as np

from qmg_lab.clsf.moving_mean import SF_MEAN_WINDOW_S
from tests.support.campaigns import config_text, run_inprocess


def test_summary_sf_change_is_the_last_60_s_mean_of_the_recorded_estimates(tmp_path: Path) -> None:
    done = run_inprocess(tmp_path, config_text())
    assert done.error is None and done.summary.status == "completed"
    with h5py.File(done.path, "r") as h5:
        t = h5["clsf/time"][:]
        sf = h5["clsf/sf_change_estimate"][:]
    keep = np.isfinite(sf) & (t >= t[-1] - SF_MEAN_WINDOW_S)
    assert keep.sum() > 100  # about 7 periods a second over the window
    expected_ppm = math.fsum(sf[keep]) / keep.sum() * 1e6
    # the same numbers summed in another order: a few roundings of the terms' size
    bound = 1e-12 * max(1.0, float(np.abs(sf[keep]).max()) * 1e6)
    assert abs(done.summary.sf_change_mean_ppm - expected_ppm) <= bound
    assert done.summary.sf_change_mean_ppm != sf[-1] * 1e6  # not the last period's own estimate
