"""Compiled (numba) step kernels of the QMG twin: the averaged slow-variable model and the carrier-level model,
sharing one lock-in controller step (demod low-pass, PLL, AGC, rate and quadrature PIDs).

Slow-variable plant (docs/physics.md sections 1-3), per axis Z = C + iS, reference phase rate omega_r (PLL):

    dZ/dt = -M Z + u,   M = Gamma + i Xi + k Omega J,   u = (-F_s + i F_c) / (2 omega_r)
    Gamma = (1/tau) I + (Delta(1/tau)/2) [[cos 2t_t, sin 2t_t], [sin 2t_t, -cos 2t_t]]
    Xi = (K - omega_r^2 I)/(2 omega_r),  K = omega^2 I + omega Delta_omega [[cos 2t_w, sin 2t_w], [., -cos 2t_w]]

Exact zero-order-hold step (inputs held over dt): write M = sigma I + N with N traceless, so N^2 = mu^2 I
(mu^2 = -det N). Then exp(-M dt) = e^{-sigma dt} (cosh(mu dt) I - sinh(mu dt)/mu N) and the input term is
M^{-1}(I - exp(-M dt)) u with M^{-1} = (sigma I - N)/(sigma^2 - mu^2). cosh and sinh(x)/x are even in mu, so
they are evaluated from mu^2 (series for |mu dt|^2 < 1e-2, complex sqrt otherwise): no matrix exponential and
no numerical integration; omega_r (PLL), Omega (table + bias) and T may change every step.

Carrier-level plant: q'' + D q' + K q + 2 k Omega J q' = f on state [x, y, x'/omega0, y'/omega0], exact ZOH
step Phi = expm(A dt) and input matrix int_0^dt expm(A s) ds B from their Taylor series (||A dt|| ~ 2 pi / 32,
13 terms: truncation < 1e-17; recomputed when T or Omega change). The forces f = F_c cos(phi) + F_s sin(phi)
are evaluated at mid-sample phase and divided by sinc(omega_r dt / 2) (DAC half-sample and sinc compensation);
one-cycle boxcar I/Q demodulation
X + iY = sqrt(2) G mean(q e^{-i phi}) gives the same demod convention X + iY = G (C - iS)/sqrt(2).

Controller (both models, once per demod sample of length dt_c):
* demod low-pass: the HF2's cascade of `order` identical first-order sections, H(s) = 1/(1 + s tc)^order,
  discretized exactly for a raw demod value that is linear between samples (first-order hold). With x = dt_c/tc,
  the chain's state y_1..y_n (a Jordan block) advances as
      y_m+ = sum_{j<=m} e^-x x^(m-j)/(m-j)! y_j + u- S_m + (u+ - u-) R_m,
      S_m = 1 - e^-x sum_{i<m} x^i/i!,   R_m = 1 - m/x + (e^-x/x) sum_{i<m} (m-i) x^i/i!
  (S_m: the m-th section's step response, R_m: its ramp response / dt_c). For one section this is the familiar
  y+ = a y + (1-a) u- + (u+ - u-)(1 - tc (1-a)/dt_c), a = e^-x. The loop delay is one more first-order section
  with tc = loop delay (a lag with the same low-frequency phase).
* Rate output: the HF2's PID updates far faster than the demod stream, so the AuxOut voltage V_r(t) is
  continuous. The twin makes it piecewise linear between its sample instants: V_r(t_i) = v_(i-1) (the PID value
  computed at the previous sample), and the forcer sees its exact mean over each step, (v_(i-2) + v_(i-1))/2.
  (The slow-variable plant only integrates the input over a step: the shape within the step enters as
  |M| dt / 12 ~ 1e-7 of it.)
* PLL: e = atan2(Y_d, X_d)[deg] - setpoint (wrapped), f = center + p e + i int(e) dt, clamped to center +- range.
* PIDs: e = setpoint - input, out = center + p e + i int(e) dt + d de/dt, clamped to center +- range; the
  integrator does not integrate while the output is clamped (anti-windup); disabled: out = center, int = 0.
  AGC input R_d = |X_d + iY_d|; rate input X_s; quadrature input Y_s.
Forces: F_xs = -K_dx V_d; F_ys = -K_f G_f(T) g (V_r + V_dither + v_n) ; F_yc = +K_f G_f(T) V_q; ARW is a white
force F_n = 2 omega0 k a0 Omega_n on both sense components (Omega_n per-sample sigma N/sqrt(dt)); v_n is the
forcer-path voltage noise at the summing node (after the recording tees, so the AuxIns do not see it), white of
one-sided density e_f: its mean over a step has sigma e_f/sqrt(2 dt). It acts on the same in-phase sense component
as the ARW force and is independent of it, so the two share one normal draw of the combined sigma
sqrt(sigma_arw^2 + sigma_f^2) (exact in distribution; one draw fewer per step; with e_f = 0 the draws are those
of a twin without it). The rate and quadrature PID outputs leave
through the AuxOut DACs: rounded to the DAC step (P_AOLSB) after each controller step, so the forcer, the next
step's PID state S_VRP and the recorded AuxOut all carry the quantised value (the PID's integrator does not).
True SF per step: sf_true (omega_x/omega0)(a/a0)/(G_f g) with a = |C_x + iS_x| the drive amplitude of the step
(equal to sqrt2 R_setpoint once the AGC has settled; during the slow AGC transient after a rate step, caused by
the Coriolis load k Omega c_y on the drive, the rate output follows the actual amplitude).
Bias: a sum of first-order Gauss-Markov rates x_j <- a_j x_j + b_j w, updated every `gm_steps` steps and held.

The kernels are compiled with nogil=True: they touch only the arrays they are given (the noise stream,
sims/noise.py, draws each block's normals in the caller's thread before the call), so another thread of the
process (the run file's writer) runs beside them.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

# ---- parameter vector P
P_W0, P_Q, P_DMIS, P_C2T, P_S2T, P_DW, P_C2W, P_S2W, P_K, P_ARW, P_PICK = 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10
P_AF, P_AW, P_AP, P_TREF, P_DELAY, P_KD, P_KF, P_A0, P_DT, P_GMSTEPS, P_SF, P_R0 = (
    11,
    12,
    13,
    14,
    15,
    16,
    17,
    18,
    19,
    20,
    21,
    22,
)
# deterministic non-idealities (docs/accuracy-budget.md): Q tempco, damping-mismatch tempco, split tempco (rad/s
# per degC), forcer cubic beta (1/V^2), feedthrough into the sense C and S slow variables per command volt,
# 2-omega ripple switch (carrier model)
P_AQ, P_ADM, P_ADW, P_BETA, P_FTC, P_FTS, P_RIP = 23, 24, 25, 26, 27, 28, 29
P_FNOISE, P_AOLSB = 30, 31  # forcer-path voltage noise (V/sqrt(Hz), one-sided); AuxOut DAC step (V, 0 = ideal)
# pickoff ratio (P_AP: the transducer's linear part at the die): the front end's linear part at the board
# temperature, the quadratic part at the die (1/degC^2), the board's lag factor per output step e^(-dt/tau_fe)
P_AE, P_A2, P_FEA = 32, 33, 34
N_PARAMS = 35

# ---- loop vector L (sims/gyro_params.pack_loops)
L_PLL = 0  # enabled, p, i, setpoint, center, range
L_AGC = 6  # enabled, p, i, d, setpoint, center, range
L_RATE = 13
L_QUAD = 20
L_GAIN, L_TC, L_ORDER = 27, 28, 29

# ---- state vector S
S_CX, S_SX, S_CY, S_SY = 0, 1, 2, 3
S_FREF, S_PLLI, S_AGCI, S_RATEI, S_QUADI, S_AGCE, S_RATEE, S_QUADE = 4, 5, 6, 7, 8, 9, 10, 11
S_VD, S_VR, S_VQ, S_GMK, S_BIAS = 12, 13, 14, 15, 16
N_GM = 16
S_GM = 17
S_FILT = S_GM + N_GM  # 4 channels x (previous raw input + up to 9 sections)
FILT_STRIDE = 10
S_PLLE = S_FILT + 4 * FILT_STRIDE
S_QX, S_QY, S_UX, S_UY, S_PHI = S_PLLE + 1, S_PLLE + 2, S_PLLE + 3, S_PLLE + 4, S_PLLE + 5
S_VRP = S_PHI + 1  # the rate PID value of the sample before (the AuxOut ramps from it to S_VR)
S_TFE = S_VRP + 1  # the front-end board temperature, degC (first-order lag of the die temperature)
N_STATE = S_TFE + 1

# ---- output rows
O_XD, O_YD, O_XS, O_YS, O_F, O_VD, O_VR, O_VQ, O_PLLE, O_SF, O_AUX = 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10
N_OUT = 11

NOISE_PER_STEP = 6  # 2 ARW (+ forcer-path noise) force components, 4 pickoff noises
SQRT2 = math.sqrt(2.0)
TWO_PI = 2.0 * math.pi
RAD_PER_DEG = math.pi / 180.0
DEG_PER_RAD = 180.0 / math.pi


@njit(cache=True, inline="always")
def _pid(on, p, ki, kd, sp, center, rng, integ, eprev, inp, dt, inv_dt):
    """One PID update: e = sp - inp, out = center + p e + ki int(e) dt + kd de/dt clamped to center +- rng, the
    integrator frozen while clamped; disabled (on = 0): out = center. Returns (out, integrator, e).

    Scalars only: a numba function inlined with array arguments pays a reference-count pair per array per call."""
    if on == 0.0:
        return center, 0.0, 0.0
    e = sp - inp
    integ += e * dt
    de = (e - eprev) * inv_dt
    out = center + p * e + ki * integ + kd * de
    if out > center + rng:
        out = center + rng
        if ki * e > 0.0:
            integ -= e * dt
    elif out < center - rng:
        out = center - rng
        if ki * e < 0.0:
            integ -= e * dt
    return out, integ, e


@njit(cache=True, inline="always")
def _dac(v, lsb, inv_lsb):
    """An AuxOut DAC: v rounded to its step lsb (inv_lsb = 1/lsb; lsb = 0: ideal)."""
    if lsb > 0.0:
        return lsb * math.floor(v * inv_lsb + 0.5)
    return v


@njit(cache=True, inline="always")
def _control(S, L, raws, filt, dt, fj, fs, fr, order, a_d, c_d, sections):
    """Demod low-pass on the 4 raw demod values (into `filt`), then PLL and the three PIDs."""
    inv_dt = 1.0 / dt
    for ch in range(4):
        base = S_FILT + FILT_STRIDE * ch
        u_new = raws[ch]
        u_old = S[base]
        S[base] = u_new
        du = u_new - u_old
        y_last_old = S[base + order]
        # the exact Jordan-chain step (module docstring), in place: section m reads the old y_1..y_m only, so the
        # sections are updated from the last to the first
        if order == 1:  # the HF2's default single section: y+ = a y + u- S_1 + (u+ - u-) R_1
            S[base + 1] = u_old * fs[0] + du * fr[0] + fj[0] * S[base + 1]
        else:
            for m in range(order - 1, -1, -1):
                acc = u_old * fs[m] + du * fr[m]
                for j in range(m + 1):
                    acc += fj[m - j] * S[base + 1 + j]
                S[base + 1 + m] = acc
        out = S[base + order]
        if sections > order:  # loop delay: one first-order section on the filter output
            y_old = S[base + 1 + order]
            y_new = a_d * y_old + (1.0 - a_d) * y_last_old + (out - y_last_old) * c_d
            S[base + 1 + order] = y_new
            out = y_new
        filt[ch] = out
    # PLL on the drive phase
    theta = _atan2(filt[1], filt[0]) * DEG_PER_RAD
    e = theta - L[L_PLL + 3]
    if not -180.0 <= e < 180.0:  # wrap into [-180, 180)
        e = e - 360.0 * math.floor((e + 180.0) * (1.0 / 360.0))
    S[S_PLLE] = e
    center, rng = L[L_PLL + 4], L[L_PLL + 5]
    if L[L_PLL] != 0.0:
        S[S_PLLI] += e * dt
        f = center + L[L_PLL + 1] * e + L[L_PLL + 2] * S[S_PLLI]
        if f > center + rng:
            f = center + rng
            if L[L_PLL + 2] * e > 0.0:
                S[S_PLLI] -= e * dt
        elif f < center - rng:
            f = center - rng
            if L[L_PLL + 2] * e < 0.0:
                S[S_PLLI] -= e * dt
    else:
        S[S_PLLI] = 0.0
        f = center
    S[S_FREF] = f
    r_d = math.sqrt(filt[0] * filt[0] + filt[1] * filt[1])
    S[S_VD], S[S_AGCI], S[S_AGCE] = _pid(
        L[L_AGC],
        L[L_AGC + 1],
        L[L_AGC + 2],
        L[L_AGC + 3],
        L[L_AGC + 4],
        L[L_AGC + 5],
        L[L_AGC + 6],
        S[S_AGCI],
        S[S_AGCE],
        r_d,
        dt,
        inv_dt,
    )
    S[S_VRP] = S[S_VR]
    S[S_VR], S[S_RATEI], S[S_RATEE] = _pid(
        L[L_RATE],
        L[L_RATE + 1],
        L[L_RATE + 2],
        L[L_RATE + 3],
        L[L_RATE + 4],
        L[L_RATE + 5],
        L[L_RATE + 6],
        S[S_RATEI],
        S[S_RATEE],
        filt[2],
        dt,
        inv_dt,
    )
    S[S_VQ], S[S_QUADI], S[S_QUADE] = _pid(
        L[L_QUAD],
        L[L_QUAD + 1],
        L[L_QUAD + 2],
        L[L_QUAD + 3],
        L[L_QUAD + 4],
        L[L_QUAD + 5],
        L[L_QUAD + 6],
        S[S_QUADI],
        S[S_QUADE],
        filt[3],
        dt,
        inv_dt,
    )


@njit(cache=True, inline="always")
def _atan2(y, x):
    """atan2(y, x) in rad; for x > 0 and |y| < 1e-3 x (the locked PLL) the series of atan(r), r = y/x, to r^5
    (relative truncation error < r^6/7 < 2e-19), else math.atan2."""
    if x > 0.0 and abs(y) < 1e-3 * x:
        r = y / x
        r2 = r * r
        return r * (1.0 - r2 * (1.0 / 3.0 - r2 * (1.0 / 5.0)))
    return math.atan2(y, x)


@njit(cache=True, inline="always")
def _exp_neg(x):
    """exp(-x) for real x; 5-term series below 1e-3 (error < 1e-18)."""
    if abs(x) < 1e-3:
        return 1.0 - x * (1.0 - x * (0.5 - x * (1.0 / 6.0 - x * (1.0 / 24.0))))
    return math.exp(-x)


@njit(cache=True, inline="always")
def _exp_neg_i(x):
    """exp(-i x) for real x; series below 1e-2 (error < 1e-18)."""
    if abs(x) < 1e-2:
        x2 = x * x
        c = 1.0 - x2 * (0.5 - x2 * (1.0 / 24.0 - x2 * (1.0 / 720.0 - x2 * (1.0 / 40320.0))))
        sn = x * (1.0 - x2 * (1.0 / 6.0 - x2 * (1.0 / 120.0 - x2 * (1.0 / 5040.0 - x2 * (1.0 / 362880.0)))))
        return complex(c, -sn)
    return complex(math.cos(x), -math.sin(x))


@njit(cache=True, inline="always")
def _bias_update(S, gm_a, gm_b, gm_noise, gi):
    """Bias instability: the Gauss-Markov sum x_j <- a_j x_j + b_j n_j (row gi of gm_noise), held in S[S_BIAS]
    (rad/s) until the next update. Returns the next row of gm_noise to use. The kernels call it only on the
    steps that update (every gm_steps steps): passing arrays to an inlined function costs reference counting."""
    b = 0.0
    for j in range(gm_a.shape[0]):
        x = gm_a[j] * S[S_GM + j] + gm_b[j] * gm_noise[gi, j]
        S[S_GM + j] = x
        b += x
    S[S_BIAS] = b
    return gi + 1


@njit(cache=True)
def input_sums(a, b, c):
    """(sum a, sum b, sum c) of a block's inputs in one compiled pass: a NaN or inf anywhere (or values near the
    float limit) makes its array's sum non-finite, which GyroSim.run refuses before touching the state."""
    sa = 0.0
    sb = 0.0
    sc = 0.0
    for i in range(a.shape[0]):
        sa += a[i]
    for i in range(b.shape[0]):
        sb += b[i]
    for i in range(c.shape[0]):
        sc += c[i]
    return sa, sb, sc


@njit(cache=True)
def _lowpass_sections(P, L, dt):
    """The demodulator low-pass (exact Jordan-chain coefficients) and the loop delay section.

    fj[i] = e^-x x^i / i!, fs[m] = S_(m+1), fr[m] = R_(m+1) of the module docstring (x = dt/tc); the loop delay
    is one first-order section y <- a y + (1 - a) u- + (u+ - u-) c, a = exp(-dt/delay), c = 1 - delay (1 - a)/dt.
    Returns (fj, fs, fr, order, a_d, c_d, sections).
    """
    tc = L[L_TC]
    order = int(L[L_ORDER])
    x = dt / tc
    ex = math.exp(-x)
    fj = np.empty(order)
    fs = np.empty(order)
    fr = np.empty(order)
    term = 1.0  # x^i / i!
    for i in range(order):
        fj[i] = ex * term
        term *= x / (i + 1)
    for m in range(1, order + 1):
        s_sum = 0.0
        r_sum = 0.0
        term = 1.0
        for i in range(m):
            s_sum += term
            r_sum += (m - i) * term
            term *= x / (i + 1)
        fs[m - 1] = 1.0 - ex * s_sum
        if x > 1e-3:
            fr[m - 1] = 1.0 - m / x + ex * r_sum / x
        else:  # series of the ramp response for a slow filter: x^m / (m + 1)! (1 - (m + 1) x / (m + 2) ...)
            fr[m - 1] = x**m / math.gamma(m + 2.0) * (1.0 - (m + 1.0) * x / (m + 2.0))
    delay = P[P_DELAY]
    sections = order
    a_d, c_d = 0.0, 1.0
    if delay > 0.0:
        sections = order + 1
        a_d = math.exp(-dt / delay)
        c_d = 1.0 - delay * (1.0 - a_d) / dt
    return fj, fs, fr, order, a_d, c_d, sections


@njit(cache=True, inline="always")
def _pickoff_ratio(a_t, a_2, a_e, dtemp, dtemp_fe):
    """G_py/G_px = 1 + a_t dT + a_2 dT^2 + a_e dT_fe: the transducer's parts at the die, the front end's at its board.
    The board temperature advances per output step as T_fe <- T + e^(-dt/tau_fe) (T_fe - T), the exact step of
    dT_fe/dt = (T - T_fe)/tau_fe with T held over the step."""
    return 1.0 + a_t * dtemp + a_2 * dtemp * dtemp + a_e * dtemp_fe


@njit(cache=True, nogil=True, error_model="numpy")
def averaged_kernel(S, P, L, gm_a, gm_b, temp_c, rate_dps, dither_v, noise, gm_noise, out):
    """Advance the averaged model by len(temp_c) steps of P[P_DT]; write outputs (rows O_*) into `out`.

    Returns (bias updates used, max |PLL error| over the block in deg)."""
    n = temp_c.shape[0]
    dt = P[P_DT]
    w0, tref = P[P_W0], P[P_TREF]
    k, a0 = P[P_K], P[P_A0]
    sig_arw = P[P_ARW] / math.sqrt(dt)
    sig_pick = P[P_PICK] / math.sqrt(2.0 * dt)
    sig_f = P[P_FNOISE] / math.sqrt(2.0 * dt)
    lsb = P[P_AOLSB]
    inv_lsb = 1.0 / lsb if lsb > 0.0 else 0.0
    fj, fs, fr, order, a_d, c_d, sections = _lowpass_sections(P, L, dt)
    gain = L[L_GAIN]
    gm_steps = P[P_GMSTEPS]
    gi = 0
    err_max = 0.0  # max |PLL error| over the block, deg
    raws = np.empty(4)
    filt = np.empty(4)
    c2w, s2w = P[P_C2W], P[P_S2W]
    c2t, s2t = P[P_C2T], P[P_S2T]
    # parameters read once (the loop stores into S and out, which the compiler cannot prove distinct from P)
    a_w, q0, a_q, dmis, a_dm, dw0, a_dw = P[P_AW], P[P_Q], P[P_AQ], P[P_DMIS], P[P_ADM], P[P_DW], P[P_ADW]
    k_d, k_f, a_f, a_p, beta, sf0 = P[P_KD], P[P_KF], P[P_AF], P[P_AP], P[P_BETA], P[P_SF]
    ftc, fts = P[P_FTC], P[P_FTS]
    a_e, a_2, fe_a = P[P_AE], P[P_A2], P[P_FEA]
    arw_f = k * a0 * w0 * sig_arw  # ARW force times omega_r (divided by omega_r per step)
    inv_sqrt2 = 1.0 / SQRT2
    sf_scale = sf0 / (w0 * a0 * gain)
    for i in range(n):
        S[S_GMK] += 1.0
        if S[S_GMK] >= gm_steps:
            S[S_GMK] = 0.0
            gi = _bias_update(S, gm_a, gm_b, gm_noise, gi)
        dtemp = temp_c[i] - tref
        w = w0 * (1.0 + a_w * dtemp)
        inv_tau = w / (2.0 * q0 * (1.0 + a_q * dtemp))
        g = 0.5 * (dmis + a_dm * dtemp) * inv_tau
        wr = TWO_PI * S[S_FREF]
        inv_2wr = 0.5 / wr
        dw = dw0 + a_dw * dtemp
        h = w * dw * inv_2wr
        delta = (w * w - wr * wr) * inv_2wr
        k_om = k * (rate_dps[i] * RAD_PER_DEG + S[S_BIAS])
        n11 = complex(g * c2t, h * c2w)
        n12 = complex(g * s2t - k_om, h * s2w)
        n21 = complex(g * s2t + k_om, h * s2w)
        mu2 = n11 * n11 + n12 * n21
        x2 = mu2 * (dt * dt)
        ax2 = x2.real * x2.real + x2.imag * x2.imag
        if ax2 < 1e-12:  # |mu dt|^2 < 1e-6 (the usual case): the terms beyond x2^2 are below 2e-22
            ch = 1.0 + x2 * (0.5 + x2 * (1.0 / 24.0))
            sh = dt * (1.0 + x2 * (1.0 / 6.0 + x2 * (1.0 / 120.0)))
        elif ax2 < 1e-4:  # |mu dt|^2 < 1e-2
            ch = 1.0 + x2 * (0.5 + x2 * (1.0 / 24.0 + x2 * (1.0 / 720.0 + x2 * (1.0 / 40320.0))))
            sh = dt * (1.0 + x2 * (1.0 / 6.0 + x2 * (1.0 / 120.0 + x2 * (1.0 / 5040.0 + x2 * (1.0 / 362880.0)))))
        else:
            mu = np.sqrt(mu2)
            ch = np.cosh(mu * dt)
            sh = np.sinh(mu * dt) / mu
        sig = complex(inv_tau, delta)
        ex = _exp_neg_i(delta * dt) * _exp_neg(inv_tau * dt)
        p11 = ex * (ch - sh * n11)
        p12 = -ex * sh * n12
        p21 = -ex * sh * n21
        p22 = ex * (ch + sh * n11)
        # inputs held over the step
        g_f = 1.0 + a_f * dtemp
        ux = complex(k_d * S[S_VD] * inv_2wr, 0.0)
        u_s = gain * (0.5 * (S[S_VRP] + S[S_VR]) + dither_v[i])
        u_c = S[S_VQ]
        kf = k_f * g_f * (1.0 + beta * (u_s * u_s + u_c * u_c)) * inv_2wr
        arw = arw_f * (2.0 * inv_2wr)
        fv = kf * gain * sig_f  # the forcer-path voltage noise, independent of the ARW force on the same component
        uy = complex(kf * u_s - math.sqrt(arw * arw + fv * fv) * noise[i, 0], kf * u_c - arw * noise[i, 1])
        # input term M^-1 (I - Phi) u, M^-1 = (sig I - N) / (sig^2 - mu^2)
        v1 = (1.0 - p11) * ux - p12 * uy
        v2 = -p21 * ux + (1.0 - p22) * uy
        den = sig * sig - mu2
        inv_den = den.conjugate() * (1.0 / (den.real * den.real + den.imag * den.imag))
        zx_in = ((sig - n11) * v1 - n12 * v2) * inv_den
        zy_in = (-n21 * v1 + (sig + n11) * v2) * inv_den
        zx = complex(S[S_CX], S[S_SX])
        zy = complex(S[S_CY], S[S_SY])
        zx_new = p11 * zx + p12 * zy + zx_in
        zy_new = p21 * zx + p22 * zy + zy_in
        S[S_CX], S[S_SX] = zx_new.real, zx_new.imag
        S[S_CY], S[S_SY] = zy_new.real, zy_new.imag
        S[S_TFE] = temp_c[i] + fe_a * (S[S_TFE] - temp_c[i])
        g_py = _pickoff_ratio(a_p, a_2, a_e, dtemp, S[S_TFE] - tref) * inv_sqrt2
        ft_c = ftc * u_c - fts * u_s  # _feedthrough
        ft_s = ftc * u_s + fts * u_c
        raws[0] = zx_new.real * inv_sqrt2 + sig_pick * noise[i, 2]
        raws[1] = -zx_new.imag * inv_sqrt2 + sig_pick * noise[i, 3]
        raws[2] = g_py * (zy_new.real + ft_c) + sig_pick * noise[i, 4]
        raws[3] = -g_py * (zy_new.imag + ft_s) + sig_pick * noise[i, 5]
        _control(S, L, raws, filt, dt, fj, fs, fr, order, a_d, c_d, sections)
        S[S_VR] = _dac(S[S_VR], lsb, inv_lsb)
        S[S_VQ] = _dac(S[S_VQ], lsb, inv_lsb)
        out[O_XD, i] = filt[0]
        out[O_YD, i] = filt[1]
        out[O_XS, i] = filt[2]
        out[O_YS, i] = filt[3]
        out[O_F, i] = S[S_FREF]
        out[O_VD, i] = S[S_VD]
        out[O_VR, i] = S[S_VR]
        out[O_VQ, i] = S[S_VQ]
        out[O_PLLE, i] = S[S_PLLE]
        ae = abs(S[S_PLLE])
        if ae > err_max or math.isnan(ae):  # a NaN error is kept (the block then reads as unlocked)
            err_max = ae
        amp = math.sqrt(zx_new.real * zx_new.real + zx_new.imag * zx_new.imag)
        w_x = math.sqrt(w * w + w * dw * c2w)
        out[O_SF, i] = sf_scale * w_x * amp * (1.0 / g_f)
        out[O_AUX, i] = S[S_VRP]
    return gi, err_max


@njit(cache=True, inline="always")
def _feedthrough(P, u_s, u_c):
    """Forcer-to-pickoff feedthrough as a sense slow-variable offset C + iS (pickoff units, G_py applied after).

    The forcer electrode carries c_e (u_c cos phi + u_s sin phi) (c_e folded into P_FTC/P_FTS with the coupling
    kappa); a coupling kappa e^{i phi_ft} puts kappa c_e [(u_c cos phi_ft - u_s sin phi_ft) cos phi
    + (u_s cos phi_ft + u_c sin phi_ft) sin phi] on the pickoff: C = P_FTC u_c - P_FTS u_s, S = P_FTC u_s + P_FTS u_c
    with P_FTC = kappa c_e cos phi_ft, P_FTS = kappa c_e sin phi_ft."""
    return complex(P[P_FTC] * u_c - P[P_FTS] * u_s, P[P_FTC] * u_s + P[P_FTS] * u_c)


@njit(cache=True)
def _expm_taylor(A, dt, term, tmp, phi_m, psi):
    """phi_m = expm(A dt), psi = int_0^dt expm(A s) ds, Taylor series to (A dt)^13 / 13! (||A dt|| ~ 0.2)."""
    for r in range(4):
        for c in range(4):
            e = 1.0 if r == c else 0.0
            term[r, c] = e
            phi_m[r, c] = e
            psi[r, c] = e * dt
    for nn in range(1, 14):
        for r in range(4):
            for c in range(4):
                acc = 0.0
                for m in range(4):
                    acc += term[r, m] * A[m, c]
                tmp[r, c] = acc * dt / nn
        for r in range(4):
            for c in range(4):
                term[r, c] = tmp[r, c]
                phi_m[r, c] += tmp[r, c]
                psi[r, c] += tmp[r, c] * dt / (nn + 1)


@njit(cache=True, nogil=True, error_model="numpy")
def carrier_kernel(S, P, L, gm_a, gm_b, m_per, temp_c, rate_dps, dither_v, noise, gm_noise, out):
    """Advance the carrier-level model by len(temp_c) demod samples of m_per carrier samples of P[P_DT].

    Returns (bias updates used, max |PLL error| over the block in deg)."""
    n = temp_c.shape[0]
    dt = P[P_DT]
    dtc = dt * m_per
    w0, tref = P[P_W0], P[P_TREF]
    k, a0 = P[P_K], P[P_A0]
    sig_arw = P[P_ARW] / math.sqrt(dtc)
    sig_pick = P[P_PICK] / math.sqrt(2.0 * dtc)
    sig_f = P[P_FNOISE] / math.sqrt(2.0 * dtc)
    lsb = P[P_AOLSB]
    inv_lsb = 1.0 / lsb if lsb > 0.0 else 0.0
    fj, fs, fr, order, a_d, c_d, sections = _lowpass_sections(P, L, dtc)
    gain = L[L_GAIN]
    gm_steps = P[P_GMSTEPS]
    gi = 0
    err_max = 0.0  # max |PLL error| over the block, deg
    raws = np.empty(4)
    filt = np.empty(4)
    c2w, s2w = P[P_C2W], P[P_S2W]
    c2t, s2t = P[P_C2T], P[P_S2T]
    A = np.zeros((4, 4))
    term = np.empty((4, 4))
    tmp = np.empty((4, 4))
    phi_m = np.empty((4, 4))
    psi = np.empty((4, 4))
    q = np.empty(4)
    qn = np.empty(4)
    last_t = 0.0
    last_om = 0.0
    for i in range(n):
        S[S_GMK] += 1.0
        if S[S_GMK] >= gm_steps:
            S[S_GMK] = 0.0
            gi = _bias_update(S, gm_a, gm_b, gm_noise, gi)
        dtemp = temp_c[i] - tref
        w = w0 * (1.0 + P[P_AW] * dtemp)
        inv_tau = w / (2.0 * P[P_Q] * (1.0 + P[P_AQ] * dtemp))
        dd = (P[P_DMIS] + P[P_ADM] * dtemp) * inv_tau
        dw = P[P_DW] + P[P_ADW] * dtemp
        om = rate_dps[i] * RAD_PER_DEG + S[S_BIAS]
        # A on [x, y, x'/w0, y'/w0]
        kxx = w * w + w * dw * c2w
        kyy = w * w - w * dw * c2w
        kxy = w * dw * s2w
        A[0, 2] = w0
        A[1, 3] = w0
        A[2, 0] = -kxx / w0
        A[2, 1] = -kxy / w0
        A[3, 0] = -kxy / w0
        A[3, 1] = -kyy / w0
        A[2, 2] = -(2.0 * inv_tau + dd * c2t)
        A[2, 3] = -(dd * s2t - 2.0 * k * om)
        A[3, 2] = -(dd * s2t + 2.0 * k * om)
        A[3, 3] = -(2.0 * inv_tau - dd * c2t)
        # Taylor series of expm(A dt) and int_0^dt expm(A s) ds (only when T or Omega changed)
        if i == 0 or temp_c[i] != last_t or om != last_om:
            last_t = temp_c[i]
            last_om = om
            _expm_taylor(A, dt, term, tmp, phi_m, psi)
        # forces (held over the demod sample), sinc-compensated, modulated at mid-sample phase
        wr = TWO_PI * S[S_FREF]
        g_f = 1.0 + P[P_AF] * dtemp
        S[S_TFE] = temp_c[i] + P[P_FEA] * (S[S_TFE] - temp_c[i])
        g_py = _pickoff_ratio(P[P_AP], P[P_A2], P[P_AE], dtemp, S[S_TFE] - tref)
        fn = 2.0 * w0 * k * a0 * sig_arw
        fxs = -P[P_KD] * S[S_VD]
        u_s = gain * (0.5 * (S[S_VRP] + S[S_VR]) + dither_v[i])
        u_c = S[S_VQ]
        kfc = P[P_KF] * g_f * (1.0 + P[P_BETA] * (u_s * u_s + u_c * u_c))
        fv = P[P_KF] * g_f * gain * sig_f  # forcer-path voltage noise: one draw with the ARW force (independent)
        fys = -kfc * u_s + math.sqrt(fn * fn + fv * fv) * noise[i, 0]
        fyc = kfc * u_c - fn * noise[i, 1]
        half = 0.5 * wr * dt
        inv_sinc = half / math.sin(half)
        fxs *= inv_sinc / w0
        fys *= inv_sinc / w0
        fyc *= inv_sinc / w0
        cr, sr = math.cos(wr * dt), math.sin(wr * dt)
        phi0 = S[S_PHI]
        cm, sm = math.cos(phi0 + half), math.sin(phi0 + half)
        ce, se = math.cos(phi0 + 2.0 * half), math.sin(phi0 + 2.0 * half)
        q[0], q[1], q[2], q[3] = S[S_QX], S[S_QY], S[S_UX], S[S_UY]
        sxc = 0.0
        sxs = 0.0
        syc = 0.0
        sys_ = 0.0
        for _j in range(m_per):
            fx = fxs * sm
            fy = fyc * cm + fys * sm
            for r in range(4):
                qn[r] = (
                    phi_m[r, 0] * q[0]
                    + phi_m[r, 1] * q[1]
                    + phi_m[r, 2] * q[2]
                    + phi_m[r, 3] * q[3]
                    + psi[r, 2] * fx
                    + psi[r, 3] * fy
                )
            for r in range(4):
                q[r] = qn[r]
            sxc += q[0] * ce
            sxs += q[0] * se
            syc += q[1] * ce
            sys_ += q[1] * se
            t1 = cm * cr - sm * sr
            sm = sm * cr + cm * sr
            cm = t1
            t2 = ce * cr - se * sr
            se = se * cr + ce * sr
            ce = t2
        S[S_QX], S[S_QY], S[S_UX], S[S_UY] = q[0], q[1], q[2], q[3]
        ph = phi0 + m_per * wr * dt
        S[S_PHI] = ph - TWO_PI * math.floor(ph / TWO_PI)
        scale = SQRT2 / m_per  # demod: X + iY = sqrt(2) mean(q e^{-i phi}); C + iS = 2 mean(q e^{+i phi})
        S[S_CX] = 2.0 * sxc / m_per
        S[S_SX] = 2.0 * sxs / m_per
        S[S_CY] = 2.0 * syc / m_per
        S[S_SY] = 2.0 * sys_ / m_per
        ft = _feedthrough(P, u_s, u_c)
        raws[0] = scale * sxc + sig_pick * noise[i, 2]
        raws[1] = -scale * sxs + sig_pick * noise[i, 3]
        raws[2] = g_py * (scale * syc + ft.real / SQRT2) + sig_pick * noise[i, 4]
        raws[3] = -g_py * (scale * sys_ + ft.imag / SQRT2) + sig_pick * noise[i, 5]
        _control(S, L, raws, filt, dtc, fj, fs, fr, order, a_d, c_d, sections)
        S[S_VR] = _dac(S[S_VR], lsb, inv_lsb)
        S[S_VQ] = _dac(S[S_VQ], lsb, inv_lsb)
        out[O_XD, i] = filt[0]
        out[O_YD, i] = filt[1]
        out[O_XS, i] = filt[2]
        out[O_YS, i] = filt[3]
        if P[P_RIP] != 0.0:  # the 2-omega term the HF2's filter leaves in the streamed sample (docstring)
            h2 = 1.0 / (1.0 - 2j * wr * L[L_TC]) ** order
            rot = h2 * complex(math.cos(2.0 * S[S_PHI]), -math.sin(2.0 * S[S_PHI])) / SQRT2
            rx = rot * complex(S[S_CX], S[S_SX])
            ry = g_py * rot * complex(S[S_CY], S[S_SY])
            out[O_XD, i] += rx.real
            out[O_YD, i] += rx.imag
            out[O_XS, i] += ry.real
            out[O_YS, i] += ry.imag
        out[O_F, i] = S[S_FREF]
        out[O_VD, i] = S[S_VD]
        out[O_VR, i] = S[S_VR]
        out[O_VQ, i] = S[S_VQ]
        out[O_PLLE, i] = S[S_PLLE]
        ae = abs(S[S_PLLE])
        if ae > err_max or math.isnan(ae):  # a NaN error is kept (the block then reads as unlocked)
            err_max = ae
        amp = 2.0 * math.sqrt(sxc * sxc + sxs * sxs) / m_per
        w_x = math.sqrt(kxx)
        out[O_SF, i] = P[P_SF] * (w_x / w0) * (amp / a0) / (g_f * gain)
        out[O_AUX, i] = S[S_VRP]
    return gi, err_max
