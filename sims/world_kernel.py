"""Compiled (numba) per-step loops of `sims.world.World.advance`: table rate and angle, chamber lags, dither means.

Each loop is the World's documented equation (sims/world.py) evaluated step by step in one pass (cumulative sums
sequential; the one-pole recursion in scipy.signal.lfilter's direct form II transposed; sines and cosines the C
library's math.sin and math.cos):

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
* `ramp_block`: the block's times and the two ramps, per step k of dt from t0: step starts t0 + k dt and
  boundaries t0 + k dt (k <= n); the table's rate-mode profile at mid-step, r0 + sign(r1 - r0) min(a (k dt +
  dt/2), |r1 - r0|) (r0 where r1 = r0); the chamber controller's setpoint at the step starts,
  s0 + sign(s1 - s0) min(slope k dt, |s1 - s0|) (s0 where s1 = s0).
* `chamber_lags`: the air lag behind the setpoint, the measured air (+ disturbance) and the gyro lag behind it,
  each `first_order_lag`, in one interleaved pass.
* `block_inputs`: one block in one compiled call: `ramp_block` (or a given table profile), `table_block`,
  `chamber_lags` and `dither_grid`.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

DITHER_SINE, DITHER_SQUARE, DITHER_TRIANGLE, DITHER_RAMP = 0, 1, 2, 3


@njit(cache=True, inline="always")
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
def chamber_lags(
    setpoint_c: np.ndarray,
    air0_c: float,
    a_air: float,
    disturbance_c: float,
    gyro0_c: float,
    a_gyro: float,
    air_c: np.ndarray,
    air_measured_c: np.ndarray,
    gyro_c: np.ndarray,
) -> None:
    """The air lag behind the setpoint, the measured air (+ disturbance) and the gyro lag behind it, in one pass:
    `first_order_lag` of each, step k of the gyro's recursion taking the measured air of step k as soon as it
    is formed (the two dependency chains interleave; the operations are those of the separate loops)."""
    b1_air, a1_air = 1.0 - a_air, -a_air
    b1_gyro, a1_gyro = 1.0 - a_gyro, -a_gyro
    z_air, z_gyro = air0_c, gyro0_c
    for k in range(setpoint_c.shape[0]):
        x = setpoint_c[k]
        air = z_air + 0.0 * x
        air_c[k] = air
        z_air = x * b1_air - air * a1_air
        measured = air + disturbance_c
        air_measured_c[k] = measured
        gyro = z_gyro + 0.0 * measured
        gyro_c[k] = gyro
        z_gyro = measured * b1_gyro - gyro * a1_gyro


@njit(cache=True, inline="always")
def _wave_integral(fn: int, u: float) -> float:
    """W(u): the integral of the unit waveform from 0 to u (cycles; sims/world.py docstring)."""
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


@njit(cache=True, inline="always")
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


@njit(cache=True, inline="always")
def ramp_block(
    t0_s: float,
    dt: float,
    rate_mode: bool,
    r0_dps: float,
    r_sign: float,
    accel_dps2: float,
    r_span_dps: float,
    s0_c: float,
    s_sign: float,
    slope_c_per_s: float,
    s_span_c: float,
    t_start_s: np.ndarray,
    t_bounds_s: np.ndarray,
    profile_mid_dps: np.ndarray,
    setpoint_c: np.ndarray,
) -> None:
    """Step starts, boundaries, the rate-mode table profile at mid-step (left alone unless `rate_mode`) and the
    chamber setpoint at the step starts (module docstring); span 0: the ramp has arrived (r1 = r0, s1 = s0)."""
    n = t_start_s.shape[0]
    for k in range(n + 1):
        tau = float(k) * dt
        t_bounds_s[k] = t0_s + tau
        if k == n:
            break
        t_start_s[k] = t0_s + tau
        if rate_mode:
            mid = tau + 0.5 * dt
            profile_mid_dps[k] = r0_dps if r_span_dps == 0.0 else r0_dps + r_sign * min(accel_dps2 * mid, r_span_dps)
        setpoint_c[k] = s0_c if s_span_c == 0.0 else s0_c + s_sign * min(slope_c_per_s * tau, s_span_c)


@njit(cache=True)
def block_inputs(
    table: np.ndarray,
    chamber: np.ndarray,
    dither: np.ndarray,
    rate_mode: bool,
    dither_on: bool,
    function: int,
    t_start_s: np.ndarray,
    t_bounds_s: np.ndarray,
    profile_mid_dps: np.ndarray,
    rate_dps: np.ndarray,
    angle_deg: np.ndarray,
    setpoint_c: np.ndarray,
    air_c: np.ndarray,
    air_measured_c: np.ndarray,
    gyro_c: np.ndarray,
    u: np.ndarray,
    w: np.ndarray,
    dither_v: np.ndarray,
) -> None:
    """One block of World inputs (module docstring) into the output arrays (n steps; t_bounds_s, u, w: n + 1).

    table = [t0, dt, r0, sign(r1 - r0), a, |r1 - r0|, scale, angle0, ripple, ripple phase (deg)];
    chamber = [s0, sign(s1 - s0), slope (degC/s), |s1 - s0|, a_air, air0, disturbance, a_gyro, gyro0];
    dither = [e0, e_w P / (2 pi), P, tau_origin, f, phase (cycles), offset, Vpp / 2] (see `dither_grid`).
    `profile_mid_dps` is an input unless `rate_mode`; without `dither_on` u, w and dither_v are left alone."""
    t0, dt = table[0], table[1]
    ramp_block(
        t0,
        dt,
        rate_mode,
        table[2],
        table[3],
        table[4],
        table[5],
        chamber[0],
        chamber[1],
        chamber[2],
        chamber[3],
        t_start_s,
        t_bounds_s,
        profile_mid_dps,
        setpoint_c,
    )
    table_block(profile_mid_dps, table[6], dt, table[7], table[8], table[9], rate_dps, angle_deg)
    chamber_lags(setpoint_c, chamber[5], chamber[4], chamber[6], chamber[8], chamber[7], air_c, air_measured_c, gyro_c)
    if dither_on:
        dither_grid(
            t_bounds_s,
            dither[0],
            dither[1],
            dither[2],
            dither[3],
            dither[4],
            dither[5],
            function,
            dither[6],
            dither[7],
            u,
            w,
            dither_v,
        )
