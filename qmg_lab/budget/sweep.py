"""Predicted accuracy of a temperature sweep and linearity of a level sweep, from a configuration's parameters.

`sweep_accuracy(cfg)` evaluates, without simulating, what the twin built from `cfg` ([sim], [loops], [plan],
[dither], [device], [lockin]) should give for the CLSF accuracy of a temperature sweep (`qmg-lab analyze`:
`clsf_accuracy_rms_ppm`) and for the RMS nonlinearity of a level sweep (`qmg-lab characterize linearity`:
`nonlinearity_rms_pct_fs`). Equations and their derivations: docs/accuracy-budget.md. In short:

* Accuracy. Pair i (a +Omega / -Omega step pair) gives the true SF change e_i from the table and the CLSF change
  c_i; the accuracy is RMS(c_i - e_i) over pairs 1..n-1. The CLSF ratio rho = beta (1 + delta) carries a relative
  error delta(T); the table measurement a relative error eps; to first order
      c_i - e_i = (delta_0 - delta_i) - (eps_i - eps_0).
  Sources (each evaluated at the gyro temperature of each pair, T(t) from the chamber's two first-order lags):
  - pickoff ratio (CLSF sees G_py/G_px, the true SF does not), three terms:
                    electronics delta = alpha_e (T_fe - T_ref), T_fe the front-end board: T through one more
                    first-order lag tau_fe (frontend_temperature_c); transducer delta = alpha_t (T - T_ref);
                    quadratic delta = alpha_2 (T - T_ref)^2 (each the mean over the pair's windows)
  - mode split:     delta = d^2 P[-s^2 / ((s + g)^2 (s + w_q)(s + w_c))],  d = 2 pi df(T) cos 2 theta_w
                    eps = the slow closed-loop tail the split leaves in each step's window (loop_tail_errors)
  - damping (Q(T), damping-mismatch drift):
                    delta = (1/tau_n - g_y(T)) P[s / ((s + g)(s + w_c))],  g_y = (1/tau)(1 - (dtau/2) cos 2 theta_t)
  - feedthrough:    delta = (kappa c_e sin phi_ft / b(T)) P[s w_c / (s + w_c)],  b = k a / SF_rad(T)
  - forcer cubic:   delta = beta (3 U^2 + u_d^2),  eps = -beta (U^2 + 3 u_d^2)   (incremental vs secant gain)
  - table ripple:   eps = (rho_+ + rho_-)/2,  rho = r (cos(th_a + phi) - cos(th_b + phi)) / (th_b - th_a)
  - table scale error: a constant factor on both steps: cancels in relative changes (term 0 by construction)
  where P[f] = sum_n w_n |H_n|^2 Re f(j n w_d) / sum_n w_n |H_n|^2 Re(1 - T(j n w_d)) projects a transfer function
  onto the dither's triangle (odd harmonics n, w_n = 1/n^4; H the demodulator filter, T = w_c/(s + w_c) the rate
  loop's complementary sensitivity, w_c and w_q the rate and quadrature loops' actual bandwidths at T: the design
  bandwidth times the plant's actual gain over its nominal one, loop_bandwidths_rad_s).
* Nonlinearity. Level j at Omega_j: the rate output O_j = SF Omega_j (1 + e)(1 + rho_j)(1 - beta (U_j^2 +
  3 u_d^2)); a straight-line fit over the levels, RMS residual / (SF FS) in % (qmg_lab/analysis/characterize.py).

Why one module of this length: each accuracy and nonlinearity term is derived from the same sense-axis
model and summed signed, pair by pair; split apart, a term would lose the sum it belongs to.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.linalg import expm

from qmg_lab.analysis.reductions import analysis_settle_s, rate_pairs
from qmg_lab.campaign.plan import Step, build_plan
from qmg_lab.config.rate_loop import config_quadrature_loop, config_rate_loop, rate_loop_t
from qmg_lab.config.schema import Config

PPM = 1e6
DETERMINISTIC_OFF: dict[str, float] = {
    "pickoff_electronics_tempco_ppm_per_c": 0.0,
    "pickoff_transducer_tempco_ppm_per_c": 0.0,
    "pickoff_ratio_tempco2_ppm_per_c2": 0.0,
    "q_tempco_ppm_per_c": 0.0,
    "damping_mismatch_tempco_per_c": 0.0,
    "freq_mismatch_hz": 0.0,
    "freq_mismatch_tempco_hz_per_c": 0.0,
    "forcer_bias_v": 0.0,
    "feedthrough_v_per_v": 0.0,
    "table_rate_ripple_ppm": 0.0,
}
"""[sim] values that switch every deterministic accuracy and linearity source of the twin off (the budget is then 0)."""


def sim_lines(values: dict[str, float]) -> str:
    """[sim] key = value lines (TOML) for a mapping of [sim] overrides."""
    return "".join(f"{k} = {v!r}\n" for k, v in values.items())


DEG_PER_RAD = 180.0 / math.pi
HARMONICS = (1, 3, 5, 7, 9, 11, 13, 15)  # odd harmonics of the square dither used in the projections


@dataclass(frozen=True)
class SweepAccuracy:
    """Predicted sweep accuracy (ppm) and level-sweep nonlinearity (% FS), per source and total.

    terms_ppm[k]: RMS over pairs 1..n-1 of source k's c_i - e_i alone; total_ppm: RMS of their sum (the sources
    add with their signs, so the total is not their root-sum-square). pair_errors_ppm: the predicted c_i - e_i of
    every pair (pair 0 is the reference, 0 by construction). nonlinearity_terms_pct_fs[k]: the RMS nonlinearity of
    source k alone; nonlinearity_rms_pct_fs: all together.
    """

    terms_ppm: dict[str, float]
    total_ppm: float
    total_mean_removed_ppm: float
    pair_errors_ppm: tuple[float, ...]
    pair_temperatures_c: tuple[float, ...]
    nonlinearity_terms_pct_fs: dict[str, float]
    nonlinearity_rms_pct_fs: float
    linearity_rates_dps: tuple[float, ...] = field(default=())
    table_errors_ppm: tuple[float, ...] = field(default=())  # e_i - t_i: the table steps against the true SF

    @property
    def dominant_accuracy_source(self) -> str:
        return max(self.terms_ppm, key=lambda k: abs(self.terms_ppm[k]))

    @property
    def dominant_nonlinearity_source(self) -> str:
        return max(self.nonlinearity_terms_pct_fs, key=lambda k: abs(self.nonlinearity_terms_pct_fs[k]))

    def to_json(self) -> dict[str, Any]:
        """Plain JSON types (the `accuracy` key of `qmg-lab budget --json`)."""
        return {
            "terms_ppm": dict(self.terms_ppm),
            "total_ppm": self.total_ppm,
            "total_mean_removed_ppm": self.total_mean_removed_ppm,
            "dominant_accuracy_source": self.dominant_accuracy_source,
            "pair_errors_ppm": list(self.pair_errors_ppm),
            "pair_temperatures_c": list(self.pair_temperatures_c),
            "nonlinearity_terms_pct_fs": dict(self.nonlinearity_terms_pct_fs),
            "nonlinearity_rms_pct_fs": self.nonlinearity_rms_pct_fs,
            "dominant_nonlinearity_source": self.dominant_nonlinearity_source,
            "linearity_rates_dps": list(self.linearity_rates_dps),
            "table_errors_ppm": list(self.table_errors_ppm),
        }


# ------------------------------------------------------------------------------------------------ timeline


@dataclass(frozen=True)
class _Window:
    """One analysed table step: commanded rate, its analysis window (s) and the table angles (deg) it spans."""

    index: int
    rate_dps: float
    t0_s: float
    t1_s: float
    angle0_deg: float
    angle1_deg: float


def _windows(cfg: Config, steps: list[Step]) -> list[_Window]:
    """Nominal step times (steps back to back from t = 0) and the table angle: at each rate/level step the table
    accelerates at the plan's acceleration from the previous rate to the new one, then holds it."""
    accel = cfg.plan.table_accel_dps2
    settle = analysis_settle_s(cfg)
    t, angle, rate = 0.0, 0.0, 0.0
    out = []
    for st in steps:
        new = st.table_rate_dps if st.kind in ("rate", "level") else (0.0 if st.kind == "return" else rate)
        t_ramp = abs(new - rate) / accel
        ramp_angle = 0.5 * (rate + new) * min(t_ramp, st.duration_s)

        def angle_at(tau: float, a0: float = angle, r0: float = rate, r1: float = new, tr: float = t_ramp) -> float:
            if tau <= tr:
                return a0 + r0 * tau + 0.5 * math.copysign(accel, r1 - r0) * tau * tau
            return a0 + 0.5 * (r0 + r1) * tr + r1 * (tau - tr)

        if st.kind in ("rate", "level") and settle < st.duration_s:
            out.append(_Window(st.index, new, t + settle, t + st.duration_s, angle_at(settle), angle_at(st.duration_s)))
        angle = angle_at(st.duration_s) if t_ramp < st.duration_s else angle + ramp_angle
        rate = new
        t += st.duration_s
    return out


def _ripple_mean(cfg: Config, w: _Window) -> float:
    """Mean of r sin(theta + phi_r) over the window's angle span (exact for a constant rate)."""
    s = cfg.sim
    r = s.table_rate_ripple_ppm / PPM
    a = math.radians(w.angle0_deg + s.table_ripple_phase_deg)
    b = math.radians(w.angle1_deg + s.table_ripple_phase_deg)
    if r == 0.0:
        return 0.0
    if abs(b - a) < 1e-9:
        return r * math.sin(a)
    return r * (math.cos(a) - math.cos(b)) / (b - a)


def gyro_temperature_c(cfg: Config, t_s: np.ndarray, ramp_start_s: float) -> np.ndarray:
    """Gyro temperature of the sweep: the chamber setpoint ramps from plan.chamber_start_c to chamber_end_c at the
    plan's rate from ramp_start_s; the air follows with tau_a, the gyro with tau_g (two first-order lags).
    Response of the two lags to a unit ramp from t = 0: R(t) = t - (tau_a + tau_g) + (tau_a^2 e^{-t/tau_a} -
    tau_g^2 e^{-t/tau_g}) / (tau_a - tau_g); the finite ramp is R(t - t_r) - R(t - t_e)."""
    p, s = cfg.plan, cfg.sim
    ta, tg = s.chamber_time_constant_s, s.thermal_lag_s
    if abs(ta - tg) < 1e-6 * max(ta, tg):
        tg = tg * (1.0 + 1e-6)
    slope = math.copysign(p.chamber_ramp_c_per_min / 60.0, p.chamber_end_c - p.chamber_start_c)
    t_end = ramp_start_s + abs(p.chamber_end_c - p.chamber_start_c) / (p.chamber_ramp_c_per_min / 60.0)

    def ramp(t: np.ndarray) -> np.ndarray:
        tt = np.maximum(t, 0.0)
        return tt - (ta + tg) + (ta * ta * np.exp(-tt / ta) - tg * tg * np.exp(-tt / tg)) / (ta - tg)

    return p.chamber_start_c + slope * (ramp(t_s - ramp_start_s) - ramp(t_s - t_end))


# ------------------------------------------------------------------------------------------------ projections


def _demod_h2(cfg: Config, w: float) -> float:
    """|H(jw)|^2 of the demodulator filter, order n of time constant tc."""
    return (1.0 + (w * cfg.lockin.demod_timeconstant_s) ** 2) ** (-cfg.lockin.demod_order)


def loop_bandwidths_rad_s(cfg: Config, temp_c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The rate and quadrature loops' actual loop gains w_c, w_q at T: the design's (b |P| of
    config.rate_loop.rate_loop_design) times the plant's actual gain over the nominal one the
    PIs were designed on, b/b_nom = (k/k_nom)(SF_nom/SF(T)) G_py(T)."""
    s, d = cfg.sim, cfg.device
    dt = temp_c - s.reference_temperature_c
    g_py = 1.0 + pickoff_linear_ppm_per_c(cfg) * 1e-6 * dt + s.pickoff_ratio_tempco2_ppm_per_c2 * 1e-6 * dt * dt
    ratio = (s.angular_gain / d.angular_gain) * (d.sf_nominal_v_per_dps * DEG_PER_RAD / _sf_rad(cfg, temp_c)) * g_py
    return config_rate_loop(cfg).gain_rad_s * ratio, config_quadrature_loop(cfg).gain_rad_s * ratio


def pickoff_linear_ppm_per_c(cfg: Config) -> float:
    """The pickoff ratio's linear tempco in a steady state (the board at the die temperature): alpha_e + alpha_t."""
    return cfg.sim.pickoff_electronics_tempco_ppm_per_c + cfg.sim.pickoff_transducer_tempco_ppm_per_c


def frontend_temperature_c(cfg: Config, t_s: np.ndarray, ramp_start_s: float, grid_step_s: float = 1.0) -> np.ndarray:
    """The front-end board temperature: the gyro temperature (gyro_temperature_c) through a first-order lag
    tau_fe = [sim] frontend_thermal_tau_s, in equilibrium at t = 0. Stepped exactly for T linear between the points
    of a grid_step_s grid (first-order hold), T_fe <- T_b - a (T_b - T_fe) ... (a = e^(-h/tau)), then interpolated."""
    tau = cfg.sim.frontend_thermal_tau_s
    if tau <= 0.0:
        return gyro_temperature_c(cfg, t_s, ramp_start_s)
    t_end = float(np.max(t_s)) if np.size(t_s) else 0.0
    grid = np.arange(0.0, t_end + 2.0 * grid_step_s, grid_step_s)
    temp = gyro_temperature_c(cfg, grid, ramp_start_s)
    a = math.exp(-grid_step_s / tau)
    ramp_gain = 1.0 - tau * (1.0 - a) / grid_step_s  # response to the ramp part of a first-order hold
    out = np.empty_like(temp)
    out[0] = temp[0]
    for k in range(1, temp.shape[0]):
        out[k] = a * out[k - 1] + (1.0 - a) * temp[k - 1] + ramp_gain * (temp[k] - temp[k - 1])
    return np.interp(t_s, grid, out)


def projection(cfg: Config, f: Any, wc: float) -> float:
    """P[f]: the in-phase part of f(s) m_d on the dither's triangle m_d, over the triangle's projection of the
    loop's forcer input m = (1 - T) m_d, T the rate loop's closed loop at loop gain w_c (config.rate_loop.rate_loop_t:
    w_c/(s + w_c) for the zero-on-pole design); f is called with s = j n w_d."""
    wd = 2.0 * math.pi * cfg.dither.frequency_hz
    loop = config_rate_loop(cfg)
    gain_scale = wc / loop.gain_rad_s
    num = den = 0.0
    for n in HARMONICS:
        s = 1j * n * wd
        weight = _demod_h2(cfg, n * wd) / n**4
        num += weight * complex(f(s)).real
        den += weight * (1.0 - complex(rate_loop_t(loop, 1.0 / cfg.device.tau_s, s, gain_scale))).real
    return num / den


# ------------------------------------------------------------------------------------------------ the sources


def _sf_rad(cfg: Config, temp_c: np.ndarray) -> np.ndarray:
    """True SF in V per rad/s at T: SF_ref (omega(T)/omega0) / G_f(T)."""
    s = cfg.sim
    dt = temp_c - s.reference_temperature_c
    return (
        s.sf_true_v_per_dps
        * DEG_PER_RAD
        * (1.0 + s.frequency_tempco_ppm_per_c * 1e-6 * dt)
        / (1.0 + s.forcer_tempco_ppm_per_c * 1e-6 * dt)
    )


def forcer_cubic_per_v2(cfg: Config) -> float:
    """beta = c_e^2 r / (2 V_p^2 (1 - r)), r = 2 k a V_p / (c_e SF_rad g omega0) (sims/gyro_params.py)."""
    s = cfg.sim
    if s.forcer_bias_v == 0.0 or s.forcer_electrode_v_per_v == 0.0:
        return 0.0
    w0 = 2.0 * math.pi * s.f0_hz
    r = (
        2.0
        * s.angular_gain
        * s.drive_amplitude_um
        * 1e-6
        * s.forcer_bias_v
        / (s.forcer_electrode_v_per_v * s.sf_true_v_per_dps * DEG_PER_RAD * s.forcer_gap_um * 1e-6 * w0)
    )
    return s.forcer_electrode_v_per_v**2 * r / (2.0 * s.forcer_bias_v**2 * (1.0 - r))


def sense_axis(cfg: Config, temp_c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The sense mode at T: its damping rate g_y = (omega(T)/2Q(T))(1 - (dmis(T)/2) cos 2 theta_tau) (1/s) and its
    detuning from the PLL (locked on the drive mode) d = 2 pi Delta_f(T) cos 2 theta_omega (rad/s)."""
    s = cfg.sim
    dt = temp_c - s.reference_temperature_c
    w = 2.0 * math.pi * s.f0_hz * (1.0 + s.frequency_tempco_ppm_per_c * 1e-6 * dt)
    inv_tau = w / (2.0 * s.q_factor * (1.0 + s.q_tempco_ppm_per_c * 1e-6 * dt))
    dmis = s.damping_mismatch + s.damping_mismatch_tempco_per_c * dt
    gamma_y = inv_tau * (1.0 - 0.5 * dmis * math.cos(2.0 * math.radians(s.damping_axis_deg)))
    split = 2.0 * math.pi * (s.freq_mismatch_hz + s.freq_mismatch_tempco_hz_per_c * dt)
    return gamma_y, split * math.cos(2.0 * math.radians(s.stiffness_axis_deg))


def _clsf_deltas(cfg: Config, temp_c: np.ndarray, rate_dps: float) -> dict[str, np.ndarray]:
    """Relative error delta of the CLSF ratio rho at each temperature, per source (table step at rate_dps)."""
    s = cfg.sim
    wc_t, wq_t = loop_bandwidths_rad_s(cfg, temp_c)
    gamma_y, split = sense_axis(cfg, temp_c)
    g0 = 2.0 * math.pi * s.f0_hz / (2.0 * s.q_factor)
    p_split = np.array(
        [
            projection(cfg, lambda z, c=c, q=q: -(z * z) / ((z + g0) ** 2 * (z + q) * (z + c)), c)
            for c, q in zip(wc_t, wq_t, strict=True)
        ]
    )
    p_damp = np.array([projection(cfg, lambda z, c=c: z / ((z + g0) * (z + c)), c) for c in wc_t])
    p_ft = np.array([projection(cfg, lambda z, c=c: z * c / (z + c), c) for c in wc_t])
    tau_n = cfg.device.tau_s
    a = math.sqrt(2.0) * cfg.device.drive_amplitude_vrms
    b = s.angular_gain * a / _sf_rad(cfg, temp_c)
    kappa_x = s.feedthrough_v_per_v * s.forcer_electrode_v_per_v * math.sin(math.radians(s.feedthrough_phase_deg))
    beta = forcer_cubic_per_v2(cfg)
    u_op = rate_dps * _sf_rad(cfg, temp_c) / DEG_PER_RAD
    u_d = cfg.dither.virtual_rate_dps * cfg.device.sf_nominal_v_per_dps
    return {
        "mode_split": split**2 * p_split,
        "damping": (1.0 / tau_n - gamma_y) * p_damp,
        "feedthrough": kappa_x / b * p_ft,
        "forcer_cubic": beta * (3.0 * u_op**2 + u_d**2),
    }


def pickoff_deltas(cfg: Config, t_die: np.ndarray, t_fe: np.ndarray) -> dict[str, np.ndarray]:
    """The pickoff ratio's three parts of the CLSF error delta per pair: the mean over each row's samples (a pair's
    windows) of alpha_e dT_fe, alpha_t dT and alpha_2 dT^2 (dT = T - T_ref at the die, dT_fe at the board)."""
    s = cfg.sim
    d = t_die - s.reference_temperature_c
    d_fe = t_fe - s.reference_temperature_c
    return {
        "pickoff_electronics": s.pickoff_electronics_tempco_ppm_per_c * 1e-6 * d_fe.mean(axis=-1),
        "pickoff_transducer": s.pickoff_transducer_tempco_ppm_per_c * 1e-6 * d.mean(axis=-1),
        "pickoff_quadratic": s.pickoff_ratio_tempco2_ppm_per_c2 * 1e-6 * (d * d).mean(axis=-1),
    }


def loop_tail_errors(
    cfg: Config,
    rates_dps: list[float],
    *,
    split_rad_s: np.ndarray,
    gamma_y: np.ndarray,
    wc_rad_s: np.ndarray,
    wq_rad_s: np.ndarray,
) -> np.ndarray:
    """Relative error of each step's window-mean rate output from the slow closed-loop tail (one per step).

    Linear model of the FTR sense axis under its two PI loops (zeros z, z_q = I/P of campaign.loops.
    rate_loop_design):
        c' = -g c + d s - w + b u_r,   b u_r = -w_c (c + z I_c),  I_c' = c
        s' = -g s - d c + b u_q,       b u_q = -w_q (s + z_q I_s),  I_s' = s
    w = k a Omega (the Coriolis term, unit per step rate), g the sense damping g_y(T), d the sense detuning. With
    the zero-on-pole design, g = z and d = 0, the PI zero cancels the resonator's pole and the output is b u_r = w
    after a fast 2 Hz transient; a mismatch (g != z) or a split (d != 0) leaves a slow mode near -z in the output,
    which the analysis window [settle, dwell] of each step averages. The critically damped design has no slow
    mode: its tail is gone before the window opens. Exact: x(t) = x_ss + e^{At}(x0 - x_ss) step by step
    (one A per step, from that step's d and g), window mean = y_ss + C A^-1 (e^{A t1} - e^{A t0})(x0 - x_ss)/(t1 -
    t0). Returned: mean b u_r - w for each step of rates_dps (the plan's table steps, back to back), in the units
    of rates_dps (w is taken as the step's rate: the tail is linear in the steps).
    """
    z = config_rate_loop(cfg).zero_rad_s
    zq = config_quadrature_loop(cfg).zero_rad_s
    t0, t1 = analysis_settle_s(cfg), cfg.plan.dwell_s
    x = np.zeros(4)
    out = np.empty(len(rates_dps))
    for k, w in enumerate(rates_dps):
        g, d = float(gamma_y[k]), float(split_rad_s[k])
        wc, wq = float(wc_rad_s[k]), float(wq_rad_s[k])
        c_out = np.array([-wc, 0.0, -wc * z, 0.0])
        a = np.array(
            [
                [-g - wc, d, -wc * z, 0.0],
                [-d, -g - wq, 0.0, -wq * zq],
                [1.0, 0.0, 0.0, 0.0],
                [0.0, 1.0, 0.0, 0.0],
            ]
        )
        x_ss = np.linalg.solve(a, np.array([w, 0.0, 0.0, 0.0]))  # A x_ss + B w = 0, B = [-1, 0, 0, 0]
        dx = x - x_ss
        e0, e1 = expm(a * t0), expm(a * t1)
        mean = float(c_out @ x_ss) + float(c_out @ np.linalg.solve(a, (e1 - e0) @ dx)) / (t1 - t0)
        out[k] = mean - w
        x = x_ss + e1 @ dx
    return out


def sweep_accuracy(cfg: Config) -> SweepAccuracy:
    """The budget of a configuration (module docstring; docs/accuracy-budget.md)."""
    acc_terms, pair_err, pair_t, table_err = _accuracy(cfg)
    nl_terms, nl_total, rates = _nonlinearity(cfg)
    total = pair_err.sum(axis=0) if pair_err.size else np.zeros(0)
    tail = total[1:]
    rms = float(np.sqrt(np.mean(tail**2))) if tail.size else float("nan")
    rms_mr = float(np.sqrt(np.mean((tail - tail.mean()) ** 2))) if tail.size else float("nan")
    return SweepAccuracy(
        terms_ppm=acc_terms,
        total_ppm=rms,
        total_mean_removed_ppm=rms_mr,
        pair_errors_ppm=tuple(float(x) for x in total),
        pair_temperatures_c=tuple(float(x) for x in pair_t),
        table_errors_ppm=tuple(float(x) for x in table_err),
        nonlinearity_terms_pct_fs=nl_terms,
        nonlinearity_rms_pct_fs=nl_total,
        linearity_rates_dps=rates,
    )


PICKOFF_SOURCES = ("pickoff_electronics", "pickoff_transducer", "pickoff_quadratic")
ACCURACY_SOURCES = (*PICKOFF_SOURCES, "mode_split", "damping", "feedthrough", "forcer_cubic", "table_ripple")


@dataclass(frozen=True)
class PairErrors:
    """The predicted c_i - e_i of every step pair per source (rows in ACCURACY_SOURCES order, ppm), each pair's
    analysis windows [(t0, t1) of the + step, of the - step] (s from the plan's start) and the ramp's start (s)."""

    rows_ppm: np.ndarray
    windows_s: list[list[tuple[float, float]]]
    ramp_start_s: float
    temperatures_c: np.ndarray
    table_ppm: np.ndarray  # the table steps' own error against the true SF (eps_i - eps_0 summed over the sources)


def pair_errors(cfg: Config) -> PairErrors:
    """The per-source pair errors of a temperature sweep (module docstring), with the windows they are taken over."""
    sweep = cfg.model_copy(update={"campaign": cfg.campaign.model_copy(update={"kind": "temperature_sweep"})})
    steps = build_plan(sweep)
    wins = {w.index: w for w in _windows(sweep, steps)}
    starts = np.cumsum([0.0] + [st.duration_s for st in steps])
    ramp_start = next((float(starts[k]) for k, st in enumerate(steps) if st.kind == "rate"), 0.0)
    pairs = [(wins[k], wins[k + 1]) for k in rate_pairs({k: (steps[k].kind, w.rate_dps) for k, w in wins.items()})]
    if not pairs:
        return PairErrors(np.zeros((len(ACCURACY_SOURCES), 0)), [], ramp_start, np.zeros(0), np.zeros(0))
    grids = np.array(
        [np.concatenate([np.linspace(wp.t0_s, wp.t1_s, 64), np.linspace(wm.t0_s, wm.t1_s, 64)]) for wp, wm in pairs]
    )
    t_die = gyro_temperature_c(sweep, grids, ramp_start)
    t_fe = frontend_temperature_c(sweep, grids.ravel(), ramp_start).reshape(grids.shape)
    temp = t_die.mean(axis=1)
    rate = pairs[0][0].rate_dps
    deltas = _clsf_deltas(sweep, temp, rate)
    deltas.update(pickoff_deltas(sweep, t_die, t_fe))
    u_d = sweep.dither.virtual_rate_dps * sweep.device.sf_nominal_v_per_dps
    u_op = rate * _sf_rad(sweep, temp) / DEG_PER_RAD
    tail_split, tail_damp = _tails(sweep, steps, pairs, ramp_start)
    eps = {
        "forcer_cubic": -forcer_cubic_per_v2(sweep) * (u_op**2 + 3.0 * u_d**2),
        "table_ripple": np.array([0.5 * (_ripple_mean(sweep, wp) + _ripple_mean(sweep, wm)) for wp, wm in pairs]),
        "mode_split": tail_split,
        "damping": tail_damp,
    }
    rows = []
    table = np.zeros_like(temp)
    for name in ACCURACY_SOURCES:
        d = deltas.get(name, np.zeros_like(temp))
        e = eps.get(name, np.zeros_like(temp))
        rows.append(((d[0] - d) - (e - e[0])) * PPM)
        table = table + (e - e[0]) * PPM
    windows = [[(wp.t0_s, wp.t1_s), (wm.t0_s, wm.t1_s)] for wp, wm in pairs]
    return PairErrors(np.array(rows), windows, ramp_start, temp, table)


def _accuracy(cfg: Config) -> tuple[dict[str, float], np.ndarray, np.ndarray, np.ndarray]:
    """Per-source RMS (ppm), the per-source pair errors (sources x pairs, ppm), the pairs' gyro temperatures and the
    table steps' own error against the true SF (ppm)."""
    pe = pair_errors(cfg)
    err, temp = pe.rows_ppm, pe.temperatures_c
    terms = {
        n: float(np.sqrt(np.mean(r[1:] ** 2))) if r.size > 1 else float("nan")
        for n, r in zip(ACCURACY_SOURCES, err, strict=True)
    }
    return terms, err, temp, pe.table_ppm


def _tails(
    cfg: Config, steps: list[Step], pairs: list[tuple[_Window, _Window]], ramp_start: float
) -> tuple[np.ndarray, np.ndarray]:
    """The table-measured SF error of each pair from the loop tail (loop_tail_errors): the split's part (tail with
    the split minus tail without) and the damping mismatch's part (tail without the split)."""
    rate_steps = [st for st in steps if st.kind == "rate"]
    starts = np.cumsum([0.0] + [st.duration_s for st in steps])
    t_mid = np.array([starts[st.index] + 0.5 * st.duration_s for st in rate_steps])
    temp = gyro_temperature_c(cfg, t_mid, ramp_start)
    gamma_y, split = sense_axis(cfg, temp)
    rates = [st.table_rate_dps for st in rate_steps]
    wc, wq = loop_bandwidths_rad_s(cfg, temp)
    with_split = loop_tail_errors(cfg, rates, split_rad_s=split, gamma_y=gamma_y, wc_rad_s=wc, wq_rad_s=wq)
    without = loop_tail_errors(cfg, rates, split_rad_s=np.zeros_like(split), gamma_y=gamma_y, wc_rad_s=wc, wq_rad_s=wq)
    pos = {st.index: k for k, st in enumerate(rate_steps)}

    def per_pair(err: np.ndarray) -> np.ndarray:  # SF error of the pair: (a+ - a-) / (Omega+ - Omega-)
        return np.array([(err[pos[wp.index]] - err[pos[wm.index]]) / (wp.rate_dps - wm.rate_dps) for wp, wm in pairs])

    return per_pair(with_split) - per_pair(without), per_pair(without)


NONLINEARITY_SOURCES = ("forcer_cubic", "table_ripple", "loop_tail")


def _level_tails(cfg: Config, steps: list[Step], wins: list[_Window]) -> np.ndarray:
    """Loop-tail error (deg/s) of each level's window mean at the plan's start temperature (loop_tail_errors)."""
    t = np.full(len(steps), cfg.plan.chamber_start_c)
    gamma_y, split = sense_axis(cfg, t)
    wc, wq = loop_bandwidths_rad_s(cfg, t)
    moving = [st for st in steps if st.kind in ("rate", "level", "return")]
    rates = [st.table_rate_dps if st.kind != "return" else 0.0 for st in moving]
    k = len(moving)
    err = loop_tail_errors(cfg, rates, split_rad_s=split[:k], gamma_y=gamma_y[:k], wc_rad_s=wc[:k], wq_rad_s=wq[:k])
    pos = {st.index: i for i, st in enumerate(moving)}
    return np.array([err[pos[w_.index]] for w_ in wins])


def _nonlinearity(cfg: Config) -> tuple[dict[str, float], float, tuple[float, ...]]:
    """RMS nonlinearity (% FS) of the level sweep per source and with all sources, from a straight-line fit."""
    lin = cfg.model_copy(update={"campaign": cfg.campaign.model_copy(update={"kind": "linearity"})})
    steps = build_plan(lin)
    wins = [w for w in _windows(lin, steps) if steps[w.index].kind == "level"]
    if len({w.rate_dps for w in wins}) < 2:
        return dict.fromkeys(NONLINEARITY_SOURCES, float("nan")), float("nan"), ()
    s = lin.sim
    rates = np.array([w.rate_dps for w in wins])
    sf = _sf_rad(lin, np.array([lin.plan.chamber_start_c]))[0] / DEG_PER_RAD  # V per deg/s at the test temperature
    beta = forcer_cubic_per_v2(lin)
    u_d = lin.dither.virtual_rate_dps * lin.device.sf_nominal_v_per_dps if lin.clsf.mode != "off" else 0.0
    u = rates * sf
    scale = 1.0 + s.table_rate_scale_error_ppm / PPM
    errors = {  # each source's error of the level means, deg/s of input rate
        "forcer_cubic": -rates * beta * (u * u + 3.0 * u_d * u_d),
        "table_ripple": rates * np.array([_ripple_mean(lin, w) for w in wins]),
        "loop_tail": _level_tails(lin, steps, wins),
    }

    def rms_pct(err: np.ndarray) -> float:
        out = sf * scale * (rates + err)
        slope, icpt = np.polyfit(rates, out, 1)
        res = out - (slope * rates + icpt)
        return float(100.0 * np.sqrt(np.mean(res**2)) / abs(slope * np.max(np.abs(rates))))

    terms = {k: rms_pct(e) for k, e in errors.items()}
    total = rms_pct(np.sum(np.array(list(errors.values())), axis=0))
    return terms, total, tuple(float(r) for r in rates)
