"""Compiled (numba) per-sample loops of the HF2 data-server twin's poll (sims/hf2_server.py): one pass each where
the vectorised version made several numpy passes over a block (and allocated a temporary per pass).

Each loop evaluates the twin's documented equation with the same floating-point operations in the same order as
the numpy expressions it replaces (sequential cumulative sums, numpy's floor-modulo, no fused multiply-adds:
numba's default fastmath=False), and draws the AuxIn noise from the same `numpy.random.Generator` in the same
order (numba's Generator.standard_normal is numpy's ziggurat on the same bit generator), so a poll's samples are
the same numbers whichever evaluated them (tests/unit/sims/test_hf2_kernel.py):

* `oscillator_phases`: phi_k = phi_0 + ((2 pi) c_k) dt with c_k = f_0 + ... + f_k (the oscillator's phase in rad
  at the end of step k, from its frequencies f_k in Hz), and the phase the demodulator reports,
  (h phi_k) mod 2 pi for harmonic h (floor-modulo, Python's and numpy's: the result takes the sign of 2 pi, in
  [0, 2 pi); the remainder of a floating-point division is exact).
* `sample_times`: timestamps T_k = T_0 + (k + 1) m in clockbase ticks (m ticks per sample), and the same instants
  in seconds, T_k / clockbase.
* `auxin_readings`: row 0, the rate AuxOut's mean over the AuxIn window W ending at each sample instant,
  V_i - (V_i - V_(i-1)) W / (2 dt) (V piecewise linear between instants; V_(-1) the previous block's last value);
  row 1 the dither's window means as given; then every reading + sigma n (n the given 2 x n standard normals,
  row 0 then row 1 of one stream, which the twin's numpy generator draws before the call (sims/noise.py
  NormalStream): drawing inside the loop through numba's Generator support gives the same numbers but costs
  ~24 us per call to unbox the generator),
  rounded to the ADC step, floor(v / lsb + 0.5) lsb, and clipped to +-R (lsb = 0: an ideal ADC, neither rounded
  nor clipped).

Compiled on first use and cached on disk (cache=True); the first campaign after an install pays about a second.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

TWO_PI = 2 * np.pi  # the constant numpy's `2 * np.pi * array` multiplies by


@njit(cache=True)
def oscillator_phases(
    frequency_hz: np.ndarray, phase0_rad: float, dt: float, harmonic: float, phase_rad: np.ndarray, wrapped: np.ndarray
) -> None:
    """Unwrapped phases (rad) at the end of every step into `phase_rad`, and (harmonic * phase) mod 2 pi into
    `wrapped` (module docstring). A harmonic of 1 is not multiplied."""
    c = 0.0
    for k in range(frequency_hz.shape[0]):
        c = frequency_hz[k] if k == 0 else c + frequency_hz[k]
        ph = phase0_rad + TWO_PI * c * dt
        phase_rad[k] = ph
        wrapped[k] = (ph if harmonic == 1.0 else ph * harmonic) % TWO_PI


@njit(cache=True)
def sample_times(
    ticks0: int, ticks_per_sample: int, clockbase_hz: float, timestamps: np.ndarray, time_s: np.ndarray
) -> None:
    """Timestamps ticks0 + (k + 1) ticks_per_sample (clockbase ticks) and the same instants in s."""
    for k in range(timestamps.shape[0]):
        ts = ticks0 + (k + 1) * ticks_per_sample
        timestamps[k] = ts
        time_s[k] = float(ts) / clockbase_hz


@njit(cache=True)
def auxin_readings(
    auxout_v: np.ndarray,
    previous_v: float,
    window_over_2dt: float,
    dither_v: np.ndarray,
    normals: np.ndarray,
    noise_v_rms: float,
    lsb_v: float,
    range_v: float,
    out: np.ndarray,
) -> None:
    """What the two AuxIns report (module docstring) into `out` (2 x n: row 0 the rate AuxOut, row 1 the dither).
    previous_v: the AuxOut at the instant before the block (its first value if there is none);
    window_over_2dt = W / (2 dt); normals: 2 x n standard normal draws (read only if noise_v_rms > 0)."""
    n = auxout_v.shape[0]
    for i in range(n):  # one pass: each reading's mean, noise, rounding and clipping in the order above
        before = previous_v if i == 0 else auxout_v[i - 1]
        rate = auxout_v[i] - (auxout_v[i] - before) * window_over_2dt
        dither = dither_v[i]
        if noise_v_rms > 0.0:
            rate += normals[0, i] * noise_v_rms
            dither += normals[1, i] * noise_v_rms
        if lsb_v > 0.0:
            rate = min(max(math.floor(rate / lsb_v + 0.5) * lsb_v, -range_v), range_v)
            dither = min(max(math.floor(dither / lsb_v + 0.5) * lsb_v, -range_v), range_v)
        out[0, i] = rate
        out[1, i] = dither
