"""Parameters, loop settings and output block of the QMG physics twin (the GyroSim contract types).

Units are in the names. The names mirror qmg_lab/config/schema.py SimSection (and [device]
drive_amplitude_vrms) so a config section can be passed to `GyroParams.from_mapping`. The values, the paper's QMG
by default (Trusov et al., 2013, docs/physics.md section 1), live in one place, that schema: this module carries no
second copy of them (the station fills `GyroParams` from the configuration; tests take the paper's device from
tests/support/twin_params.py).

Derived constants (`Derived`), with omega0 = 2 pi f0, tau = 2Q/omega (amplitude decay time of the slow
variables, physics.md section 2), a0 = sqrt(2) drive_amplitude_vrms (G_px = 1 V/unit at T_ref):

    K_dx = 2 omega0 a0 / (tau0 V_d0)            drive force per drive volt (F_xs = -K_dx V_d)
    K_f  = 2 omega0 k a0 / SF_rad               forcer force per volt, SF_rad = sf_true_v_per_dps * 180/pi
    SF_true(T, g) = sf_true (omega_x/omega0)(a/a0) / (G_f(T) g)     V per deg/s
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

DEG_PER_RAD = 180.0 / math.pi
RAD_PER_DEG = math.pi / 180.0


NOISE_OFF: dict[str, Any] = {
    "arw_deg_per_rt_h": 0.0,
    "bias_instability_deg_per_h": 0.0,
    "pickoff_noise_vrms_per_rt_hz": 0.0,
    "forcer_noise_v_per_rt_hz": 0.0,
    "auxout_bits": 0,
}
"""GyroParams values that switch off every random source and the AuxOut DAC rounding (GyroParams.noiseless)."""


@dataclass
class GyroParams:
    """Physical parameters of the simulated QMG.

    Every field is required: the configuration's [sim] section (and [device] drive_amplitude_vrms) exposes each
    one, and the schema (qmg_lab/config/schema.py SimSection) is the one place of their defaults, bounds and
    descriptions; qmg_lab/station.py `gyro_params` maps a configuration to this class. A default written here
    would be a second copy that could drift from the schema (tests/unit/sims/test_sim_defaults_one_place.py).
    """

    f0_hz: float
    q_factor: float
    damping_mismatch: float  # Delta(1/tau) / (1/tau)
    damping_axis_deg: float
    freq_mismatch_hz: float  # mode split after tuning, Hz; assumed ("mode-matched" in the paper)
    stiffness_axis_deg: float  # its principal axis; assumed (0 would leave the quadrature loop idle)
    angular_gain: float
    arw_dps_per_rt_hz: float | None  # if None: arw_deg_per_rt_h / 60
    arw_deg_per_rt_h: float
    bias_instability_deg_per_h: float  # IEEE 952 B: overlapping-ADEV floor / 0.664
    pickoff_noise_vrms_per_rt_hz: float  # per demod quadrature (docs/noise-budget.md: inferred)
    forcer_noise_v_per_rt_hz: float  # summing node + modulator, one-sided, not recorded (assumed)
    auxout_bits: int  # HF2 AuxOut DAC: bits over +-auxout_range_v (0 = ideal)
    auxout_range_v: float
    auxin_bits: int  # HF2 AuxIn ADC: bits over +-auxin_range_v (0 = ideal)
    auxin_range_v: float
    auxin_noise_v_rms: float  # white noise of one AuxIn reading (assumed)
    forcer_tempco_ppm_per_c: float
    frequency_tempco_ppm_per_c: float
    pickoff_electronics_tempco_ppm_per_c: float  # G_py/G_px at the front-end board temperature T_fe
    pickoff_transducer_tempco_ppm_per_c: float  # G_py/G_px at the die temperature T
    pickoff_ratio_tempco2_ppm_per_c2: float  # quadratic part at the die temperature
    frontend_thermal_tau_s: float  # T_fe follows T through this first-order lag (0: T_fe = T)
    reference_temperature_c: float
    loop_delay_us: float
    drive_voltage_v: float  # sustains drive_amplitude_vrms at T_ref
    sf_true_v_per_dps: float  # true FTR SF at T_ref, drive_amplitude_vrms, forcer gain 1
    drive_amplitude_vrms: float  # the drive amplitude at which sf_true applies
    # ---- deterministic non-idealities (docs/accuracy-budget.md: each value's origin and what the paper implies)
    q_tempco_ppm_per_c: float  # dQ/Q per degC; assumed (thermoelastic-limited silicon: Q falls with T)
    damping_mismatch_tempco_per_c: float  # d(Delta(1/tau)/(1/tau))/dT, per degC; assumed
    freq_mismatch_tempco_hz_per_c: float  # d(split)/dT, Hz per degC; assumed (sign unknown)
    forcer_bias_v: float  # proof-mass polarization voltage V_p on the sense forcer; assumed
    forcer_gap_um: float  # parallel-plate forcer gap g; assumed (deep-etched silicon class)
    drive_amplitude_um: float  # physical drive amplitude a at drive_amplitude_vrms; assumed
    forcer_electrode_v_per_v: float  # forcer AC amplitude per volt of command (paper: 10 V <-> 150 deg/s)
    feedthrough_v_per_v: float  # sense pickoff volts per forcer-electrode volt; assumed (EAM-suppressed)
    feedthrough_phase_deg: float  # feedthrough phase against the force (capacitive: into Y); assumed
    hf2_demod_ripple: bool  # carrier model: the demodulator filter's residual 2 omega term in the stream

    @classmethod
    def field_names(cls) -> frozenset[str]:
        """The names of the parameters (what `from_mapping` accepts)."""
        return frozenset(f.name for f in dataclasses.fields(cls))

    def noiseless(self, **values: Any) -> GyroParams:
        """This device (with `values` changed) with every noise source off and an ideal AuxOut DAC: the
        deterministic plant that the physics tests check against their equations."""
        return dataclasses.replace(self, **{**NOISE_OFF, **values})

    @classmethod
    def from_mapping(cls, d: Mapping[str, Any]) -> GyroParams:
        """Build from a mapping of every parameter name. A key this class does not know, or one it needs and
        does not find, is an error that names it: a misspelt parameter must not be silently dropped."""
        unknown = sorted(set(d) - cls.field_names())
        if unknown:
            raise ValueError(f"GyroParams: unknown parameters {unknown}; known: {sorted(cls.field_names())}")
        missing = sorted(cls.field_names() - set(d))
        if missing:
            raise ValueError(f"GyroParams: missing parameters {missing}")
        return cls(**d)

    @property
    def arw_rad_per_rt_s(self) -> float:
        """ARW N in rad/s/sqrt(Hz): per-sample rate sigma is N/sqrt(dt); ADEV(tau) = N/sqrt(tau)."""
        n_dps = self.arw_dps_per_rt_hz if self.arw_dps_per_rt_hz is not None else self.arw_deg_per_rt_h / 60.0
        return n_dps * RAD_PER_DEG

    @property
    def auxout_lsb_v(self) -> float:
        """AuxOut DAC step 2 range / 2^bits, V (0 = ideal DAC)."""
        return 2.0 * self.auxout_range_v / 2.0**self.auxout_bits if self.auxout_bits > 0 else 0.0

    @property
    def auxin_lsb_v(self) -> float:
        """AuxIn ADC step 2 range / 2^bits, V (0 = ideal ADC)."""
        return 2.0 * self.auxin_range_v / 2.0**self.auxin_bits if self.auxin_bits > 0 else 0.0

    @property
    def omega0_rad_s(self) -> float:
        return 2.0 * math.pi * self.f0_hz

    @property
    def tau_s(self) -> float:
        """tau = 2Q/omega0 at T_ref (173.6 s for the paper's device)."""
        return 2.0 * self.q_factor / self.omega0_rad_s

    @property
    def a0(self) -> float:
        """Nominal drive displacement amplitude, pickoff units (G_px = 1 V/unit): sqrt(2) R_d0."""
        return math.sqrt(2.0) * self.drive_amplitude_vrms

    @property
    def k_drive(self) -> float:
        """K_dx = 2 omega0 a0 / (tau0 V_d0): V_d0 sustains a0 at T_ref."""
        return 2.0 * self.omega0_rad_s * self.a0 / (self.tau_s * self.drive_voltage_v)

    @property
    def k_forcer(self) -> float:
        """K_f = 2 omega0 k a0 / SF_rad (SF in V per rad/s)."""
        return 2.0 * self.omega0_rad_s * self.angular_gain * self.a0 / (self.sf_true_v_per_dps * DEG_PER_RAD)

    @property
    def electrostatic_spring_ratio(self) -> float:
        """r = k_e / k_m: the forcer's electrostatic spring eps0 A V_p^2 / g^3 against the sense stiffness m omega0^2.

        The forcer's area A is not free: its 1-omega force eps0 A V_p v / g^2 at the electrode amplitude
        v = c_e u must rebalance the Coriolis force 2 m k omega0 a Omega at the command u = SF Omega, so
        eps0 A / g^2 = 2 m k omega0 a / (c_e SF_rad V_p) and the mass cancels:
        r = 2 k a V_p / (c_e SF_rad g omega0)   (a, g in metres; SF_rad in V per rad/s).
        """
        if self.forcer_bias_v == 0.0:
            return 0.0
        a_m, g_m = self.drive_amplitude_um * 1e-6, self.forcer_gap_um * 1e-6
        sf_rad = self.sf_true_v_per_dps * DEG_PER_RAD
        return (
            2.0
            * self.angular_gain
            * a_m
            * self.forcer_bias_v
            / (self.forcer_electrode_v_per_v * sf_rad * g_m * self.omega0_rad_s)
        )

    @property
    def forcer_cubic_per_v2(self) -> float:
        """beta: the forcer's gain grows as (1 + beta u^2) with the command amplitude u (V).

        Parallel-plate forcer at gap g, polarization V_p, AC amplitude v = c_e u (c_e = forcer_electrode_v_per_v):
        F = eps0 A (V_p + v cos wt)^2 / (2 (g - y)^2). Its 1-omega part eps0 A V_p v / (g - y)^2 is the rebalance
        force; its DC part eps0 A v^2 / (4 g^2) deflects the mass quasi-statically by y = eps0 A v^2 / (4 g^2 k_eff)
        (k_eff = k_m - k_e, the electrostatically softened stiffness), which narrows the gap:
        F_1w = (eps0 A V_p v / g^2)(1 + 2 y / g) = F_lin (1 + beta u^2),
        beta = c_e^2 eps0 A / (2 g^3 k_eff) = c_e^2 r / (2 V_p^2 (1 - r))   (r: electrostatic_spring_ratio)
             = c_e k a / (SF_rad V_p g omega0 (1 - r)).
        """
        if self.forcer_bias_v == 0.0:
            return 0.0
        r = self.electrostatic_spring_ratio
        return self.forcer_electrode_v_per_v**2 * r / (2.0 * self.forcer_bias_v**2 * (1.0 - r))

    def omega_rad_s(self, temperature_c: float) -> float:
        """Mean resonance omega(T) = omega0 (1 + alpha_w (T - T_ref))."""
        return self.omega0_rad_s * (
            1.0 + self.frequency_tempco_ppm_per_c * 1e-6 * (temperature_c - self.reference_temperature_c)
        )

    def q_at(self, temperature_c: float) -> float:
        """Q(T) = Q0 (1 + alpha_Q (T - T_ref))."""
        return self.q_factor * (1.0 + self.q_tempco_ppm_per_c * 1e-6 * (temperature_c - self.reference_temperature_c))

    def damping_mismatch_at(self, temperature_c: float) -> float:
        """Delta(1/tau)/(1/tau) at T: damping_mismatch + its tempco (T - T_ref)."""
        return self.damping_mismatch + self.damping_mismatch_tempco_per_c * (
            temperature_c - self.reference_temperature_c
        )

    def freq_mismatch_at_hz(self, temperature_c: float) -> float:
        """Mode split Delta f(T) = freq_mismatch_hz + its tempco (T - T_ref), Hz (signed)."""
        return self.freq_mismatch_hz + self.freq_mismatch_tempco_hz_per_c * (
            temperature_c - self.reference_temperature_c
        )

    def omega_x_rad_s(self, temperature_c: float) -> float:
        """Drive-mode resonance sqrt(K_xx) = sqrt(omega^2 + omega Delta_omega(T) cos 2 theta_omega)."""
        w = self.omega_rad_s(temperature_c)
        dw = 2.0 * math.pi * self.freq_mismatch_at_hz(temperature_c)
        return math.sqrt(w * w + w * dw * math.cos(2.0 * self.stiffness_axis_deg * RAD_PER_DEG))

    def forcer_gain_factor(self, temperature_c: float) -> float:
        """G_f(T) = 1 + alpha_f (T - T_ref)."""
        return 1.0 + self.forcer_tempco_ppm_per_c * 1e-6 * (temperature_c - self.reference_temperature_c)

    def sense_pickoff_gain(self, temperature_c: float, frontend_c: float | None = None) -> float:
        """G_py = 1 + alpha_t dT + alpha_2 dT^2 + alpha_e dT_fe (G_px = 1), dT = T - T_ref at the die, dT_fe at the
        front-end board (frontend_c; None: the board at the die temperature, the steady state)."""
        d = temperature_c - self.reference_temperature_c
        d_fe = d if frontend_c is None else frontend_c - self.reference_temperature_c
        return (
            1.0
            + self.pickoff_transducer_tempco_ppm_per_c * 1e-6 * d
            + self.pickoff_ratio_tempco2_ppm_per_c2 * 1e-6 * d * d
            + self.pickoff_electronics_tempco_ppm_per_c * 1e-6 * d_fe
        )

    def true_scale_factor(
        self, temperature_c: float, forcer_gain: float = 1.0, drive_amplitude_vrms: float | None = None
    ) -> float:
        """SF_true(T) = sf_true (omega_x/omega0) (a/a0) / (G_f(T) g), V per deg/s; a = sqrt2 R_sp / G_px."""
        r = self.drive_amplitude_vrms if drive_amplitude_vrms is None else drive_amplitude_vrms
        return (
            self.sf_true_v_per_dps
            * self.omega_x_rad_s(temperature_c)
            / self.omega0_rad_s
            * (r / self.drive_amplitude_vrms)
            / (self.forcer_gain_factor(temperature_c) * forcer_gain)
        )


NONIDEALITIES_OFF: dict[str, Any] = {
    "freq_mismatch_hz": 0.0,
    "q_tempco_ppm_per_c": 0.0,
    "damping_mismatch_tempco_per_c": 0.0,
    "freq_mismatch_tempco_hz_per_c": 0.0,
    "forcer_bias_v": 0.0,  # no electrostatic cubic (beta = 0)
    "feedthrough_v_per_v": 0.0,
    "hf2_demod_ripple": False,
}
"""GyroParams overrides that switch every deterministic electronics/physics non-ideality off (ideal-twin tests)."""


@dataclass
class PidSettings:
    """One HF2 PID in lock-in units: e = setpoint - input; out = center + p e + i int(e) dt + d de/dt,
    clamped to center +- range (integration stops while clamped); when disabled out = center."""

    enabled: bool = False
    p: float = 0.0
    i: float = 0.0
    d: float = 0.0
    setpoint: float = 0.0
    center: float = 0.0
    range: float = 10.0

    @classmethod
    def from_gains(cls, gains: Any, enabled: bool = True) -> PidSettings:
        """From any object with p, i, d, setpoint, center, range attributes (e.g. qmg_lab PidGains)."""
        return cls(
            enabled=enabled,
            p=float(gains.p),
            i=float(gains.i),
            d=float(getattr(gains, "d", 0.0)),
            setpoint=float(gains.setpoint),
            center=float(gains.center),
            range=float(gains.range),
        )


@dataclass
class PllSettings:
    """HF2 PLL: e = phase - setpoint (deg); f = center + p e + i int(e) dt, clamped to center +- range (Hz)."""

    enabled: bool = False
    p: float = 0.0
    i: float = 0.0
    setpoint_deg: float = 0.0
    center_hz: float = 2200.0
    range_hz: float = 22.0

    @classmethod
    def from_gains(cls, gains: Any, enabled: bool = True) -> PllSettings:
        """From any object with p, i, setpoint (deg), center (Hz), range (Hz) attributes (qmg_lab PidGains)."""
        return cls(
            enabled=enabled,
            p=float(gains.p),
            i=float(gains.i),
            setpoint_deg=float(gains.setpoint),
            center_hz=float(gains.center),
            range_hz=float(gains.range),
        )


@dataclass
class LoopSettings:
    """Everything the lock-in closes around the gyro, as the physics sees it."""

    pll: PllSettings = field(default_factory=PllSettings)
    agc: PidSettings = field(default_factory=PidSettings)
    rate: PidSettings = field(default_factory=PidSettings)
    quadrature: PidSettings = field(default_factory=PidSettings)
    forcer_gain: float = 1.0  # forcer-path gain (HF2 forcer carrier amplitude / nominal)
    demod_timeconstant_s: float = 1e-4
    demod_order: int = 1


MAX_DEMOD_ORDER = 8


def pack_loops(loops: LoopSettings) -> np.ndarray:
    """LoopSettings as the float64 vector the kernels read (layout: sims/gyro_kernel.py L_* indices)."""
    if not 1 <= int(loops.demod_order) <= MAX_DEMOD_ORDER:
        raise ValueError(f"LoopSettings.demod_order must be 1..{MAX_DEMOD_ORDER}, got {loops.demod_order!r}")
    if not (math.isfinite(loops.demod_timeconstant_s) and loops.demod_timeconstant_s > 0):
        raise ValueError(f"LoopSettings.demod_timeconstant_s must be > 0, got {loops.demod_timeconstant_s!r}")
    if not math.isfinite(loops.forcer_gain):
        raise ValueError(f"LoopSettings.forcer_gain must be finite, got {loops.forcer_gain!r}")
    pl = loops.pll
    vals = [float(pl.enabled), pl.p, pl.i, pl.setpoint_deg, pl.center_hz, pl.range_hz]
    for name in ("agc", "rate", "quadrature"):
        s: PidSettings = getattr(loops, name)
        vals += [float(s.enabled), s.p, s.i, s.d, s.setpoint, s.center, s.range]
    vals += [loops.forcer_gain, loops.demod_timeconstant_s, float(int(loops.demod_order))]
    arr = np.array(vals, dtype=np.float64)
    if not np.all(np.isfinite(arr)):
        raise ValueError("LoopSettings contain a non-finite number")
    if pl.range_hz < 0 or any(getattr(loops, n).range < 0 for n in ("agc", "rate", "quadrature")):
        raise ValueError("LoopSettings: PID/PLL ranges must be >= 0")
    return arr


@dataclass
class GyroBlock:
    """One block of simulated demod samples; every array has one entry per step, the value at the END of
    the step (what a demod sample reports). Demod outputs in Vrms: X + iY = G (C - iS)/sqrt(2)."""

    x_drive: np.ndarray
    y_drive: np.ndarray
    x_sense: np.ndarray
    y_sense: np.ndarray
    frequency_hz: np.ndarray  # PLL oscillator frequency
    drive_output_v: np.ndarray  # AGC PID output
    rate_output_v: np.ndarray  # rate PID output: the FTR rebalance command f_y
    quadrature_output_v: np.ndarray
    pll_error_deg: np.ndarray
    sf_true_v_per_dps: np.ndarray  # the instantaneous true FTR scale factor
    rate_true_dps: np.ndarray  # the true input rate (table, without gyro bias)
    pll_locked: bool  # PLL enabled and |pll_error| < PLL_LOCK_DEG over the whole block
    # the rate AuxOut voltage AT the sample instant (piecewise linear between instants, sims/gyro_kernel.py):
    # the PID value of the sample before; what a cable from the AuxOut to an AuxIn carries
    rate_auxout_v: np.ndarray | None = None

    def __len__(self) -> int:
        return int(self.x_drive.shape[0])


PLL_LOCK_DEG = 5.0
