"""Noise sources of the QMG twin: the bias-instability (flicker) model and the per-step random draws.

Bias instability (docs/noise-budget.md): a sum of first-order Gauss-Markov rates with correlation
times T_j = 10^(j/3) s, j = 0..15 (1 s ... 1e5 s, 3 per decade), each of variance

    sigma_j^2 = B^2 / (pi n_e),   n_e = 3 / ln 10   (processes per e-fold of T)

because sum_j 4 sigma_j^2 T_j / (1 + (2 pi f T_j)^2) ~ n_e * integral 4 sigma^2 dT / (1 + (2 pi f T)^2)
= sigma^2 n_e / f = B^2 / (pi f): the ONE-sided flicker spectrum whose overlapping Allan deviation is
sqrt(2 ln 2 B^2 / pi) = 0.664 B (IEEE 952 writes S = B^2/(2 pi f) two-sided). B = bias_instability in rad/s.
Each process is updated every update period T_u (about 0.1 s) and held in between:
x <- a x + sigma sqrt(1 - a^2) w, a = exp(-T_u / T_j) (exact discretization of the Gauss-Markov process).

Per-step draws and bias-update draws come from two independent PCG64 streams of one seed, drawn in the caller's
thread when asked for (numpy's Generator): a stream read in order gives the same values however the reads are split
into blocks, so a run is reproducible from its seed.
"""

from __future__ import annotations

import math

import numpy as np

GM_UPDATE_S = 0.1
GM_TIMES_S = 10.0 ** (np.arange(16) / 3.0)
N_E = 3.0 / math.log(10.0)
RAD_S_PER_DEG_H = math.pi / 180.0 / 3600.0


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


class NormalStream:
    """Float64 standard normals of one generator, in stream order: the n values of each call are the generator's
    next n (a float64 normal draw split into pieces is the same sequence as one draw of the whole)."""

    def __init__(self, gen: np.random.Generator) -> None:
        self._gen = gen

    def take(self, n: int) -> np.ndarray:
        """The next n values, shape (n,)."""
        return self._gen.standard_normal(n)


class NoiseStream:
    """Reproducible standard-normal draws for one simulator: per-step draws and bias-update draws come from
    two independent PCG64 streams spawned from SeedSequence(seed) (per-step first, bias second), each read in
    order, so the draws do not depend on how a run is split into blocks."""

    def __init__(self, seed: int, per_step: int, n_gm: int) -> None:
        if not isinstance(seed, (int, np.integer)) or seed < 0:
            raise ValueError(f"seed must be a non-negative integer, got {seed!r}")
        s1, s2 = np.random.SeedSequence(int(seed)).spawn(2)
        self.per_step = per_step
        self.n_gm = n_gm
        self._step_gen = np.random.Generator(np.random.PCG64(s1))
        self._gm_gen = np.random.Generator(np.random.PCG64(s2))

    def steps(self, n: int, enabled: bool = True) -> np.ndarray:
        """(n, per_step) float32 draws (ziggurat; single precision is ample for noise and twice as fast), the
        next n rows of the per-step stream; zeros without drawing when every per-step noise is off."""
        if not enabled:
            return np.zeros((n, self.per_step), dtype=np.float32)
        return self._step_gen.standard_normal((n, self.per_step), dtype=np.float32)

    def gm(self, n_updates: int, enabled: bool = True) -> np.ndarray:
        """(n_updates, n_gm) draws for the bias processes (at least one row so the kernel can index it)."""
        if n_updates <= 0 or not enabled:
            return np.zeros((max(1, n_updates), self.n_gm))
        return self._gm_gen.standard_normal((n_updates, self.n_gm))
