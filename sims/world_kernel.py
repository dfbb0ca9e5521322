"""Compiled (numba) per-step loops of `sims.world.World.advance`: table rate and angle, chamber lags, dither means.

Each loop is the World's documented equation (sims/world.py) evaluated step by step in one pass, with the same
floating-point operations in the same order as the vectorised numpy expressions they replace, so that a block's
inputs do not depend on which of the two evaluated them (numpy's cumulative sums are sequential; the one-pole
recursion is scipy.signal.lfilter's direct form II transposed; no fused multiply-adds: numba's default
fastmath=False):

* `table_block`: r_k = p_k s (s = 1 + scale error), and with a ripple r != 0, at the ripple-free mid-step angle
  m_k = theta0 + (r_0 + ... + r_k) dt - r_k dt / 2: r_k <- r_k (1 + r sin(radians(m_k + phi_r))); then the step-start
  angles theta_k = theta0 + (r_0 + ... + r_(k-1)) dt.
* `first_order_lag`: y_0 = y0, y_(k+1) = a y_k + (1 - a) u_k, as z + b0 u_k (output) and z <- b1 u_k - a1 y_k
  (state) with b = [0, 1 - a], a = [1, -a].
* `dither_grid`: the DS345's phase u_j = f (tau(t_j) - tau_origin) + phase/360 in cycles at the step boundaries
  t_j, tau(t) = t (1 + e0) + (e_w P / 2 pi) (1 - cos(2 pi t / P)), the antiderivative W(u_j) of the unit waveform,
  and the exact step means offset + (Vpp/2) (W(u_(k+1)) - W(u_k)) / (u_(k+1) - u_k).
* `dither_window_means`: the means over [t_(k+1) - w, t_(k+1)] with du = w (u_(k+1) - u_k) / (t_(k+1) - t_k):
  offset + (Vpp/2) (W(u_(k+1)) - W(u_(k+1) - du)) / du.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

DITHER_SINE, DITHER_SQUARE, DITHER_TRIANGLE, DITHER_RAMP = 0, 1, 2, 3


@njit(cache=True)
def table_block(
    profile_mid_dps: np.ndarray,
    scale: float,
    dt: float,
    angle0_deg: float,
    ripple: float,
    ripple_phase_deg: float,
    rate_dps: np.ndarray,
    angle_deg: np.ndarray,
) -> None:
    """Delivered mean rates (deg/s) and step-start angles (deg) of a block into `rate_dps` and `angle_deg`
    (module docstring); `ripple` = r as a fraction (ppm * 1e-6), 0: no ripple."""
    n = profile_mid_dps.shape[0]
    deg = math.pi / 180.0
    cum = 0.0
    for k in range(n):
        r = profile_mid_dps[k] * scale
        if ripple != 0.0:
            cum = r if k == 0 else cum + r
            mid = angle0_deg + cum * dt - 0.5 * r * dt
            r = r * (1.0 + ripple * math.sin((mid + ripple_phase_deg) * deg))
        rate_dps[k] = r
    if n > 0:
        angle_deg[0] = 0.0 + angle0_deg
    cum = 0.0
    for k in range(1, n):
        cum = rate_dps[0] if k == 1 else cum + rate_dps[k - 1]
        angle_deg[k] = cum * dt + angle0_deg


@njit(cache=True)
def first_order_lag(u: np.ndarray, y0: float, a: float, y: np.ndarray) -> None:
    """y[0] = y0, y[k+1] = a y[k] + (1 - a) u[k] into `y` (module docstring), 0 < a < 1."""
    b0 = 0.0
    b1 = 1.0 - a
    a1 = -a
    z = y0
    for k in range(u.shape[0]):
        x = u[k]
        yk = z + b0 * x
        y[k] = yk
        z = x * b1 - yk * a1


@njit(cache=True, inline="always")
def _wave_integral(fn: int, u: float) -> float:
    """W(u): the integral of the unit waveform from 0 to u (cycles), as World._wave_integral."""
    if fn == DITHER_SQUARE:
        frac = u - math.floor(u)
        return frac if frac < 0.5 else 1.0 - frac
    if fn == DITHER_TRIANGLE:
        f = u - math.floor(u)
        return -f + 2 * f * f if f < 0.5 else 3 * (f - 0.5) - 2 * (f * f - 0.25)
    if fn == DITHER_RAMP:
        f = u - math.floor(u)
        return f * f - f
    return (1.0 - math.cos(2 * math.pi * u)) / (2 * math.pi)


@njit(cache=True)
def dither_grid(
    t_bounds_s: np.ndarray,
    e0: float,
    wander_amp_s: float,
    wander_period_s: float,
    tau_origin_s: float,
    frequency_hz: float,
    phase_cycles: float,
    function: int,
    offset_v: float,
    half_vpp: float,
    u: np.ndarray,
    w: np.ndarray,
    means_v: np.ndarray,
) -> None:
    """Phases `u` (cycles) and W(u) `w` at the n + 1 step boundaries, and the n exact step means `means_v` (V).
    wander_amp_s = e_w P / (2 pi); half_vpp = Vpp / 2 (module docstring)."""
    for j in range(t_bounds_s.shape[0]):
        t = t_bounds_s[j]
        tau = t * (1.0 + e0) + wander_amp_s * (1.0 - math.cos(2 * math.pi * t / wander_period_s))
        uj = frequency_hz * (tau - tau_origin_s) + phase_cycles
        u[j] = uj
        w[j] = _wave_integral(function, uj)
    for k in range(means_v.shape[0]):
        means_v[k] = offset_v + half_vpp * (w[k + 1] - w[k]) / (u[k + 1] - u[k])


@njit(cache=True)
def dither_window_means(
    t_bounds_s: np.ndarray,
    u: np.ndarray,
    w: np.ndarray,
    window_s: float,
    function: int,
    offset_v: float,
    half_vpp: float,
    means_v: np.ndarray,
) -> None:
    """The exact means (V) over the last `window_s` of every step, into `means_v` (module docstring)."""
    for k in range(means_v.shape[0]):
        rate = (u[k + 1] - u[k]) / (t_bounds_s[k + 1] - t_bounds_s[k])
        du = rate * window_s
        w0 = _wave_integral(function, u[k + 1] - du)
        means_v[k] = offset_v + half_vpp * (w[k + 1] - w0) / du
