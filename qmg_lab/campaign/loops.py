"""Loop design: PLL, AGC, rate (FTR) and quadrature PI gains from bandwidths, in the HF2LI's units.

Conventions (shared with the HF2 twin; see docs/wiring.md):

* Demodulator output X + iY = G (C - iS)/sqrt(2) for a pickoff signal C cos(phi) + S sin(phi) referenced to the
  PLL oscillator phase phi: Vrms, standard lock-in convention. Drive demod amplitude R_d = G_px a / sqrt(2).
* HF2 PID: e = setpoint - input, output = center + P e + I integral(e) (+ D de/dt), clamped to center +- range.
  Gains are signed by the sign of the plant, so that every loop is negative feedback.
* HF2 PLL: error e = phase - setpoint (deg), frequency = center + p e + i integral(e): for our phase convention
  (theta = atan2(Y, X), d(theta)/dt = 360 (f_drive - f_ref) deg/s) positive p, i lock.

Plants (slow-variable model, docs/physics.md sections 1-3):

* Rate loop. With FTR holding c_y ~ 0, the sense demod X_s obeys
  dX_s/dt = -X_s/tau - k R_d Omega + (k R_d / SF) G V,  SF the FTR scale factor in V per rad/s,
  V = rate command (V), G = forcer-path gain, b = k R_d / SF. Two PI designs (rate_loop_design, written in
  qmg_lab/config/rate_loop.py with the closed loop and its settle time, and imported here):
  "zero_on_pole", I = P (1/tau + 2 pi f_z): with f_z = 0 the zero cancels the envelope pole (paper eq. 5 with
  tau_cy = tau/2), the loop is b P / s, the closed loop first order with f_bw = b P / (2 pi); and
  "critically_damped" (the default): both closed-loop poles at -p, -3 dB at f_bw, no slow mode.
* Quadrature loop: dY_s/dt = -Y_s/tau - (k R_d / SF) V_q: same magnitude, opposite sign.
* AGC: dR_d/dt = -R_d/tau + b_d V_d with b_d = R_d0 / (tau V_d0), V_d0 the drive voltage that sustains the
  nominal amplitude. P = 2 pi f_agc / b_d, I = P (1/tau + 2 pi f_z,agc).
* PLL: second order, d(theta)/dt = 360 (f_x - f_ref): omega_n = 2 pi f_pll / 2 (15 Hz bandwidth ~ omega_n =
  2 pi 7.5), p = 2 zeta omega_n / 360 Hz/deg, i = omega_n^2 / 360 Hz^2/deg.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from qmg_lab.config.rate_loop import RatePiDesign, rate_loop_design
from qmg_lab.config.schema import Config, DeviceSection
from qmg_lab.instruments import LockInSetup, PidGains

DEG_PER_RAD = 180.0 / math.pi


def sf_v_per_rad_s(sf_v_per_dps: float) -> float:
    """Scale factor in V per rad/s from V per deg/s."""
    return sf_v_per_dps * DEG_PER_RAD


@dataclass(frozen=True)
class RatePlant:
    """First-order plant of the sense demod X under rebalance: b = k R_d / SF (Vrms/s per V), tau (s)."""

    b: float
    tau_s: float


def rate_plant(device: DeviceSection) -> RatePlant:
    return RatePlant(
        b=device.angular_gain * device.drive_amplitude_vrms / sf_v_per_rad_s(device.sf_nominal_v_per_dps),
        tau_s=device.tau_s,
    )


FORCER_PATH_PLAUSIBLE = (0.5, 2.0)  # rho_0 / b outside this: the forcer does not act as the configuration says


def forcer_path_problem(rho_ref: float, device: DeviceSection, forcer_gain: float = 1.0) -> str | None:
    """Words for a forcer path that cannot be the configured one, else None.

    The CLSF reference rho_0 (qmg_lab/clsf/estimator.py) measures beta of dX/dt = -X/tau + beta u - kappa Omega,
    the forcer path's gain; the loops were designed on b = k R_d / SF ([device]), which beta equals times the
    forcer gain in force, up to the device's spread and temperature (percent, not a factor). A ratio outside
    0.5-2 is a wiring or configuration fault: a forcer carrier on an oscillator that does not run at the drive
    frequency (no force: rho_0 ~ 0), a forcer output off or on another channel, an inverted forcer, or [device]
    constants off by more than a factor 2. Every SF figure of such a run would be meaningless.
    """
    b = rate_plant(device).b * forcer_gain
    ratio = rho_ref / b
    lo, hi = FORCER_PATH_PLAUSIBLE
    if lo <= ratio <= hi:
        return None
    return (
        f"the CLSF reference forcer-path gain rho_0 = {rho_ref:.4g} Vrms/(V s) is {ratio:.3g} times the plant gain "
        f"the loops were designed on, b = k R_d / SF = {b:.4g} ([device] angular_gain, drive_amplitude_vrms, "
        f"sf_nominal_v_per_dps; outside {lo:g}-{hi:g}): the forcer does not act as configured. Check that the "
        "forcer carrier runs on an oscillator locked to the drive (on an HF2 without MF, the oscillator of the "
        "forcer's output channel; [lockin] wiring), that the forcer output is on and on the sense electrode, its "
        "sign, and the [device] constants"
    )


def rate_pi(
    device: DeviceSection, bandwidth_hz: float, zero_offset_hz: float = 0.0, design: RatePiDesign = "zero_on_pole"
) -> PidGains:
    """FTR rate PI from rate_loop_design: P = w_l / b, I = P z. Output range = the forcer limit."""
    plant = rate_plant(device)
    loop = rate_loop_design(device, bandwidth_hz, design, zero_offset_hz)
    p = loop.gain_rad_s / plant.b
    return PidGains(p=p, i=p * loop.zero_rad_s, setpoint=0.0, center=0.0, range=device.max_forcer_v)


def quadrature_pi(device: DeviceSection, bandwidth_hz: float, design: RatePiDesign = "zero_on_pole") -> PidGains:
    """Quadrature PI on Y, the same plant as the rate loop's with gain -b, so the gains are negative: P = -w_l / b,
    I = P z (rate_loop_design at zero offset). Its slow mode would reach the rate output through a mode split."""
    plant = rate_plant(device)
    loop = rate_loop_design(device, bandwidth_hz, design)
    p = -loop.gain_rad_s / plant.b
    return PidGains(p=p, i=p * loop.zero_rad_s, setpoint=0.0, center=0.0, range=device.max_forcer_v)


def agc_pi(device: DeviceSection, bandwidth_hz: float, zero_offset_hz: float = 0.0) -> PidGains:
    """AGC PI on R of the drive demod -> drive amplitude (V): P = 2 pi f_agc / b_d, I = P (1/tau + 2 pi f_z).

    With the zero exactly on the envelope pole (f_z = 0) a step disturbance of the drive (the Coriolis term
    k Omega c_y after a table step) is rejected with the resonator's own time constant tau; a zero f_z above it
    makes the slow closed-loop pole about -(1/tau + 2 pi f_z).
    """
    b_d = device.drive_amplitude_vrms / (device.tau_s * device.drive_voltage_v)
    p = 2.0 * math.pi * bandwidth_hz / b_d
    i = p * (1.0 / device.tau_s + 2.0 * math.pi * zero_offset_hz)
    # The drive output sits at its sustaining value; centre the PID there so the integrator starts near it.
    return PidGains(
        p=p,
        i=i,
        setpoint=device.drive_amplitude_vrms,
        center=device.drive_voltage_v,
        range=min(device.max_forcer_v, 100 * device.drive_voltage_v),
    )


def pll_pi(f0_hz: float, bandwidth_hz: float, damping: float) -> PidGains:
    """PLL PI in Hz/deg and Hz^2/deg for a second-order loop of natural frequency 2 pi (bandwidth/2)."""
    wn = 2.0 * math.pi * bandwidth_hz / 2.0
    return PidGains(
        p=2.0 * damping * wn / 360.0, i=wn * wn / 360.0, setpoint=0.0, center=f0_hz, range=max(1.0, 0.01 * f0_hz)
    )


def lockin_setup(cfg: Config, forcer_gain: float = 1.0) -> LockInSetup:
    """The complete lock-in setup for a configuration."""
    dev, lp = cfg.device, cfg.loops
    pll = pll_pi(dev.f0_hz, lp.pll_bandwidth_hz, lp.pll_damping)
    return LockInSetup(
        f0_hz=dev.f0_hz,
        pll=pll,
        pll_range_hz=pll.range,
        agc=agc_pi(dev, lp.agc_bandwidth_hz, lp.agc_zero_offset_hz),
        rate=rate_pi(dev, lp.rate_bandwidth_hz, lp.rate_zero_offset_hz, lp.sense_pi_design),
        quadrature=quadrature_pi(dev, lp.quadrature_bandwidth_hz, lp.sense_pi_design),
        demod_rate_hz=cfg.lockin.demod_rate_hz,
        demod_timeconstant_s=cfg.lockin.demod_timeconstant_s,
        demod_order=cfg.lockin.demod_order,
        forcer_gain=forcer_gain,
        auxin_averaging=cfg.lockin.auxin_averaging,
    )
