"""The QMG physics twin: averaged (slow-variable) model, the primary simulator of every campaign.

`GyroSim(params, dt_s, seed).run(inputs, loops)` advances the gyroscope by one block of steps of dt_s under the
loops the HF2 twin closes, and returns what the lock-in's demodulators and PIDs would report at the end of each
step (`GyroBlock`). The equations (docs/physics.md sections 1-3; docs/simulation.md) and their exact
zero-order-hold discretization are in sims/gyro_kernel.py; the noise model in sims/noise.py; the parameter and
settings types in sims/gyro_params.py; the carrier-level cross-check model in sims/carrier.py.

Electrical model (qmg_lab/campaign/loops.py conventions): pickoff gains G_px = 1, G_py(T) = 1 + alpha_p (T - T_ref)
V per displacement unit; drive demod X_d + iY_d = (c_x - i s_x)/sqrt(2); sense demod
X_s + iY_s = G_py (c_y - i s_y)/sqrt(2); AGC (input R_d) -> V_d, F_xs = -K_dx V_d; rate PID (input X_s) -> V_r,
quadrature PID (input Y_s) -> V_q; F_ys = -K_f G_f(T) g (V_r + V_dither), F_yc = +K_f G_f(T) V_q; Omega = table rate
+ Gauss-Markov bias; ARW as white force noise on the sense axis; pickoff noise white on the demod outputs.

Memory: a block allocates only its own outputs (the kernel writes into them in place) and runs the kernel in chunks
of CHUNK_STEPS, each with its own per-step noise rows drawn just before it (sims/noise.py); between blocks only the
state vector (about 80 numbers) and the noise generators are kept. The rows are the same however a block is split:
the stream hands them out in order.
"""

from __future__ import annotations

import copy
import math
from typing import Any

import numpy as np

from sims import gyro_kernel as gk
from sims.gyro_params import (
    PLL_LOCK_DEG,
    RAD_PER_DEG,
    GyroBlock,
    GyroParams,
    LoopSettings,
    PidSettings,
    PllSettings,
    pack_loops,
)
from sims.noise import NoiseStream, gm_coefficients, gm_sigmas_rad_s, gm_steps
from sims.world import BlockInputs

__all__ = ["GyroBlock", "GyroParams", "GyroSim", "LoopSettings", "PidSettings", "PllSettings", "held_inputs"]

INPUT_NAMES = ("gyro_c", "table_rate_dps", "dither_v")
CHUNK_STEPS = 1 << 13  # 8192 steps: the chunk's noise draws (192 kB) stay in the L2 cache


def pack_params(p: GyroParams, dt_s: float, steps_per_gm: int, output_step_s: float | None = None) -> np.ndarray:
    """GyroParams as the float64 vector the kernels read (indices P_* in sims/gyro_kernel.py); output_step_s is the
    interval between outputs (the controller step; dt_s if None), over which the front-end board's lag advances."""
    v = np.zeros(gk.N_PARAMS)
    two_t = 2.0 * p.damping_axis_deg * RAD_PER_DEG
    two_w = 2.0 * p.stiffness_axis_deg * RAD_PER_DEG
    v[gk.P_W0] = p.omega0_rad_s
    v[gk.P_Q] = p.q_factor
    v[gk.P_DMIS] = p.damping_mismatch
    v[gk.P_C2T], v[gk.P_S2T] = math.cos(two_t), math.sin(two_t)
    v[gk.P_DW] = 2.0 * math.pi * p.freq_mismatch_hz
    v[gk.P_C2W], v[gk.P_S2W] = math.cos(two_w), math.sin(two_w)
    v[gk.P_K] = p.angular_gain
    v[gk.P_ARW] = p.arw_rad_per_rt_s
    v[gk.P_PICK] = p.pickoff_noise_vrms_per_rt_hz
    v[gk.P_FNOISE] = p.forcer_noise_v_per_rt_hz
    v[gk.P_AOLSB] = p.auxout_lsb_v
    v[gk.P_AF] = p.forcer_tempco_ppm_per_c * 1e-6
    v[gk.P_AW] = p.frequency_tempco_ppm_per_c * 1e-6
    v[gk.P_AP] = p.pickoff_transducer_tempco_ppm_per_c * 1e-6
    v[gk.P_AE] = p.pickoff_electronics_tempco_ppm_per_c * 1e-6
    v[gk.P_A2] = p.pickoff_ratio_tempco2_ppm_per_c2 * 1e-6
    tau_fe = p.frontend_thermal_tau_s
    step = dt_s if output_step_s is None else output_step_s
    v[gk.P_FEA] = math.exp(-step / tau_fe) if tau_fe > 0.0 else 0.0
    v[gk.P_TREF] = p.reference_temperature_c
    v[gk.P_DELAY] = p.loop_delay_us * 1e-6
    v[gk.P_KD] = p.k_drive
    v[gk.P_KF] = p.k_forcer
    v[gk.P_A0] = p.a0
    v[gk.P_DT] = dt_s
    v[gk.P_GMSTEPS] = float(steps_per_gm)
    v[gk.P_SF] = p.sf_true_v_per_dps
    v[gk.P_R0] = p.drive_amplitude_vrms
    v[gk.P_AQ] = p.q_tempco_ppm_per_c * 1e-6
    v[gk.P_ADM] = p.damping_mismatch_tempco_per_c
    v[gk.P_ADW] = 2.0 * math.pi * p.freq_mismatch_tempco_hz_per_c
    v[gk.P_BETA] = p.forcer_cubic_per_v2
    phi_ft = p.feedthrough_phase_deg * RAD_PER_DEG
    v[gk.P_FTC] = p.feedthrough_v_per_v * p.forcer_electrode_v_per_v * math.cos(phi_ft)
    v[gk.P_FTS] = p.feedthrough_v_per_v * p.forcer_electrode_v_per_v * math.sin(phi_ft)
    v[gk.P_RIP] = 1.0 if p.hf2_demod_ripple else 0.0
    return v


def _as_inputs(inputs: BlockInputs) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(gyro temperature, table rate, dither) as contiguous float64 arrays of one length, checked (the sums of
    all three in one compiled pass: this runs on every block)."""
    temp = np.ascontiguousarray(inputs.gyro_c, dtype=np.float64)
    rate = np.ascontiguousarray(inputs.table_rate_dps, dtype=np.float64)
    dither = np.ascontiguousarray(inputs.dither_v, dtype=np.float64)
    n = temp.shape[0]
    if not (temp.ndim == rate.ndim == dither.ndim == 1 and n == rate.shape[0] == dither.shape[0] and n > 0):
        _refuse_inputs((temp, rate, dither))
    sums = gk.input_sums(temp, rate, dither)
    if not (math.isfinite(sums[0]) and math.isfinite(sums[1]) and math.isfinite(sums[2])):
        for name, total in zip(INPUT_NAMES, sums, strict=True):
            if not math.isfinite(total):  # a NaN or inf anywhere makes the sum non-finite
                raise ValueError(f"BlockInputs.{name} contains a non-finite value (or values near the float limit)")
    return temp, rate, dither


def _refuse_inputs(arrays: tuple[np.ndarray, np.ndarray, np.ndarray]) -> None:
    """Raise the ValueError naming what is wrong with a block's inputs (shape, length, emptiness)."""
    for name, a in zip(INPUT_NAMES, arrays, strict=True):
        if a.ndim != 1:
            raise ValueError(f"BlockInputs.{name} must be 1-D, got shape {a.shape}")
    n = arrays[0].shape[0]
    if n == 0:
        raise ValueError("BlockInputs must hold at least one step")
    raise ValueError(
        "BlockInputs arrays must all have the same length "
        f"(gyro_c {n}, table_rate_dps {arrays[1].shape[0]}, dither_v {arrays[2].shape[0]})"
    )


def held_inputs(
    n: int,
    dt_s: float,
    *,
    rate_dps: float | np.ndarray = 0.0,
    temperature_c: float | np.ndarray = 25.0,
    dither_v: float | np.ndarray = 0.0,
    t0_s: float = 0.0,
) -> BlockInputs:
    """BlockInputs for n steps of dt_s without a World (tests, benchmarks): scalars are held, arrays used as is."""
    if n < 1:
        raise ValueError(f"n must be >= 1, got {n!r}")
    z = np.zeros(n)
    rate = z + rate_dps
    temp = z + temperature_c
    return BlockInputs(
        t=t0_s + dt_s * np.arange(n),
        table_rate_dps=rate,
        table_angle_deg=np.concatenate(([0.0], np.cumsum(rate[:-1]) * dt_s)),
        chamber_c=temp,
        gyro_c=temp,
        dither_v=z + dither_v,
    )


class _TwinBase:
    """State, reset/settling and block bookkeeping shared by the averaged and the carrier-level model.

    Subclasses set `self.step_s` (the interval between outputs) and implement `_kernel`."""

    step_s: float

    def __init__(self, params: GyroParams, dt_s: float, seed: int, step_s: float) -> None:
        if not isinstance(params, GyroParams):
            raise TypeError(f"params must be a GyroParams, got {type(params).__name__}")
        if not (isinstance(dt_s, (int, float)) and math.isfinite(dt_s) and dt_s > 0):
            raise ValueError(f"dt_s must be a finite number > 0, got {dt_s!r}")
        self.params = params
        self.dt_s = float(dt_s)
        self.step_s = float(step_s)
        self.gm_steps = gm_steps(self.step_s)
        self._P = pack_params(params, self.dt_s, self.gm_steps, self.step_s)
        self._gm_a, self._gm_b = gm_coefficients(params.bias_instability_deg_per_h, self.gm_steps * self.step_s)
        self._noise = NoiseStream(seed, gk.NOISE_PER_STEP, gk.N_GM)
        self._step_noise_on = (
            params.arw_rad_per_rt_s > 0
            or params.pickoff_noise_vrms_per_rt_hz > 0
            or params.forcer_noise_v_per_rt_hz > 0
        )
        self._bias_on = params.bias_instability_deg_per_h > 0
        self._S = np.zeros(gk.N_STATE)
        self._loops_key: tuple[LoopSettings, np.ndarray] | None = None
        self._pending: str = "settle"
        self.reset(settled=True)

    # ------------------------------------------------------------------ state
    def reset(self, settled: bool = True) -> None:
        """Zero the state. settled=True: the first run starts at the steady state of its loops (nominal drive
        amplitude, PLL on the drive resonance, rate/quadrature outputs balancing the inputs); settled=False:
        the resonator at rest, every integrator empty, the PLL at its centre frequency."""
        self._S[:] = 0.0
        sig = gm_sigmas_rad_s(self.params.bias_instability_deg_per_h)
        gm0 = self._noise.gm(1, self._bias_on)[0] * sig
        self._S[gk.S_GM : gk.S_GM + gk.N_GM] = gm0
        self._S[gk.S_BIAS] = float(gm0.sum())
        self._pending = "settle" if settled else "rest"

    def set_modal_state(self, cx: float, sx: float, cy: float, sy: float) -> None:
        """Set the slow variables C + iS of both axes (displacement units, G_px = 1 V/unit), e.g. for a
        ring-down. The demod filters are set to match; call after reset and before run."""
        self._S[gk.S_CX : gk.S_SY + 1] = (cx, sx, cy, sy)
        if self._pending == "none":
            self._init_filters()
        else:
            self._pending = "rest"

    @property
    def state(self) -> dict[str, Any]:
        """A snapshot of the physical and controller state (units in the keys)."""
        s = self._S
        return {
            "c_x": s[gk.S_CX],
            "s_x": s[gk.S_SX],
            "c_y": s[gk.S_CY],
            "s_y": s[gk.S_SY],
            "pll_frequency_hz": s[gk.S_FREF],
            "drive_output_v": s[gk.S_VD],
            "rate_output_v": s[gk.S_VR],
            "quadrature_output_v": s[gk.S_VQ],
            "bias_dps": s[gk.S_BIAS] / RAD_PER_DEG,
        }

    def true_scale_factor(
        self, temperature_c: float, forcer_gain: float = 1.0, drive_amplitude_vrms: float | None = None
    ) -> float:
        """True FTR SF, V per deg/s (GyroParams.true_scale_factor)."""
        return self.params.true_scale_factor(temperature_c, forcer_gain, drive_amplitude_vrms)

    # ------------------------------------------------------------------ settling
    def _start(self, temp0: float, rate0_dps: float, loops: LoopSettings) -> None:
        """Apply the pending reset mode at the first step of the first run after reset()."""
        s, p = self._S, self.params
        pll = loops.pll
        s[gk.S_TFE] = temp0  # the front-end board starts in equilibrium with the die
        if self._pending == "rest":
            s[gk.S_FREF] = pll.center_hz
            self._init_filters()
            return
        w = p.omega_rad_s(temp0)
        inv_tau = w / (2.0 * p.q_at(temp0))
        g = 0.5 * p.damping_mismatch_at(temp0) * inv_tau
        two_t = 2.0 * p.damping_axis_deg * RAD_PER_DEG
        two_w = 2.0 * p.stiffness_axis_deg * RAD_PER_DEG
        dw = 2.0 * math.pi * p.freq_mismatch_at_hz(temp0)
        if pll.enabled:
            f = min(
                max(p.omega_x_rad_s(temp0) / (2.0 * math.pi), pll.center_hz - pll.range_hz),
                pll.center_hz + pll.range_hz,
            )
            s[gk.S_PLLI] = (f - pll.center_hz) / pll.i if pll.i != 0.0 else 0.0
        else:
            f = pll.center_hz
        s[gk.S_FREF] = f
        wr = 2.0 * math.pi * f
        gamma_xx = inv_tau + g * math.cos(two_t)
        agc = loops.agc
        if agc.enabled:
            a = math.sqrt(2.0) * agc.setpoint
            vd = 2.0 * wr * gamma_xx * a / p.k_drive
            vd = min(max(vd, agc.center - agc.range), agc.center + agc.range)
            s[gk.S_AGCI] = (vd - agc.center) / agc.i if agc.i != 0.0 else 0.0
        else:
            vd = agc.center
            a = p.k_drive * vd / (2.0 * wr * gamma_xx)
        s[gk.S_VD] = vd
        sp = pll.setpoint_deg * RAD_PER_DEG if pll.enabled else 0.0
        s[gk.S_CX], s[gk.S_SX] = a * math.cos(sp), -a * math.sin(sp)
        g_f = p.forcer_gain_factor(temp0)
        kf = p.k_forcer
        omega = rate0_dps * RAD_PER_DEG + s[gk.S_BIAS]
        rate = loops.rate
        if rate.enabled and loops.forcer_gain != 0.0:
            vr = 2.0 * wr * (g * math.sin(two_t) + p.angular_gain * omega) * a / (kf * g_f * loops.forcer_gain)
            vr = min(max(vr, rate.center - rate.range), rate.center + rate.range)
            s[gk.S_RATEI] = (vr - rate.center) / rate.i if rate.i != 0.0 else 0.0
            s[gk.S_VR] = vr
            s[gk.S_VRP] = vr
        else:
            s[gk.S_VR] = rate.center
            s[gk.S_VRP] = rate.center
        quad = loops.quadrature
        if quad.enabled:
            xi_yx = w * dw * math.sin(two_w) / (2.0 * wr)
            vq = 2.0 * wr * xi_yx * a / (kf * g_f)
            vq = min(max(vq, quad.center - quad.range), quad.center + quad.range)
            s[gk.S_QUADI] = (vq - quad.center) / quad.i if quad.i != 0.0 else 0.0
            s[gk.S_VQ] = vq
        else:
            s[gk.S_VQ] = quad.center
        self._init_filters()

    def _init_filters(self) -> None:
        """Demod filters at the demod values of the current slow variables (no start-up transient)."""
        s = self._S
        g_py = 1.0  # temperature is not known before the first step; a ppm-level start transient at most
        raws = (
            s[gk.S_CX] / math.sqrt(2.0),
            -s[gk.S_SX] / math.sqrt(2.0),
            g_py * s[gk.S_CY] / math.sqrt(2.0),
            -g_py * s[gk.S_SY] / math.sqrt(2.0),
        )
        for ch, r in enumerate(raws):
            base = gk.S_FILT + gk.FILT_STRIDE * ch
            s[base : base + gk.FILT_STRIDE] = r
        self._init_carrier()

    def _init_carrier(self) -> None:
        """Carrier model only: displacement and velocity from the slow variables."""

    # ------------------------------------------------------------------ running
    def _kernel(
        self,
        temp: np.ndarray,
        rate: np.ndarray,
        dither: np.ndarray,
        noise: np.ndarray,
        gm: np.ndarray,
        out: np.ndarray,
        loops_vec: np.ndarray,
    ) -> tuple[int, float]:
        """Run the compiled kernel on one chunk; returns (bias updates used, max |PLL error| in deg)."""
        raise NotImplementedError

    def _loops_vector(self, loops: LoopSettings) -> np.ndarray:
        """pack_loops(loops), kept while the settings stay equal (the HF2 twin passes the same settings every
        poll; comparing is a sixth of the cost of packing and checking). The key is a private copy, so changing
        the caller's LoopSettings in place is seen."""
        if self._loops_key is not None and _same_loops(loops, self._loops_key[0]):
            return self._loops_key[1]
        vec = pack_loops(loops)
        self._loops_key = (copy.deepcopy(loops), vec)
        return vec

    def run(self, inputs: BlockInputs, loops: LoopSettings) -> GyroBlock:
        """Advance the state by len(inputs.t) steps under `loops`; return the block of outputs."""
        if not isinstance(loops, LoopSettings):
            raise TypeError(f"loops must be a LoopSettings, got {type(loops).__name__}")
        temp, rate, dither = _as_inputs(inputs)
        lvec = self._loops_vector(loops)
        if self._pending != "none":
            self._start(float(temp[0]), float(rate[0]), loops)
            self._pending = "none"
        n = temp.shape[0]
        out = np.empty((gk.N_OUT, n))
        on = self._step_noise_on
        if n <= CHUNK_STEPS:  # a poll's block: one chunk, no slicing
            err_max = self._run_chunk(temp, rate, dither, self._noise.steps(n, on), out, lvec)
        else:  # a long block chunk by chunk, each chunk's noise drawn just before it
            err_max = 0.0
            for a in range(0, n, CHUNK_STEPS):
                b = min(n, a + CHUNK_STEPS)
                noise = self._noise.steps(b - a, on)
                chunk_err = self._run_chunk(temp[a:b], rate[a:b], dither[a:b], noise, out[:, a:b], lvec)
                if not chunk_err <= err_max:  # also keeps a NaN: the block then reads as unlocked
                    err_max = chunk_err
        locked = bool(loops.pll.enabled and err_max < PLL_LOCK_DEG)
        return GyroBlock(
            x_drive=out[gk.O_XD],
            y_drive=out[gk.O_YD],
            x_sense=out[gk.O_XS],
            y_sense=out[gk.O_YS],
            frequency_hz=out[gk.O_F],
            drive_output_v=out[gk.O_VD],
            rate_output_v=out[gk.O_VR],
            quadrature_output_v=out[gk.O_VQ],
            pll_error_deg=out[gk.O_PLLE],
            sf_true_v_per_dps=out[gk.O_SF],
            rate_true_dps=rate.copy(),
            pll_locked=locked,
            rate_auxout_v=out[gk.O_AUX],
        )

    def _run_chunk(
        self,
        temp: np.ndarray,
        rate: np.ndarray,
        dither: np.ndarray,
        noise: np.ndarray,
        out: np.ndarray,
        lvec: np.ndarray,
    ) -> float:
        """Run the kernel on one chunk with its per-step noise rows (outputs into `out`), drawing its bias
        updates; returns its max |PLL error|."""
        m = temp.shape[0]
        n_upd = (int(self._S[gk.S_GMK]) + m) // self.gm_steps
        gm = self._noise.gm(n_upd, self._bias_on)
        used, err_max = self._kernel(temp, rate, dither, noise, gm, out, lvec)
        if used != n_upd:
            raise RuntimeError(f"bias update count mismatch ({used} != {n_upd}): kernel and planner disagree")
        return err_max


def _same_loops(a: LoopSettings, b: LoopSettings) -> bool:
    """a == b as the dataclasses compare them, with each settings object's field dictionary compared in C (half
    the time of the generated __eq__, which builds tuples). A test holds it to == for every field."""
    return (
        a.pll.__dict__ == b.pll.__dict__
        and a.agc.__dict__ == b.agc.__dict__
        and a.rate.__dict__ == b.rate.__dict__
        and a.quadrature.__dict__ == b.quadrature.__dict__
        and a.forcer_gain == b.forcer_gain
        and a.demod_timeconstant_s == b.demod_timeconstant_s
        and a.demod_order == b.demod_order
    )


class GyroSim(_TwinBase):
    """Averaged (slow-variable) model of the QMG under the HF2 loops; one output per step of dt_s."""

    def __init__(self, params: GyroParams, dt_s: float, seed: int) -> None:
        if dt_s > 0.01:
            raise ValueError(f"dt_s = {dt_s!r} s is too coarse for the loops (PLL 15 Hz): use <= 0.01 s")
        super().__init__(params, dt_s, seed, step_s=dt_s)

    def _kernel(
        self,
        temp: np.ndarray,
        rate: np.ndarray,
        dither: np.ndarray,
        noise: np.ndarray,
        gm: np.ndarray,
        out: np.ndarray,
        loops_vec: np.ndarray,
    ) -> tuple[int, float]:
        used, err_max = gk.averaged_kernel(
            self._S, self._P, loops_vec, self._gm_a, self._gm_b, temp, rate, dither, noise, gm, out
        )
        return int(used), float(err_max)
