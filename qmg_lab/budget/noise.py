"""The CLSF noise budget: the Allan deviation of the scale-factor estimate predicted from a configuration.

Equations and their derivation: docs/noise-budget.md. In short, for the ratio estimator of qmg_lab/clsf/estimator.py:

1. **Equation error.** Every noise source is written as an error n_Y in the sense equation Y = beta m + line
   (qmg_lab/clsf/estimator.py eq. 2), expressed as an angle theta_n = n_Y / kappa (rad). Its two-sided spectral density
   S_theta(f), rad^2/Hz, for f > 0:

   | source | S_theta(f) |
   |---|---|
   | ARW N (rad/s/sqrt(Hz), IEEE 952 S_Omega = N^2) | N^2 / (2 pi f)^2 |
   | bias instability B (IEEE 952 flicker S_Omega = B^2 / (2 pi f)) | B^2 / (2 pi f) / (2 pi f)^2 |
   | forcer-path voltage noise e_f (V/sqrt(Hz) one-sided, not recorded) | (e_f^2 / 2) / SF^2 / (2 pi f)^2 |
   | pickoff noise n (V/sqrt(Hz) one-sided per demod quadrature) | (n^2 / 2) / kappa^2, kappa = k R_d |
   | AuxIn reading noise of the rate record, sigma_a^2 = sigma^2 + lsb^2/12 | h sigma_a^2 cos^2(pi f h) / SF^2 / w^2 |

   The same AuxIn noise on the dither record moves the level step hi - lo the estimator reads per block: a
   block-constant error added as its own white level (`dither_level_q_sq`).

   w = 2 pi f, SF in V per rad/s, R_d the drive amplitude (Vrms), k the angular gain, h the stream's sample
   interval. AuxOut quantisation enters the forcer and the AuxIn record alike, so it cancels in the ratio (zero).

2. **One dither period.** The estimate projects the equation error on r, the filtered triangle with its mean and
   slope removed, and divides by the same projection of the forcer input's integral, which the closed rate loop
   shapes by its sensitivity S(s) = 1 - T(s), T the closed loop of the configured sense PI
   (qmg_lab.config.rate_loop.rate_loop_t; s / (s + w_c) for the zero-on-pole design, w_c = 2 pi rate bandwidth).
   With the triangle's Fourier coefficients 4 A / (pi^2 m^2) at the odd harmonics m f_d (A = Omega_v / (4 f_d))
   and the demodulator filter H, the per-period estimates are independent and white, of
   level (ADEV = q / sqrt(tau))

       q^2 = (pi^4 / (32 A^2)) sum_m S_theta(m f_d) |H_m|^4 / m^4 / (sum_m |H_m|^2 Re S_m / m^4)^2.

3. **The CLSF loop.** Observe mode: the estimate is q-white. Correct mode integrates eta into the forcer gain
   with time constant tau_c, applied once per block (delay d = block/2 + T_d/2): the estimate is the loop's
   error e = n / (1 + G), G(s) = exp(-s d) / (s tau_c), the self-calibrated SF follows -n G / (1 + G). Their Allan
   deviations follow from sigma^2(tau) = 4 int S_two(f) |E(f)|^2 sin^4(pi f tau) / (pi f tau)^2 df with
   S_two = q^2, evaluated numerically on the loop's exact transfer functions. Sources are independent, so
   variances add.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from qmg_lab.budget.sweep import SweepAccuracy, sweep_accuracy
from qmg_lab.clsf.stream_plan import hf2_rate
from qmg_lab.config.rate_loop import config_rate_loop, rate_loop_t
from qmg_lab.config.schema import Config

RAD_PER_DEG = math.pi / 180.0
RAD_S_PER_DEG_H = RAD_PER_DEG / 3600.0
TAUS_S = (1.0, 2.0, 5.0, 10.0, 20.0, 30.0, 60.0, 100.0, 200.0, 300.0, 600.0, 1000.0, 2000.0, 3000.0)
HARMONICS = 199  # odd harmonics summed (weights fall as 1/m^4 or faster)
PAPER_ADEV_PPM = {60.0: 30.0, 2000.0: 1.0}  # the paper's Fig. 7: 30 ppm after 1 min, 1 ppm after 2000 s
PPM = 1e6


@dataclass(frozen=True)
class SourceBudget:
    """One noise source: its configured value and where it comes from, and what it does to the CLSF."""

    name: str
    key: str  # the [sim] key holding the value
    value: float
    unit: str
    origin: str
    white_ppm_rt_s: float  # q: the per-period estimate's white level, ppm sqrt(s)
    adev_ppm: dict[float, float]  # the estimate's Allan deviation in the configured mode, ppm
    sf_adev_ppm: dict[float, float]  # the self-calibrated SF's (correct mode), ppm
    # the value that, alone, would give the paper's figure at each of its taus (inverse problem)
    value_for_paper: dict[float, float] = field(default_factory=dict)


@dataclass(frozen=True)
class NoiseBudget:
    """The CLSF Allan deviation predicted from a configuration: each source and the total."""

    mode: str
    taus_s: tuple[float, ...]
    sources: list[SourceBudget]
    adev_ppm: dict[float, float]
    sf_adev_ppm: dict[float, float]
    loop: dict[str, float]
    notes: list[str]
    accuracy: SweepAccuracy  # the temperature sweep's accuracy and the linearity (qmg_lab/budget/sweep.py)

    def dominant(self, tau_s: float) -> str:
        """Name of the source with the largest contribution at tau_s."""
        return max(self.sources, key=lambda s: s.adev_ppm[tau_s]).name

    def to_json(self) -> dict[str, Any]:
        def keyed(d: dict[float, float]) -> dict[str, float]:
            return {f"{t:g}": v for t, v in d.items()}

        total60 = self.adev_ppm.get(60.0, float("nan"))
        return {
            "mode": self.mode,
            "taus_s": list(self.taus_s),
            "adev_ppm": keyed(self.adev_ppm),
            "adev_self_calibrated_sf_ppm": keyed(self.sf_adev_ppm),
            "paper_adev_ppm": keyed(PAPER_ADEV_PPM),
            "dominant_at_60s": self.dominant(60.0) if 60.0 in self.adev_ppm else None,
            "sources": [
                {
                    "name": s.name,
                    "key": s.key,
                    "value": s.value,
                    "unit": s.unit,
                    "origin": s.origin,
                    "white_ppm_rt_s": s.white_ppm_rt_s,
                    "adev_ppm": keyed(s.adev_ppm),
                    "adev_self_calibrated_sf_ppm": keyed(s.sf_adev_ppm),
                    "share_of_variance_at_60s": (s.adev_ppm.get(60.0, 0.0) / total60) ** 2 if total60 > 0 else 0.0,
                    "value_for_paper": keyed(s.value_for_paper),
                }
                for s in self.sources
            ],
            "loop": self.loop,
            "notes": self.notes,
            "accuracy": self.accuracy.to_json(),
        }


# ---------------------------------------------------------------------------------------------- the estimator


def _harmonics() -> np.ndarray:
    return np.arange(1, 2 * HARMONICS, 2, dtype=np.float64)


def demod_filter_response(f_hz: np.ndarray, tc_s: float, order: int) -> np.ndarray:
    """H(i 2 pi f) = 1 / (1 + i 2 pi f tc)^order: the HF2 demodulator's cascade."""
    return 1.0 / (1.0 + 2j * math.pi * f_hz * tc_s) ** order


def rate_loop_sensitivity(f_hz: np.ndarray, bandwidth_hz: float) -> np.ndarray:
    """S = 1 / (1 + L), L = w_c / s: the share of the dither the forcer input keeps under the first-order
    (zero-on-pole) loop; noise_budget takes S = 1 - T of the configured loop."""
    s = 2j * math.pi * f_hz
    return s / (s + 2.0 * math.pi * bandwidth_hz)


def white_level_sq(
    s_theta: np.ndarray, virtual_rate_rad_s: float, dither_hz: float, h_m: np.ndarray, s_m: np.ndarray
) -> float:
    """q^2 (relative^2 s: ADEV = q / sqrt(tau)) of the per-period ratio estimate for an equation error of two-sided
    density s_theta (rad^2/Hz) at the odd harmonics m f_d (module docstring, step 2)."""
    m = _harmonics()
    amp = virtual_rate_rad_s / (4.0 * dither_hz)  # triangle amplitude A, rad
    h2 = np.abs(h_m) ** 2
    num = float(np.sum(s_theta * h2 * h2 / m**4))
    den = float(np.sum(h2 * np.real(s_m) / m**4))
    return math.pi**4 / (32.0 * amp * amp) * num / (den * den)


def dither_level_q_sq(sigma_sq_v2: float, vpp_v: float, h_s: float, h_m: np.ndarray, s_m: np.ndarray) -> float:
    """q^2 of the error the dither record's levels put into the estimate.

    The estimator takes the square wave's step hi - lo from each block's plateau readings
    (qmg_lab/clsf/dither_edges.py), about B/(2h) of each level in a block of B s: a relative error delta with
    variance 4 sigma_a^2 h / (B Vpp^2), constant over the block. It scales the reconstructed m_d, so rho moves by
    -delta sum(H m_d) r / sum(H m) r = -delta sum |H_m|^2/m^4 / sum |H_m|^2 Re S_m/m^4. White over blocks: q^2 =
    variance x B."""
    m = _harmonics()
    h2 = np.abs(h_m) ** 2
    gain = float(np.sum(h2 / m**4) / np.sum(h2 * np.real(s_m) / m**4))
    return gain * gain * 4.0 * sigma_sq_v2 * h_s / (vpp_v * vpp_v)


# ---------------------------------------------------------------------------------------------- the CLSF loop


def _allan_kernel(f: np.ndarray, tau: float) -> np.ndarray:
    x = math.pi * f * tau
    with np.errstate(invalid="ignore", divide="ignore"):
        k = np.sin(x) ** 4 / (x * x)
    return np.where(x > 0, k, 0.0)


def loop_adev(
    q_sq: float, taus: tuple[float, ...], mode: str, *, tau_c_s: float, delay_s: float, f_max_hz: float
) -> tuple[dict[float, float], dict[float, float]]:
    """(estimate, self-calibrated SF) Allan deviations, relative, for a white per-period estimate of level q^2.

    sigma^2(tau) = 4 int_0^inf q^2 |X(f)|^2 sin^4(pi f tau) / (pi f tau)^2 df, X = 1/(1+G) for the estimate and
    -G/(1+G) for the SF, G = exp(-i 2 pi f d) / (i 2 pi f tau_c); the estimate's integral is q^2/tau minus the part
    the loop removes, integrated up to f_max (the per-period series' Nyquist frequency)."""
    est: dict[float, float] = {}
    sf: dict[float, float] = {}
    for tau in taus:
        if mode != "correct":
            est[tau] = math.sqrt(q_sq / tau)
            sf[tau] = 0.0
            continue
        df = min(1.0 / (40.0 * tau), 1.0 / (40.0 * tau_c_s))
        f = np.arange(1, int(f_max_hz / df) + 1) * df
        s = 2j * math.pi * f
        g = np.exp(-s * delay_s) / (s * tau_c_s)
        e2 = np.abs(1.0 / (1.0 + g)) ** 2
        x2 = np.abs(g / (1.0 + g)) ** 2
        k = _allan_kernel(f, tau)
        removed = 4.0 * q_sq * float(np.sum((1.0 - e2) * k)) * df
        est[tau] = math.sqrt(max(q_sq / tau - removed, 0.0))
        sf[tau] = math.sqrt(4.0 * q_sq * float(np.sum(x2 * k)) * df)
    return est, sf


# ---------------------------------------------------------------------------------------------- the sources


def _sources(cfg: Config, f: np.ndarray, h_s: float) -> list[tuple[str, str, float, str, str, np.ndarray, float]]:
    """(name, key, value, unit, origin, S_theta at f, d q / d value scale exponent) for every source."""
    sim = cfg.sim
    sf_rad = sim.sf_true_v_per_dps / RAD_PER_DEG  # V per rad/s
    kappa = sim.angular_gain * cfg.device.drive_amplitude_vrms  # V per rad of angle, sense demod X
    w = 2.0 * math.pi * f
    arw = (sim.arw_dps_per_rt_hz if sim.arw_dps_per_rt_hz is not None else sim.arw_deg_per_rt_h / 60.0) * RAD_PER_DEG
    b = sim.bias_instability_deg_per_h * RAD_S_PER_DEG_H
    lsb = 2.0 * sim.auxin_range_v / 2.0**sim.auxin_bits if sim.auxin_bits > 0 else 0.0
    aux_sq = sim.auxin_noise_v_rms**2
    aux_kernel = h_s * np.cos(math.pi * f * h_s) ** 2 / sf_rad**2 / w**2
    return [
        (
            "angle random walk",
            "arw_deg_per_rt_h",
            sim.arw_deg_per_rt_h if sim.arw_dps_per_rt_hz is None else sim.arw_dps_per_rt_hz * 60.0,
            "deg/sqrt(h)",
            "paper (QMG ARW 0.02 deg/sqrt(h), open loop)",
            arw**2 / w**2,
            1.0,
        ),
        (
            "bias instability",
            "bias_instability_deg_per_h",
            sim.bias_instability_deg_per_h,
            "deg/h",
            "paper (0.2 deg/h); flicker S = B^2/(2 pi f) at the dither harmonics",
            b * b / w / w**2,
            1.0,
        ),
        (
            "pickoff noise",
            "pickoff_noise_vrms_per_rt_hz",
            sim.pickoff_noise_vrms_per_rt_hz,
            "V/sqrt(Hz)",
            "inferred from the paper's 30 ppm at 60 s (docs/noise-budget.md); HF2 input alone would be far lower",
            np.full(f.shape, 0.5 * sim.pickoff_noise_vrms_per_rt_hz**2 / kappa**2),
            1.0,
        ),
        (
            "forcer-path voltage noise",
            "forcer_noise_v_per_rt_hz",
            sim.forcer_noise_v_per_rt_hz,
            "V/sqrt(Hz)",
            "assumed (summing node and modulator); bounded by the paper's ARW (docs/noise-budget.md)",
            0.5 * sim.forcer_noise_v_per_rt_hz**2 / sf_rad**2 / w**2,
            1.0,
        ),
        (
            "AuxIn reading noise",
            "auxin_noise_v_rms",
            sim.auxin_noise_v_rms,
            "V rms",
            "assumed",
            aux_sq * aux_kernel,
            1.0,
        ),
        (
            "AuxIn quantisation",
            "auxin_bits",
            float(sim.auxin_bits),
            "bits",
            f"HF2 AuxIn {sim.auxin_bits} bit over +-{sim.auxin_range_v:g} V (HF2 specification as recalled); "
            "white while noise moves the record by more than a step",
            (lsb * lsb / 12.0) * aux_kernel,
            0.0,
        ),
        (
            "AuxOut quantisation",
            "auxout_bits",
            float(sim.auxout_bits),
            "bits",
            "HF2 AuxOut DAC; the AuxIn records the quantised voltage, so it cancels in the ratio",
            np.zeros(f.shape),
            0.0,
        ),
    ]


def sample_interval_s(cfg: Config) -> float:
    """The stream's sample interval: 1 / the HF2 rate the configured rate becomes."""
    return 1.0 / hf2_rate(cfg.lockin.demod_rate_hz)


def noise_budget(cfg: Config, sim_blocks: bool = False, taus: tuple[float, ...] = TAUS_S) -> NoiseBudget:
    """The CLSF Allan deviation predicted from cfg ([sim] noise values, [dither], [loops], [clsf], [lockin]).

    sim_blocks: the CLSF gain is applied once per `lockin.sim_poll_interval_s` block (the twins) instead of
    `lockin.poll_interval_s` (the bench); it moves only the loop delay."""
    f_d = cfg.dither.frequency_hz
    m = _harmonics()
    f = m * f_d
    h = demod_filter_response(f, cfg.lockin.demod_timeconstant_s, cfg.lockin.demod_order)
    s_m = 1.0 - rate_loop_t(config_rate_loop(cfg), 1.0 / cfg.device.tau_s, 2j * math.pi * f)
    omega_v = cfg.dither.virtual_rate_dps * RAD_PER_DEG
    h_s = sample_interval_s(cfg)
    block = cfg.lockin.sim_poll_interval_s if sim_blocks else cfg.lockin.poll_interval_s
    delay = 0.5 * block + 0.5 / f_d
    mode = cfg.clsf.mode
    f_max = 0.5 * f_d
    out: list[SourceBudget] = []
    total_est = dict.fromkeys(taus, 0.0)
    total_sf = dict.fromkeys(taus, 0.0)
    sim = cfg.sim
    lsb = 2.0 * sim.auxin_range_v / 2.0**sim.auxin_bits if sim.auxin_bits > 0 else 0.0
    level_var = {"auxin_noise_v_rms": sim.auxin_noise_v_rms**2, "auxin_bits": lsb * lsb / 12.0}
    vpp = 2.0 * cfg.dither.virtual_rate_dps * sim.sf_true_v_per_dps
    for name, key, value, unit, origin, s_theta, linear in _sources(cfg, f, h_s):
        q_sq = white_level_sq(s_theta, omega_v, f_d, h, s_m)
        if key in level_var:
            q_sq += dither_level_q_sq(level_var[key], vpp, h_s, h, s_m)
        est, sf = loop_adev(q_sq, taus, mode, tau_c_s=cfg.clsf.time_constant_s, delay_s=delay, f_max_hz=f_max)
        inverse: dict[float, float] = {}
        if linear and value > 0:
            for tau_p, ppm_p in PAPER_ADEV_PPM.items():
                got = (
                    loop_adev(q_sq, (tau_p,), mode, tau_c_s=cfg.clsf.time_constant_s, delay_s=delay, f_max_hz=f_max)[0][
                        tau_p
                    ]
                    * PPM
                )
                inverse[tau_p] = value * ppm_p / got if got > 0 else float("inf")
        for t in taus:
            total_est[t] += est[t] ** 2
            total_sf[t] += sf[t] ** 2
        out.append(
            SourceBudget(
                name=name,
                key=key,
                value=value,
                unit=unit,
                origin=origin,
                white_ppm_rt_s=math.sqrt(q_sq) * PPM,
                adev_ppm={t: v * PPM for t, v in est.items()},
                sf_adev_ppm={t: v * PPM for t, v in sf.items()},
                value_for_paper=inverse,
            )
        )
    notes = []
    if cfg.plan.table_step_interval_s > 0 and cfg.campaign.kind == "allan":
        notes.append(
            "the plan steps the table during the Allan run: the hold windows and the steps' disturbance of CLSF are "
            "not in this budget (it assumes the table at rest)"
        )
    if mode == "off":
        notes.append("CLSF is off: no estimate")
    return NoiseBudget(
        mode=mode,
        accuracy=sweep_accuracy(cfg),
        taus_s=tuple(taus),
        sources=out,
        adev_ppm={t: math.sqrt(v) * PPM for t, v in total_est.items()},
        sf_adev_ppm={t: math.sqrt(v) * PPM for t, v in total_sf.items()},
        loop={
            "dither_hz": f_d,
            "virtual_rate_dps": cfg.dither.virtual_rate_dps,
            "rate_bandwidth_hz": cfg.loops.rate_bandwidth_hz,
            "clsf_time_constant_s": cfg.clsf.time_constant_s,
            "clsf_update_delay_s": delay,
            "sample_interval_s": h_s,
            "kappa_v_per_rad": cfg.sim.angular_gain * cfg.device.drive_amplitude_vrms,
            "sf_v_per_dps": cfg.sim.sf_true_v_per_dps,
        },
        notes=notes,
    )
