"""The recorder: each block's rows land in their groups and columns; /truth keeps only the delivered samples."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from qmg_lab.campaign.recorder import BlockRecorder
from qmg_lab.clsf.estimator import ClsfPeriods
from qmg_lab.instruments import ChamberReading, LockInBlock, TableReading, TruthBlock
from qmg_lab.storage.writer import RunWriter, read_run

FS = 1800.0


def _writer(path: Path) -> RunWriter:
    return RunWriter.create(
        path, config_text="", config_sha256="0" * 64, mode="sim", software_version="test", t0_unix=0.0, truth=True
    )


def test_a_block_with_a_lost_sample_is_recorded_group_by_group(tmp_path: Path) -> None:
    n = 10
    k_all = np.arange(n)
    delivered = np.delete(k_all, 4)  # the stream lost the 5th sample; the truth source has all ten
    t = 100.0 + delivered / FS
    block = LockInBlock(*(t + j for j in range(len(LockInBlock.FIELDS))), samples_lost=1)
    periods = ClsfPeriods(*(np.array([100.001, 100.002]) * (j + 1) for j in range(5)))
    truth_t = 50.0 + k_all / FS  # on the world's clock: another origin, same sample period
    truth = TruthBlock(truth_t, 0.06 + k_all * 1e-6, 25.0 + k_all * 0.01, 5.0 + k_all)
    path = tmp_path / "run.h5"
    w = _writer(path)
    rec = BlockRecorder(w)
    rec.record(t, block, periods, TableReading(4.99, 12.5, 0), 5.0, ChamberReading(26.5, 27.0), truth, 1 / FS, 0.25)
    w.close()
    run = read_run(path)
    g = run.groups
    np.testing.assert_array_equal(g["lockin"]["time"], t)
    for j, f in enumerate(LockInBlock.FIELDS[1:], start=1):
        np.testing.assert_array_equal(g["lockin"][f], t + j)
    np.testing.assert_array_equal(g["clsf"]["rate_output_mean"], periods.rate_output_mean)
    assert g["table"]["time"].tolist() == [t[-1]] and g["table"]["rate_command"].tolist() == [5.0]
    assert (g["table"]["rate_measured"][0], g["table"]["position"][0]) == (4.99, 12.5)
    assert (g["chamber"]["temperature"][0], g["chamber"]["setpoint"][0]) == (26.5, 27.0)
    np.testing.assert_array_equal(g["truth"]["time"], t)  # the lock-in's times, sample for sample
    np.testing.assert_array_equal(g["truth"]["rate"], 5.0 + delivered)  # the lost sample's truth is dropped
    assert run.attrs["clsf_reference"] == 0.25


def test_the_pll_lock_flag_of_each_block_is_on_every_one_of_its_samples(tmp_path: Path) -> None:
    path = tmp_path / "run.h5"
    w = _writer(path)
    rec = BlockRecorder(w)
    none = ClsfPeriods(*(np.zeros(0) for _ in range(5)))
    for k, locked in enumerate((True, False, True)):
        t = k + np.arange(4) / FS
        block = LockInBlock(*(t for _ in range(len(LockInBlock.FIELDS))), pll_locked=locked)
        rec.record(t, block, none, None, 0.0, None, None, 1 / FS)
    w.close()
    lockin = read_run(path).groups["lockin"]
    assert lockin["pll_locked"].dtype == np.uint8
    assert lockin["pll_locked"].tolist() == [1] * 4 + [0] * 4 + [1] * 4
