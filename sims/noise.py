"""Noise sources of the QMG twin: the bias-instability (flicker) model and the per-step random draws.

Bias instability (docs/noise-budget.md): a sum of first-order Gauss-Markov rates with correlation
times T_j = 10^(j/3) s, j = 0..15 (1 s ... 1e5 s, 3 per decade), each of variance

    sigma_j^2 = B^2 / (pi n_e),   n_e = 3 / ln 10   (processes per e-fold of T)

because sum_j 4 sigma_j^2 T_j / (1 + (2 pi f T_j)^2) ~ n_e * integral 4 sigma^2 dT / (1 + (2 pi f T)^2)
= sigma^2 n_e / f = B^2 / (pi f): the ONE-sided flicker spectrum whose overlapping Allan deviation is
sqrt(2 ln 2 B^2 / pi) = 0.664 B (IEEE 952 writes S = B^2/(2 pi f) two-sided). B = bias_instability in rad/s.
Each process is updated every update period T_u (about 0.1 s) and held in between:
x <- a x + sigma sqrt(1 - a^2) w, a = exp(-T_u / T_j) (exact discretization of the Gauss-Markov process).

Per-step draws (NoiseStream.steps) are prefetched: while the caller's compiled kernel runs (nogil), one shared
background thread draws the next rows of the same stream (numpy's Generator fills release the GIL), so on a
machine with a free core the draws cost the caller almost nothing. The realisation is unchanged: the rows come
from one PCG64 stream in the order they are handed out, and a float32 normal draw split into pieces gives the same
sequence as one draw of the whole (the bit generator keeps the unused half of a 64-bit output between calls).
"""

from __future__ import annotations

import math
import os
import threading
from collections.abc import Mapping
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any

import numpy as np

GM_UPDATE_S = 0.1
GM_TIMES_S = 10.0 ** (np.arange(16) / 3.0)
N_E = 3.0 / math.log(10.0)
RAD_S_PER_DEG_H = math.pi / 180.0 / 3600.0
PREFETCH_ROWS = 1 << 13  # per-step rows drawn ahead per prefetch, at most (8192 x 6 float32 = 192 kB; larger calls: n)
GM_ROWS_AHEAD = 1 << 7  # bias-update rows drawn at a time (128 x 16 float64 = 16 kB: 12.8 s of updates at 0.1 s)


def gm_steps(dt_s: float) -> int:
    """Steps between bias updates: round(0.1 s / dt), at least 1."""
    return max(1, int(round(GM_UPDATE_S / dt_s)))


def gm_sigmas_rad_s(bias_instability_deg_per_h: float) -> np.ndarray:
    """Stationary standard deviation of each Gauss-Markov process, rad/s: B / sqrt(pi n_e)."""
    b = bias_instability_deg_per_h * RAD_S_PER_DEG_H
    return np.full(GM_TIMES_S.shape, b / math.sqrt(math.pi * N_E))


def gm_coefficients(bias_instability_deg_per_h: float, update_period_s: float) -> tuple[np.ndarray, np.ndarray]:
    """(a_j, b_j) of x <- a_j x + b_j w for an update period T_u: a = exp(-T_u/T_j), b = sigma sqrt(1 - a^2)."""
    a = np.exp(-update_period_s / GM_TIMES_S)
    b = gm_sigmas_rad_s(bias_instability_deg_per_h) * np.sqrt(1.0 - a * a)
    return a, b


class _PrefetchThread:
    """The one background thread of a process that draws NoiseStream rows ahead (a ThreadPoolExecutor of one
    worker, created on first use, so a process that never prefetches starts no thread and many streams share
    one). After os.fork the child forgets the parent's executor (its thread does not exist there) and creates
    its own when needed; the executor's own exit hook lets a running fill finish (< 1 ms) at interpreter exit."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._executor: ThreadPoolExecutor | None = None
        os.register_at_fork(after_in_child=self._forget)

    def _forget(self) -> None:
        self._lock = threading.Lock()
        self._executor = None

    def submit(self, gen: np.random.Generator, rows: int, width: int, dtype: type) -> Future[np.ndarray] | None:
        """Start drawing (rows, width) standard normals of dtype from gen; None when no thread can take it (the
        interpreter is shutting down): the caller then draws them itself when it needs them."""
        with self._lock:
            if self._executor is None:
                self._executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix="sims-noise-prefetch")
            executor = self._executor
        try:
            return executor.submit(gen.standard_normal, (rows, width), dtype)
        except RuntimeError:  # "cannot schedule new futures after (interpreter) shutdown"
            return None


_PREFETCH = _PrefetchThread()


def usable_cpus() -> int:
    """CPUs this process may run on (its affinity mask where the OS has one, else os.cpu_count())."""
    if hasattr(os, "sched_getaffinity"):
        return len(os.sched_getaffinity(0))
    return os.cpu_count() or 1


_DEFAULTS: dict[str, bool | None] = {"prefetch": None}  # set_default_prefetch's process-wide setting


def set_default_prefetch(enabled: bool | None) -> None:
    """The prefetch of NoiseStreams created from now on in this process when they are not told: True (draw ahead
    on the background thread), False (draw in the caller's thread), None (the automatic choice: draw ahead when
    the process may run on more than one CPU). For processes that share the machine's cores with as many others
    as there are cores (a study's workers): there the second thread finds no idle core and only takes turns."""
    _DEFAULTS["prefetch"] = enabled


def default_prefetch() -> bool:
    """What a NoiseStream created now prefetches by default (set_default_prefetch, else usable_cpus() > 1)."""
    chosen = _DEFAULTS["prefetch"]
    return chosen if chosen is not None else usable_cpus() > 1


@dataclass
class _Prefetch:
    """Rows being drawn ahead: the future of the draw, its size, the generator state before it (to redo it in a
    process forked while it was pending) and the id of the process that started it."""

    future: Future[np.ndarray]
    rows: int
    state: Mapping[str, Any]
    pid: int


class _RowStream:
    """Rows of standard normals (width per row, float32 or float64) handed out in stream order, drawn ahead: on
    the shared background thread (`background`, from the second call on, at most one chunk outstanding: as many
    whole calls of the last call's n rows as fit in `ahead` rows, at least one, so that calls of one size never
    straddle two chunks and need no copy) or here when rows run out (`ahead` rows at least without the
    background thread). Handed-out arrays are never reused."""

    def __init__(self, gen: np.random.Generator, width: int, dtype: type, ahead: int, background: bool) -> None:
        self._gen = gen
        self._width = width
        self._dtype = dtype
        self._ahead = ahead
        self.background = background
        self._rows: np.ndarray = np.empty((0, width), dtype=dtype)  # drawn rows; [_pos:] not yet handed out
        self._pos = 0
        self._job: _Prefetch | None = None
        self._called = False

    def take(self, n: int) -> np.ndarray:
        """The next n rows, shape (n, width)."""
        pos = self._pos
        if n <= self._rows.shape[0] - pos:
            out = self._rows[pos : pos + n]
            self._pos = pos + n
        else:
            out = self._take_across(n)
        if self.background and self._job is None:
            if self._called:  # whole calls of this size: the next ones are handed out without a copy
                self._prefetch(n * max(1, self._ahead // n) if n > 0 else self._ahead)
            self._called = True
        return out

    def _draw(self, rows: int) -> np.ndarray:
        return self._gen.standard_normal((rows, self._width), dtype=self._dtype)

    def _take_across(self, n: int) -> np.ndarray:
        """n rows when the drawn ones do not suffice: the rest of them, then the prefetched rows (waiting for
        them), then rows drawn here (only when nothing is pending, so the stream order is kept)."""
        parts = [self._rows[self._pos :]]
        need = n - parts[0].shape[0]
        self._rows, self._pos = self._rows[:0], 0
        if self._job is not None:
            drawn = self._collect(self._job)
            take = min(need, drawn.shape[0])
            parts.append(drawn[:take])
            need -= take
            self._rows, self._pos = drawn, take
        if need > 0:
            if self.background:  # the next prefetch is started by take()
                parts.append(self._draw(need))
            else:
                drawn = self._draw(max(self._ahead, need))
                parts.append(drawn[:need])
                self._rows, self._pos = drawn, need
        parts = [p for p in parts if p.shape[0] > 0]
        return parts[0] if len(parts) == 1 else np.concatenate(parts)

    def _prefetch(self, rows: int) -> None:
        """Start drawing the next `rows` rows on the background thread (the generator is not touched here until
        they are collected)."""
        state = self._gen.bit_generator.state
        future = _PREFETCH.submit(self._gen, rows, self._width, self._dtype)
        if future is not None:
            self._job = _Prefetch(future, rows, state, os.getpid())

    def _collect(self, job: _Prefetch) -> np.ndarray:
        """The rows of the pending prefetch `job`: its result, or drawn here when its thread has not started it
        yet (a busy machine: cancelling it leaves the generator untouched, and waiting for a thread that has no
        core would only add latency). In a process forked while it was pending, the draw never ran there (or
        stopped half-way, its generator lock held): redo it here from the generator state saved before it."""
        self._job = None
        if job.pid != os.getpid():
            bits = type(self._gen.bit_generator)()
            bits.state = job.state
            self._gen = np.random.Generator(bits)
        elif not job.future.cancel():
            return job.future.result()
        return self._draw(job.rows)

    def __getstate__(self) -> dict[str, Any]:
        """The state for copy/pickle, a pending prefetch first collected into the drawn rows."""
        if self._job is not None:
            drawn = self._collect(self._job)
            self._rows, self._pos = np.concatenate([self._rows[self._pos :], drawn]), 0
        return self.__dict__.copy()


class _DrawnAhead:
    """The `prefetch` switch of a stream whose values `_ahead` draws ahead."""

    _ahead: _RowStream

    @property
    def prefetch(self) -> bool:
        """Whether the values are drawn ahead on the background thread."""
        return self._ahead.background

    @prefetch.setter
    def prefetch(self, on: bool) -> None:
        self._ahead.background = bool(on)


class NormalStream(_DrawnAhead):
    """Float64 standard normals of one generator, handed out in stream order and drawn ahead like NoiseStream's
    per-step rows: from the second call on, the shared background thread draws as many values as the last call
    asked for while the caller computes, so a caller that asks for the same count every time (a poll's block)
    finds its values drawn and gets them without a copy. The values are those of drawing exactly what each call
    asks for in the caller's thread: numpy's float64 normals keep no state between draws but the bit
    generator's, so a draw split into pieces is the same sequence as one draw of the whole.
    `prefetch`: as NoiseStream's (None: default_prefetch())."""

    def __init__(self, gen: np.random.Generator, prefetch: bool | None = None) -> None:
        if prefetch is None:
            prefetch = default_prefetch()
        self._ahead = _RowStream(gen, 1, np.float64, 1, prefetch)  # ahead = 1: each prefetch draws the last n

    def take(self, n: int) -> np.ndarray:
        """The next n values, shape (n,) (a view of drawn values, never reused)."""
        return self._ahead.take(n).reshape(n)


class NoiseStream(_DrawnAhead):
    """Reproducible standard-normal draws for one simulator: per-step draws and bias-update draws come from
    two independent PCG64 streams seeded from `seed`, so the draws do not depend on how a run is split
    into blocks.

    The per-step rows are prefetched: from the second call of `steps` on, the next rows are drawn on the shared
    background thread while the caller computes (as many whole calls of the last call's n as fit in
    PREFETCH_ROWS, at least n); the bias rows are drawn
    GM_ROWS_AHEAD at a time. Either way each stream is read in order, so the values are those of drawing
    exactly what each call asks for. A copy (copy.deepcopy, pickle) first collects a pending prefetch.
    `prefetch=False` (or setting `.prefetch` later) draws the per-step rows in the caller's thread instead, with
    the same values (benchmarks compare the two); the default (default_prefetch) prefetches when the process may
    run on more than one CPU, unless set_default_prefetch says otherwise."""

    def __init__(self, seed: int, per_step: int, n_gm: int, prefetch: bool | None = None) -> None:
        if not isinstance(seed, (int, np.integer)) or seed < 0:
            raise ValueError(f"seed must be a non-negative integer, got {seed!r}")
        ss = np.random.SeedSequence(int(seed))
        s1, s2 = ss.spawn(2)
        self.per_step = per_step
        self.n_gm = n_gm
        if prefetch is None:  # a second thread only pays with a second CPU to run on
            prefetch = default_prefetch()
        step_gen, gm_gen = np.random.Generator(np.random.PCG64(s1)), np.random.Generator(np.random.PCG64(s2))
        self._ahead = _RowStream(step_gen, per_step, np.float32, PREFETCH_ROWS, prefetch)  # the per-step rows
        self._gm = _RowStream(gm_gen, n_gm, np.float64, GM_ROWS_AHEAD, False)

    def steps(self, n: int, enabled: bool = True) -> np.ndarray:
        """(n, per_step) float32 draws (ziggurat; single precision is ample for noise and twice as fast), the
        next n rows of the per-step stream; zeros without drawing when every per-step noise is off."""
        if not enabled:
            return np.zeros((n, self.per_step), dtype=np.float32)
        return self._ahead.take(n)

    def gm(self, n_updates: int, enabled: bool = True) -> np.ndarray:
        """(n_updates, n_gm) draws for the bias processes (at least one row so the kernel can index it)."""
        if n_updates <= 0 or not enabled:
            return np.zeros((max(1, n_updates), self.n_gm))
        return self._gm.take(n_updates)
