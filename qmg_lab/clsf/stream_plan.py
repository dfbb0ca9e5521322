"""What a lock-in rate and a dither frequency mean for CLSF: samples per period, edge phases, filter attenuation.

The HF2 streams at its own discrete rates and the DS345 runs on its own crystal: a dither period is a
non-integer number of samples, N + phi. The CLSF estimator (qmg_lab/clsf/estimator.py) locates each edge from the
recorded dither; an edge that falls between two AuxIn readings is known only to within that gap, and the edge
tracker (qmg_lab/clsf/dither_edges.py) removes that error by fitting a line through the last FIT_EDGES edges. The fit
works when the edges' positions within the sample interval, frac(j (N + phi)) for j = 0..FIT_EDGES-1, cover the
interval: then the gap errors average out. When N + phi is close to a fraction p/q with a small q, the edges
come back to the same q positions and their error is a bias that no fit removes; it moves with the DS345's
timebase wander and enters the estimate as 48 (delta/T)^2 (delta: the edge-time error, T: the period). So a
configuration must leave the edge phases spread: `edge_phase_gap` is the largest gap between the sorted phases
(1/FIT_EDGES when they are perfectly spread, 1 when every edge sits at one phase), checked at the nominal ratio
and at the DS345's worst timebase offset.

Demodulator filter: H(s) = 1/(1 + s tc)^n (qmg_lab/clsf/demod_filter.py); its attenuation at the dither's odd
harmonics shows how much of the dither's shape reaches c_y (the estimator compensates it exactly; a strongly
attenuated dither only costs signal).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from qmg_lab.clsf.demod_filter import DemodFilter

# The HF2's demodulator rates as this project takes them: the binary ladder HF2_RATE_BASE_HZ / 2^k through the
# power-on 1800 Sa/s (900, 1800, 3600, 7200, ... Sa/s). *Assumed*: the HF2 documentation says a requested rate is
# approximated to the nearest supported value but does not list them; the driver reads the applied rate back,
# and `qmg-lab instruments` shows it, so a different ladder on a real HF2 shows up before a run.
HF2_RATE_BASE_HZ = 921.6e3
FIT_EDGES = 32
MAX_EDGE_PHASE_GAP = 0.25  # edges must visit every quarter of the sample interval within one fit window
DS345_WORST_OFFSET_PPM = 50.0  # timebase offsets a configuration must tolerate


def hf2_rate(requested_hz: float) -> float:
    """The HF2 rate nearest (in ratio) to a requested one, Sa/s."""
    k = max(1, round(math.log2(HF2_RATE_BASE_HZ / requested_hz)))
    return HF2_RATE_BASE_HZ / 2.0**k


def edge_phase_gap(samples_per_period: float, edges: int = FIT_EDGES) -> float:
    """Largest gap (fraction of a sample interval, circular) between the phases frac(j * samples_per_period)."""
    ph = np.sort(np.mod(np.arange(edges) * samples_per_period, 1.0))
    gaps = np.diff(np.concatenate((ph, [ph[0] + 1.0])))
    return float(np.max(gaps))


@dataclass(frozen=True)
class StreamPlan:
    """The CLSF's view of a rate, a dither frequency and a demodulator filter."""

    rate_hz: float
    dither_hz: float
    filter_order: int
    filter_tc_s: float

    @property
    def samples_per_period(self) -> float:
        return self.rate_hz / self.dither_hz

    def worst_edge_phase_gap(self, offset_ppm: float = DS345_WORST_OFFSET_PPM) -> float:
        """edge_phase_gap at the nominal ratio and across DS345 timebase offsets within +-offset_ppm."""
        n = self.samples_per_period
        ratios = n / (1.0 + np.linspace(-offset_ppm, offset_ppm, 41) * 1e-6)
        return max(edge_phase_gap(float(r)) for r in ratios)

    def harmonic_attenuation(self, harmonics: tuple[int, ...] = (1, 3, 5)) -> dict[int, float]:
        """|H| of the demodulator filter at the dither's odd harmonics."""
        filt = DemodFilter(self.filter_order, self.filter_tc_s)
        return {h: float(filt.gain(h * self.dither_hz)) for h in harmonics}

    def problem(self) -> str | None:
        """Why this combination cannot give a trustworthy CLSF, or None."""
        gap = self.worst_edge_phase_gap()
        if gap > MAX_EDGE_PHASE_GAP:
            n = self.samples_per_period
            return (
                f"{n:.4f} samples per dither period ({self.rate_hz:g} Sa/s / {self.dither_hz:g} Hz) is too close "
                f"to a simple fraction: the dither's edges keep landing at the same places between samples (phase "
                f"gap {gap:.2f} > {MAX_EDGE_PHASE_GAP} within {FIT_EDGES} edges, DS345 offsets up to "
                f"+-{DS345_WORST_OFFSET_PPM:g} ppm), so their timing cannot be refined; shift "
                "dither.frequency_hz by a few percent"
            )
        return None

    def summary(self) -> dict[str, float]:
        att = self.harmonic_attenuation()
        return {
            "rate_hz": self.rate_hz,
            "samples_per_period": self.samples_per_period,
            "edge_phase_gap": self.worst_edge_phase_gap(),
            "filter_delay_s": self.filter_order * self.filter_tc_s,
            **{f"filter_gain_h{h}": g for h, g in att.items()},
        }
