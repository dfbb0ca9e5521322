"""The per-step equations of `sims.world.World.advance` over a block, in numpy: table rate and angle, chamber lags,
dither means.

Each function is the World's documented equation (sims/world.py) over a block's steps, written into the caller's
arrays (cumulative sums by np.cumsum; the one-pole recursion by scipy.signal.lfilter):

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
* `block_inputs`: one block: `ramp_block` (or a given table profile), `table_block`, `chamber_lags` and
  `dither_grid`.
"""

from __future__ import annotations

import numpy as np
from scipy.signal import lfilter

DITHER_SINE, DITHER_SQUARE, DITHER_TRIANGLE, DITHER_RAMP = 0, 1, 2, 3


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
    r = profile_mid_dps * scale
    if ripple != 0.0:
        mid = angle0_deg + np.cumsum(r) * dt - 0.5 * r * dt
        r *= 1.0 + ripple * np.sin(np.deg2rad(mid + ripple_phase_deg))
    rate_dps[:] = r
    if n > 0:
        angle_deg[0] = angle0_deg
        angle_deg[1:] = np.cumsum(r[:-1]) * dt + angle0_deg


def first_order_lag(u: np.ndarray, y0: float, a: float, y: np.ndarray) -> None:
    """y[0] = y0, y[k+1] = a y[k] + (1 - a) u[k] into `y` (module docstring), 0 < a < 1."""
    y[:] = lfilter([0.0, 1.0 - a], [1.0, -a], u, zi=[y0])[0]


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
    """The air lag behind the setpoint, the measured air (+ disturbance) and the gyro lag behind it
    (`first_order_lag` of each)."""
    first_order_lag(setpoint_c, air0_c, a_air, air_c)
    np.add(air_c, disturbance_c, out=air_measured_c)
    first_order_lag(air_measured_c, gyro0_c, a_gyro, gyro_c)


def wave_integral(fn: int, u: np.ndarray) -> np.ndarray:
    """W(u): the integral of the unit waveform from 0 to u (cycles; sims/world.py docstring)."""
    f = u - np.floor(u)
    if fn == DITHER_SQUARE:
        return np.where(f < 0.5, f, 1.0 - f)
    if fn == DITHER_TRIANGLE:
        return np.where(f < 0.5, -f + 2 * f * f, 3 * (f - 0.5) - 2 * (f * f - 0.25))
    if fn == DITHER_RAMP:
        return f * f - f
    return (1.0 - np.cos(2 * np.pi * u)) / (2 * np.pi)


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
    t = t_bounds_s
    tau = t * (1.0 + e0) + wander_amp_s * (1.0 - np.cos(2 * np.pi * t / wander_period_s))
    u[:] = frequency_hz * (tau - tau_origin_s) + phase_cycles
    w[:] = wave_integral(function, u)
    means_v[:] = offset_v + half_vpp * (w[1:] - w[:-1]) / (u[1:] - u[:-1])


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
    du = (u[1:] - u[:-1]) / (t_bounds_s[1:] - t_bounds_s[:-1]) * window_s
    means_v[:] = offset_v + half_vpp * (w[1:] - wave_integral(function, u[1:] - du)) / du


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
    tau = np.arange(n + 1, dtype=np.float64) * dt
    t_bounds_s[:] = t0_s + tau
    t_start_s[:] = t_bounds_s[:n]
    if rate_mode:
        if r_span_dps == 0.0:
            profile_mid_dps[:] = r0_dps
        else:
            profile_mid_dps[:] = r0_dps + r_sign * np.minimum(accel_dps2 * (tau[:n] + 0.5 * dt), r_span_dps)
    if s_span_c == 0.0:
        setpoint_c[:] = s0_c
    else:
        setpoint_c[:] = s0_c + s_sign * np.minimum(slope_c_per_s * tau[:n], s_span_c)


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
