"""Carrier-level reference model of the QMG twin (cross-check only; campaigns use the averaged GyroSim).

The second-order plant q'' + D q' + K q + 2 k Omega J q' = f (docs/physics.md sections 1-3) is stepped at
`samples_per_cycle` >= 32 samples per f0 cycle with the exact 4x4 zero-order-hold step (sims/gyro_kernel.py
carrier_kernel); the drive and forcer commands are modulated onto the carrier with the PLL phase (mid-sample
phase, sinc-compensated DAC), the pickoffs are demodulated with a one-cycle boxcar I/Q demodulator, and the same
lock-in controller step (demod low-pass, PLL, AGC, rate and quadrature PIDs) runs once per demod sample.

One demod sample = one nominal carrier cycle = samples_per_cycle * dt_s = 1/f0; `run` takes one BlockInputs
entry per demod sample (World.advance(n, sim.demod_interval_s)) and returns a GyroBlock at that interval.
"""

from __future__ import annotations

import math

import numpy as np

from sims import gyro_kernel as gk
from sims.gyro import _TwinBase
from sims.gyro_params import GyroParams

MIN_SAMPLES_PER_CYCLE = 32


class CarrierGyroSim(_TwinBase):
    """Carrier-level model: dt_s = 1 / (samples_per_cycle * f0) with an integer samples_per_cycle >= 32."""

    def __init__(self, params: GyroParams, dt_s: float, seed: int) -> None:
        if not (isinstance(dt_s, (int, float)) and math.isfinite(dt_s) and dt_s > 0):
            raise ValueError(f"dt_s must be a finite number > 0, got {dt_s!r}")
        ratio = 1.0 / (dt_s * params.f0_hz)
        m = int(round(ratio))
        if abs(ratio - m) > 1e-6 * m or m < MIN_SAMPLES_PER_CYCLE:
            raise ValueError(
                f"dt_s = {dt_s!r} s gives {ratio:.6g} samples per f0 cycle: the carrier model needs "
                f"dt_s = 1/(M f0) with an integer M >= {MIN_SAMPLES_PER_CYCLE} (e.g. {1.0 / (32 * params.f0_hz)!r})"
            )
        self.samples_per_cycle = m
        super().__init__(params, dt_s, seed, step_s=m * dt_s)

    @property
    def demod_interval_s(self) -> float:
        """Interval between demod samples (outputs and input entries), s: one nominal carrier cycle."""
        return self.step_s

    def _init_carrier(self) -> None:
        """q = C cos(phi) + S sin(phi), q' = omega_r (-C sin(phi) + S cos(phi)) at phi = 0; q' stored / omega0."""
        s = self._S
        wr_over_w0 = s[gk.S_FREF] / self.params.f0_hz if s[gk.S_FREF] > 0 else 1.0
        s[gk.S_PHI] = 0.0
        s[gk.S_QX], s[gk.S_QY] = s[gk.S_CX], s[gk.S_CY]
        s[gk.S_UX], s[gk.S_UY] = wr_over_w0 * s[gk.S_SX], wr_over_w0 * s[gk.S_SY]

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
        used, err_max = gk.carrier_kernel(
            self._S,
            self._P,
            loops_vec,
            self._gm_a,
            self._gm_b,
            self.samples_per_cycle,
            temp,
            rate,
            dither,
            noise,
            gm,
            out,
        )
        return int(used), float(err_max)
