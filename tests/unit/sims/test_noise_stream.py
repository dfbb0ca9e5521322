"""NoiseStream and NormalStream: the twin's random draws are standard normals, reproducible by seed, and
independent of how a run is split into blocks.

Statistical tolerances: for N independent standard normals the sample mean has standard deviation 1/sqrt(N), the
sample variance sqrt(2/N) (normal fourth moment 3), a sample correlation of two independent columns 1/sqrt(N), and
the sample excess kurtosis sqrt(24/N); every bound below is 5 of those standard deviations (a false alarm of
about 6e-7 per check for a fair generator; the seeds are fixed, so a check's outcome does not change between runs).
"""

from __future__ import annotations

import copy
import itertools
import math
import pickle
import threading

import numpy as np
import pytest

from sims import gyro_kernel as gk
from sims.gyro import GyroSim, held_inputs
from sims.noise import NoiseStream, NormalStream
from tests.support.paper_loops import paper_loops
from tests.support.twin_params import paper_gyro_params

PATTERNS = {
    "hf2 poll blocks": [900] * 30,
    "single rows and odd sizes": [1, 1, 2, 3, 899, 1, 7, 5000, 13, 1, 4096],
    "long blocks": [3, 2 * 8192 + 5, 10, 3 * 8192, 1, 8193, 900],
}


def _z(n: int) -> float:
    """Five standard deviations of a sample mean (or correlation) of n independent standard normals."""
    return 5.0 / math.sqrt(n)


def _check_standard_normal(x: np.ndarray) -> None:
    """Columns of x (rows: samples) have mean 0, variance 1, excess kurtosis 0 and no correlation between
    columns or between consecutive rows, each to 5 standard deviations of its estimator."""
    n, width = x.shape
    x64 = x.astype(np.float64)
    for col in x64.T:
        assert abs(col.mean()) < _z(n)
        assert abs(col.var() - 1.0) < 5.0 * math.sqrt(2.0 / n)
        excess = float(np.mean((col - col.mean()) ** 4) / col.var() ** 2 - 3.0)
        assert abs(excess) < 5.0 * math.sqrt(24.0 / n)
        assert abs(float(np.corrcoef(col[:-1], col[1:])[0, 1])) < _z(n - 1)  # no correlation from step to step
    corr = np.corrcoef(x64, rowvar=False)
    for i, j in itertools.combinations(range(width), 2):
        assert abs(corr[i, j]) < _z(n)


def test_per_step_and_bias_draws_are_independent_standard_normals() -> None:
    stream = NoiseStream(5, gk.NOISE_PER_STEP, gk.N_GM)
    steps = stream.steps(200_000)
    gm = stream.gm(50_000)
    assert steps.shape == (200_000, gk.NOISE_PER_STEP) and steps.dtype == np.float32
    assert gm.shape == (50_000, gk.N_GM) and gm.dtype == np.float64
    _check_standard_normal(steps)
    _check_standard_normal(gm)
    # the per-step and the bias streams are independent of each other
    both = np.concatenate([steps[:50_000].astype(np.float64), gm], axis=1)
    corr = np.corrcoef(both, rowvar=False)[: gk.NOISE_PER_STEP, gk.NOISE_PER_STEP :]
    assert np.max(np.abs(corr)) < _z(50_000)


@pytest.mark.parametrize("pattern", list(PATTERNS.values()), ids=list(PATTERNS))
def test_the_rows_do_not_depend_on_how_the_run_is_split_into_blocks(pattern: list[int]) -> None:
    """A run cut into blocks draws the same rows as the same run in one block (the stream is read in order)."""
    split = NoiseStream(7, gk.NOISE_PER_STEP, gk.N_GM)
    whole = NoiseStream(7, gk.NOISE_PER_STEP, gk.N_GM)
    got = np.concatenate([split.steps(n) for n in pattern])
    np.testing.assert_array_equal(got, whole.steps(sum(pattern)))
    gm_pattern = [5, 1, 127, 1, 257, 3]
    np.testing.assert_array_equal(np.concatenate([split.gm(n) for n in gm_pattern]), whole.gm(sum(gm_pattern)))


def test_the_same_seed_gives_the_same_draws_and_other_seeds_other_draws() -> None:
    pattern = PATTERNS["single rows and odd sizes"]
    runs = {}
    for seed in (0, 1, 2**40 + 3):
        a, b = NoiseStream(seed, gk.NOISE_PER_STEP, gk.N_GM), NoiseStream(seed, gk.NOISE_PER_STEP, gk.N_GM)
        rows_a = np.concatenate([a.steps(n) for n in pattern])
        np.testing.assert_array_equal(rows_a, np.concatenate([b.steps(n) for n in pattern]))
        np.testing.assert_array_equal(a.gm(40), b.gm(40))
        runs[seed] = rows_a
    for s, t in itertools.combinations(runs, 2):  # distinct seeds: independent streams, not shifted copies
        corr = np.corrcoef(runs[s].ravel().astype(np.float64), runs[t].ravel().astype(np.float64))[0, 1]
        assert abs(corr) < _z(runs[s].size)


def test_consecutive_blocks_are_independent_of_each_other() -> None:
    """Block k + 1 does not repeat or correlate with block k (the stream moves on; no row handed out twice)."""
    stream = NoiseStream(3, gk.NOISE_PER_STEP, gk.N_GM)
    blocks = [stream.steps(3600).astype(np.float64) for _ in range(20)]
    for a, b in itertools.pairwise(blocks):
        assert not np.array_equal(a, b)
        assert abs(float(np.corrcoef(a.ravel(), b.ravel())[0, 1])) < _z(a.size)
    _check_standard_normal(np.concatenate(blocks))


def test_off_calls_draw_nothing() -> None:
    """Zeros when a noise is off, and the stream is not advanced: the next draws are those it would have made."""
    stream = NoiseStream(9, gk.NOISE_PER_STEP, gk.N_GM)
    ref = NoiseStream(9, gk.NOISE_PER_STEP, gk.N_GM)
    np.testing.assert_array_equal(stream.steps(17, enabled=False), np.zeros((17, gk.NOISE_PER_STEP), np.float32))
    np.testing.assert_array_equal(stream.gm(4, enabled=False), np.zeros((4, gk.N_GM)))
    np.testing.assert_array_equal(stream.gm(0), np.zeros((1, gk.N_GM)))  # the kernel indexes one row
    np.testing.assert_array_equal(stream.steps(900), ref.steps(900))
    np.testing.assert_array_equal(stream.gm(3), ref.gm(3))


def test_a_copy_continues_the_stream_like_the_original() -> None:
    stream = NoiseStream(4, gk.NOISE_PER_STEP, gk.N_GM)
    for n in (900, 900, 900):
        stream.steps(n)
    twins = [copy.deepcopy(stream), pickle.loads(pickle.dumps(stream))]
    expected = stream.steps(5000)
    for s in twins:
        np.testing.assert_array_equal(s.steps(5000), expected)


@pytest.mark.parametrize("seed", [-1, 1.5, "3"])
def test_a_seed_must_be_a_non_negative_integer(seed: object) -> None:
    with pytest.raises(ValueError, match="seed"):
        NoiseStream(seed, 6, 16)  # type: ignore[arg-type]


def test_normal_stream_is_the_generators_normals_in_order_whatever_the_split() -> None:
    """NormalStream (the HF2 twin's AuxIn noise): float64 standard normals, the same values however the calls
    split them, reproducible from the generator's seed."""
    seed = np.random.SeedSequence(11, spawn_key=(7,))
    pattern = [7200, 7200, 1800, 0, 1, 14400, 3]
    stream = NormalStream(np.random.Generator(np.random.PCG64(seed)))
    got = [stream.take(n) for n in pattern]
    for g, n in zip(got, pattern, strict=True):
        assert g.shape == (n,) and g.dtype == np.float64
    again = NormalStream(np.random.Generator(np.random.PCG64(seed))).take(sum(pattern))
    np.testing.assert_array_equal(np.concatenate(got), again)
    _check_standard_normal(stream.take(200_000).reshape(-1, 2))


def test_twins_draw_in_the_callers_thread_and_start_none() -> None:
    """Many simulators running blocks leave the process's thread count as it was: no draw-ahead thread."""
    loops = paper_loops(1.0)
    inputs = held_inputs(900, 1.0 / 1800.0)
    before = {t.ident for t in threading.enumerate()}
    sims = [GyroSim(paper_gyro_params(), 1.0 / 1800.0, seed=seed) for seed in range(20)]
    for sim in sims:
        for _ in range(3):
            sim.run(inputs, loops)
    assert {t.ident for t in threading.enumerate()} <= before
