"""NoiseStream: the prefetched per-step draws and the read-ahead bias draws are the stream's own values, in order.

The reference is what NoiseStream did before it drew ahead: each call draws exactly the rows it returns from
PCG64 generators seeded from SeedSequence(seed).spawn(2) (per-step stream first, bias stream second). The block
patterns cross the prefetch size (PREFETCH_ROWS) and the bias read-ahead (GM_ROWS_AHEAD) in every way: single
rows, a request larger than a prefetch, requests that end exactly on a boundary, off-calls that draw nothing.
"""

from __future__ import annotations

import copy
import os
import pickle
import select
import signal
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import pytest

from sims import gyro_kernel as gk
from sims.gyro import GyroParams, GyroSim, held_inputs
from sims.noise import GM_ROWS_AHEAD, PREFETCH_ROWS, NoiseStream, NormalStream, set_default_prefetch
from tests.support.paper_loops import paper_loops

ROOT = Path(__file__).resolve().parents[3]
P = PREFETCH_ROWS
PATTERNS = {
    "hf2 poll blocks": [900] * 30,
    "single rows and odd sizes": [1, 1, 2, 3, 899, 1, 7, 5000, 13, 1, 4096],
    "ends on prefetch boundaries": [P, P, P // 2, P // 2, P, 1, P - 1, P],
    "larger than a prefetch": [3, 2 * P + 5, 10, 3 * P, 1, P + 1, 900],
}


def _generators(seed: int) -> tuple[np.random.Generator, np.random.Generator]:
    s1, s2 = np.random.SeedSequence(seed).spawn(2)
    return np.random.Generator(np.random.PCG64(s1)), np.random.Generator(np.random.PCG64(s2))


def _reference_steps(seed: int, pattern: list[int]) -> list[np.ndarray]:
    """The draws of the stream without read-ahead: exactly n float32 rows per call."""
    gen, _ = _generators(seed)
    return [gen.standard_normal((n, gk.NOISE_PER_STEP), dtype=np.float32) for n in pattern]


@pytest.mark.parametrize("pattern", list(PATTERNS.values()), ids=list(PATTERNS))
@pytest.mark.parametrize("seed", [0, 5, 2**40 + 3])
def test_per_step_rows_are_the_stream_in_order_for_any_block_pattern(seed: int, pattern: list[int]) -> None:
    stream = NoiseStream(seed, gk.NOISE_PER_STEP, gk.N_GM, prefetch=True)
    got = [stream.steps(n) for n in pattern]
    for g, ref in zip(got, _reference_steps(seed, pattern), strict=True):
        assert g.dtype == np.float32
        np.testing.assert_array_equal(g, ref)
    # and the same values as one draw of the whole (a float32 draw split into pieces is the same sequence)
    whole = _generators(seed)[0].standard_normal((sum(pattern), gk.NOISE_PER_STEP), dtype=np.float32)
    np.testing.assert_array_equal(np.concatenate(got), whole)


@pytest.mark.parametrize("pattern", list(PATTERNS.values()), ids=list(PATTERNS))
def test_switching_prefetch_off_and_on_mid_stream_keeps_the_order(pattern: list[int]) -> None:
    stream = NoiseStream(8, gk.NOISE_PER_STEP, gk.N_GM, prefetch=False)
    got = []
    for k, n in enumerate(pattern):
        if k % 3 == 2:
            stream.prefetch = not stream.prefetch  # a pending prefetch is still collected in order
        got.append(stream.steps(n))
    for g, ref in zip(got, _reference_steps(8, pattern), strict=True):
        np.testing.assert_array_equal(g, ref)


def test_rows_handed_out_stay_valid_while_the_stream_draws_on() -> None:
    stream = NoiseStream(3, gk.NOISE_PER_STEP, gk.N_GM, prefetch=True)
    pattern = [900] * 40
    kept = [stream.steps(n) for n in pattern]  # every array kept until the end: none may be overwritten
    for g, ref in zip(kept, _reference_steps(3, pattern), strict=True):
        np.testing.assert_array_equal(g, ref)


def test_off_calls_draw_nothing_and_bias_rows_are_their_own_stream_in_order() -> None:
    stream = NoiseStream(9, gk.NOISE_PER_STEP, gk.N_GM, prefetch=True)
    step_pattern = [900, 900, 900, 900]
    gm_pattern = [5, 0, 1, GM_ROWS_AHEAD - 6, 1, 2 * GM_ROWS_AHEAD + 1, 3]
    steps, gms = [], []
    for k, n_gm in enumerate(gm_pattern):
        if k < len(step_pattern):
            steps.append(stream.steps(step_pattern[k]))
        off = stream.steps(17, enabled=False)
        np.testing.assert_array_equal(off, np.zeros((17, gk.NOISE_PER_STEP), dtype=np.float32))
        np.testing.assert_array_equal(stream.gm(4, enabled=False), np.zeros((4, gk.N_GM)))
        gms.append(stream.gm(n_gm))
    _, gm_gen = _generators(9)
    for n_gm, got in zip(gm_pattern, gms, strict=True):
        expected = gm_gen.standard_normal((n_gm, gk.N_GM)) if n_gm > 0 else np.zeros((1, gk.N_GM))
        np.testing.assert_array_equal(got, expected)
    for g, ref in zip(steps, _reference_steps(9, step_pattern), strict=True):
        np.testing.assert_array_equal(g, ref)


def test_a_copy_continues_the_stream_like_the_original() -> None:
    stream = NoiseStream(4, gk.NOISE_PER_STEP, gk.N_GM, prefetch=True)
    pattern = [900, 900, 900, P, 900, 900]
    ref = _reference_steps(4, pattern)
    for n in pattern[:3]:
        stream.steps(n)  # a prefetch is outstanding from the second call on
    twins = [stream, copy.deepcopy(stream), pickle.loads(pickle.dumps(stream))]
    for s in twins:
        for n, r in zip(pattern[3:], ref[3:], strict=True):
            np.testing.assert_array_equal(s.steps(n), r)


def test_many_sims_share_one_prefetch_thread() -> None:
    loops = paper_loops(1.0)
    inputs = held_inputs(900, 1.0 / 1800.0)
    sims = []
    before = threading.active_count()
    for seed in range(150):
        sim = GyroSim(GyroParams(), 1.0 / 1800.0, seed=seed)
        sim._noise.prefetch = True  # whatever the CPU count of the machine running the test
        for _ in range(3):  # the second block starts a prefetch
            sim.run(inputs, loops)
        sims.append(sim)
    prefetchers = [t for t in threading.enumerate() if t.name.startswith("sims-noise-prefetch")]
    assert len(prefetchers) == 1
    assert threading.active_count() <= before + 1


@pytest.mark.skipif(not hasattr(os, "fork"), reason="os.fork is POSIX only")
def test_a_forked_child_continues_the_stream_with_its_own_prefetch_thread() -> None:
    pattern = [900] * 12
    ref = np.concatenate(_reference_steps(6, pattern))
    stream = NoiseStream(6, gk.NOISE_PER_STEP, gk.N_GM, prefetch=True)
    head = [stream.steps(n) for n in pattern[:2]]  # the second call left a prefetch pending (or finished)
    r, w = os.pipe()
    pid = os.fork()
    if pid == 0:  # the child: draw on (its prefetches need a thread of its own), send the rows, exit at once
        try:
            rows = np.concatenate(head + [stream.steps(n) for n in pattern[2:]])
            alive = any(t.name.startswith("sims-noise-prefetch") for t in threading.enumerate())
            os.write(w, rows.tobytes() + (b"T" if alive else b"F"))
        finally:
            os._exit(0)
    os.close(w)
    received = b""
    try:
        while len(received) < ref.nbytes + 1:
            ready, _, _ = select.select([r], [], [], 60.0)
            if not ready:
                os.kill(pid, signal.SIGKILL)
                pytest.fail("the forked child did not deliver its draws within 60 s (a deadlock)")
            chunk = os.read(r, ref.nbytes + 1 - len(received))
            if not chunk:
                break
            received += chunk
    finally:
        os.close(r)
        _, status = os.waitpid(pid, 0)
    assert os.waitstatus_to_exitcode(status) == 0
    child = np.frombuffer(received[:-1], dtype=np.float32).reshape(ref.shape)
    np.testing.assert_array_equal(child, ref)
    assert received[-1:] == b"T", "the child's prefetches found no thread (the parent's executor was kept)"
    # the parent's stream is untouched by the child
    parent = np.concatenate(head + [stream.steps(n) for n in pattern[2:]])
    np.testing.assert_array_equal(parent, ref)


@pytest.mark.skipif(not hasattr(os, "sched_setaffinity"), reason="no CPU affinity on this OS")
def test_the_default_prefetches_only_with_a_second_cpu_to_run_on() -> None:
    code = (
        "import os; from sims.noise import NoiseStream, usable_cpus; "
        "print(usable_cpus(), NoiseStream(1, 6, 16).prefetch); "
        "os.sched_setaffinity(0, {min(os.sched_getaffinity(0))}); "
        "print(usable_cpus(), NoiseStream(1, 6, 16).prefetch)"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=ROOT)
    first, pinned = out.stdout.split("\n")[:2]
    n = len(os.sched_getaffinity(0))
    assert first == f"{n} {n > 1}"
    assert pinned == "1 False"


def test_a_process_wide_default_overrides_the_automatic_choice_and_keeps_the_values() -> None:
    """set_default_prefetch (what a study's full LocalCluster sets in its workers) decides for streams created
    afterwards; None restores the automatic choice; an explicit prefetch= still wins; the values do not change."""
    auto = len(os.sched_getaffinity(0)) > 1 if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1) > 1
    pattern = PATTERNS["hf2 poll blocks"]
    try:
        set_default_prefetch(False)
        off = NoiseStream(3, 6, 16)
        forced_on = NoiseStream(3, 6, 16, prefetch=True)
        assert (off.prefetch, forced_on.prefetch) == (False, True)
        set_default_prefetch(True)
        assert NoiseStream(3, 6, 16).prefetch is True
        set_default_prefetch(None)
        assert NoiseStream(3, 6, 16).prefetch is auto
    finally:
        set_default_prefetch(None)
    rows_off = np.concatenate([off.steps(n) for n in pattern])
    rows_on = np.concatenate([forced_on.steps(n) for n in pattern])
    np.testing.assert_array_equal(rows_off, rows_on)
    np.testing.assert_array_equal(rows_off, np.concatenate(_reference_steps(3, pattern)))


NORMAL_PATTERNS = {
    "hf2 AuxIn blocks (2 x 3600)": [7200] * 12,
    "the block size changes": [7200, 7200, 1800, 1800, 7200, 1, 7200, 14400, 3],
    "off-calls interleaved": [7200, 0, 7200, 7200, 0, 0, 7200],
}


@pytest.mark.parametrize("prefetch", [True, False])
@pytest.mark.parametrize("pattern", list(NORMAL_PATTERNS.values()), ids=list(NORMAL_PATTERNS))
def test_normal_stream_hands_out_the_generators_float64_draws_in_order(pattern: list[int], prefetch: bool) -> None:
    """NormalStream (the HF2 twin's AuxIn noise) gives exactly what drawing each call's count in the caller's
    thread gives, and the same as one draw of the whole; arrays handed out stay valid while it draws on."""
    seed = np.random.SeedSequence(11, spawn_key=(7,))
    stream = NormalStream(np.random.Generator(np.random.PCG64(seed)), prefetch=prefetch)
    assert stream.prefetch is prefetch
    got = [stream.take(n) for n in pattern]
    ref_gen = np.random.Generator(np.random.PCG64(seed))
    for g, n in zip(got, pattern, strict=True):
        assert g.shape == (n,) and g.dtype == np.float64
        np.testing.assert_array_equal(g, ref_gen.standard_normal(n))
    whole = np.random.Generator(np.random.PCG64(seed)).standard_normal(sum(pattern))
    np.testing.assert_array_equal(np.concatenate(got), whole)


def test_normal_stream_switched_mid_stream_and_copied_keeps_the_order() -> None:
    seed = np.random.SeedSequence(5)
    stream = NormalStream(np.random.Generator(np.random.PCG64(seed)), prefetch=True)
    pattern = [7200] * 9
    ref = np.random.Generator(np.random.PCG64(seed)).standard_normal(sum(pattern))
    head = [stream.take(n) for n in pattern[:3]]  # a prefetch is pending from the second call on
    stream.prefetch = False
    head.append(stream.take(pattern[3]))
    stream.prefetch = True
    head.append(stream.take(pattern[4]))
    for other in (stream, copy.deepcopy(stream), pickle.loads(pickle.dumps(stream))):
        tail = [other.take(n) for n in pattern[5:]]
        np.testing.assert_array_equal(np.concatenate(head + tail), ref)


def test_calls_of_one_size_come_from_whole_prefetched_chunks_without_a_copy() -> None:
    """From the third call on, calls of one size (a poll's block) are views of a prefetch of whole calls: no call
    straddles two chunks (PREFETCH_ROWS // n calls per chunk), and the values are the stream's."""
    n = 3600
    stream = NoiseStream(2, gk.NOISE_PER_STEP, gk.N_GM, prefetch=True)
    got = [stream.steps(n) for _ in range(9)]
    for rows in got[2:]:
        assert rows.base is not None and rows.base.shape[0] == n * (PREFETCH_ROWS // n)
    for g, ref in zip(got, _reference_steps(2, [n] * 9), strict=True):
        np.testing.assert_array_equal(g, ref)
