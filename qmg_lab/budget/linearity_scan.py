"""The paper's Fig. 2 (0.5 % FS RMS nonlinearity over +-5 deg/s) against the twin's documented sources, from the
analytic budget (qmg_lab/budget/sweep.py) without simulating: what each source would have to be to give a target
nonlinearity, and what that value does to the temperature sweep's CLSF accuracy (Fig. 6).

* Level protocol. The paper does not state the dwell, the settle or the order of its Fig. 2 levels. The loop tail
  (sweep.loop_tail_errors) is the twin's only source that reaches 0.5 % FS with a value of plausible order: a
  sense-mode split d = 2 pi df cos 2 theta_w leaves after every table step a slow closed-loop mode near -z
  (z = 1/tau_n, tau_n = 174 s), of size proportional to d^2. The level means of a staircase carry the sum of the
  earlier steps' tails; what is not a straight line in the rate is the decay between levels, so for a dwell T
  much shorter than 1/z the nonlinearity grows as T (first order in T z), and for T >> 1/z it vanishes.
  nonlinearity_pct_fs(cfg, protocol) evaluates one protocol.
* The split a target needs. split_for_nonlinearity_hz solves NL(df) = target (NL grows as df^2, monotonic).
* What the split does to the sweep. The same tail acts on every +-5 deg/s pair of the sweep: the reference pair 0
  starts from rest, later pairs from the periodic state of the alternating steps, and the tail's size follows
  d(T)^2 and the loop bandwidth w_c(T). accuracy_tempco_window finds the split tempcos (Hz/degC) that keep the
  campaign's accuracy at or below a bound.
* The other sources, in closed form (other_source_requirements): each acts linearly in its parameter, so the value
  a target needs is the parameter times target / (the source's nonlinearity alone); for an undithered converter of
  n bits over +-range, the rate output's quantisation error is uniform, RMS LSB/sqrt(12), LSB = 2 range / 2^n.

`python -m qmg_lab.budget.linearity_scan [CONFIG]` prints the scan as the markdown tables that
docs/accuracy-budget.md quotes ("Fig. 2's 0.5 %: the scan").
"""

from __future__ import annotations

import math
import sys
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

from scipy.optimize import brentq, minimize_scalar

from qmg_lab.budget.sweep import DETERMINISTIC_OFF, forcer_cubic_per_v2, sweep_accuracy
from qmg_lab.config.schema import Config, load_config

STAIRCASE_DPS = (-5.0, -4.0, -3.0, -2.0, -1.0, 0.0, 1.0, 2.0, 3.0, 4.0, 5.0)
INTERLEAVED_DPS = (0.0, 1.0, -1.0, 2.0, -2.0, 3.0, -3.0, 4.0, -4.0, 5.0, -5.0)
UP_DOWN_DPS = (0.0, 1.0, 2.0, 3.0, 4.0, 5.0, 4.0, 3.0, 2.0, 1.0, 0.0)
UP_AND_DOWN_DPS = (*UP_DOWN_DPS, *(-r for r in UP_DOWN_DPS[1:]))  # 0 up to +5, back, down to -5, back to 0
PAPER_NONLINEARITY_PCT_FS = 0.5
TABLE_RATE_ACCURACY_PPM = 100.0  # the 1291BR's rate accuracy, as the paper quotes it
TEMPCO_SPAN_HZ_PER_C = 0.02  # the scan's split-tempco range: +-0.02 Hz/degC, 9 ppm/degC of the 2.2 kHz resonance


@dataclass(frozen=True)
class LevelProtocol:
    """A level sweep: rates in the order they are applied (deg/s), each held dwell_s, the first settle_s unused."""

    name: str
    rates_dps: tuple[float, ...]
    dwell_s: float
    settle_s: float


PROTOCOLS = (
    LevelProtocol("staircase, 60 s levels (the default plan)", STAIRCASE_DPS, 60.0, 5.0),
    LevelProtocol("staircase, 20 s levels", STAIRCASE_DPS, 20.0, 2.0),
    LevelProtocol("staircase, 5 s levels, 0.5 s settle (Fig. 2-like)", STAIRCASE_DPS, 5.0, 0.5),
    LevelProtocol("staircase, 2 s levels, 0.5 s settle", STAIRCASE_DPS, 2.0, 0.5),
    LevelProtocol("staircase, 180 s levels", STAIRCASE_DPS, 180.0, 5.0),
    LevelProtocol("up and down, 60 s levels", UP_AND_DOWN_DPS, 60.0, 5.0),
    LevelProtocol("up and down, 5 s levels", UP_AND_DOWN_DPS, 5.0, 0.5),
    LevelProtocol("interleaved 0, +1, -1, ..., 60 s levels", INTERLEAVED_DPS, 60.0, 5.0),
)
"""The protocols the scan compares: the paper states none of them."""


def with_overrides(
    cfg: Config, sim: Mapping[str, float] | None = None, protocol: LevelProtocol | None = None
) -> Config:
    """cfg with [sim] values replaced and, if given, the plan's linearity levels, dwell and settle set to protocol's."""
    out = cfg
    if sim:
        out = out.model_copy(update={"sim": out.sim.model_copy(update=dict(sim))})
    if protocol is not None:
        plan = {"linearity_rates_dps": list(protocol.rates_dps), "dwell_s": protocol.dwell_s}
        out = out.model_copy(update={"plan": out.plan.model_copy(update={**plan, "settle_s": protocol.settle_s})})
    return out


def split_sim(split_hz: float, axis_deg: float, tempco_hz_per_c: float = 0.0) -> dict[str, float]:
    """The [sim] values of a mode split df (Hz) on the stiffness axis theta_w (deg) with tempco d df/dT (Hz/degC)."""
    return {
        "freq_mismatch_hz": split_hz,
        "stiffness_axis_deg": axis_deg,
        "freq_mismatch_tempco_hz_per_c": tempco_hz_per_c,
    }


def nonlinearity_pct_fs(cfg: Config, protocol: LevelProtocol | None = None) -> float:
    """Predicted `nonlinearity_rms_pct_fs` of `characterize linearity` (% FS) with the plan's or protocol's levels."""
    return sweep_accuracy(with_overrides(cfg, protocol=protocol)).nonlinearity_rms_pct_fs


def split_for_nonlinearity_hz(
    cfg: Config, target_pct_fs: float, *, axis_deg: float, protocol: LevelProtocol | None = None
) -> float:
    """The split df (Hz, tempco 0) whose loop tail, with cfg's other sources, gives target_pct_fs: NL(df) = target
    solved by bracketing (NL grows as df^2); NaN if no split up to 2 Hz (near the 2 Hz loops) reaches it."""

    def excess(df: float) -> float:
        return nonlinearity_pct_fs(with_overrides(cfg, split_sim(df, axis_deg)), protocol) - target_pct_fs

    lo, hi = 1e-3, 0.05
    if excess(lo) >= 0.0:
        return lo
    while excess(hi) < 0.0:
        if hi >= 2.0:
            return float("nan")
        lo, hi = hi, min(2.0, 2.0 * hi)
    return float(brentq(excess, lo, hi, xtol=1e-4))


@dataclass(frozen=True)
class TempcoWindow:
    """The paper campaign's accuracy against the split tempco at one split: its minimum, where, and the tempco
    interval [low, high] (Hz/degC) that keeps it at or below bound_ppm (NaN, NaN if none does)."""

    split_hz: float
    axis_deg: float
    min_accuracy_ppm: float
    tempco_at_min_hz_per_c: float
    bound_ppm: float
    low_hz_per_c: float
    high_hz_per_c: float

    @property
    def width_hz_per_c(self) -> float:
        return self.high_hz_per_c - self.low_hz_per_c


def accuracy_tempco_window(cfg: Config, split_hz: float, axis_deg: float, bound_ppm: float) -> TempcoWindow:
    """Scan the split tempco over +-TEMPCO_SPAN_HZ_PER_C: the sweep accuracy (`total_ppm`, the analysis' pair-0
    reference) is smooth in it with one minimum; the interval's edges are where it crosses bound_ppm."""

    def acc(tc: float) -> float:
        return sweep_accuracy(with_overrides(cfg, split_sim(split_hz, axis_deg, tc))).total_ppm

    span = TEMPCO_SPAN_HZ_PER_C
    best = minimize_scalar(acc, bounds=(-span, span), method="bounded", options={"xatol": 1e-5})
    tc_min, a_min = float(best.x), float(best.fun)
    if a_min > bound_ppm:
        return TempcoWindow(split_hz, axis_deg, a_min, tc_min, bound_ppm, float("nan"), float("nan"))

    def edge(far: float) -> float:
        if acc(far) <= bound_ppm:
            return far
        return float(brentq(lambda tc: acc(tc) - bound_ppm, tc_min, far, xtol=1e-5))

    return TempcoWindow(split_hz, axis_deg, a_min, tc_min, bound_ppm, edge(-span), edge(span))


NO_TEMPCOS: dict[str, float] = {
    "forcer_tempco_ppm_per_c": 0.0,
    "frequency_tempco_ppm_per_c": 0.0,
    "pickoff_electronics_tempco_ppm_per_c": 0.0,
    "pickoff_transducer_tempco_ppm_per_c": 0.0,
    "pickoff_ratio_tempco2_ppm_per_c2": 0.0,
    "q_tempco_ppm_per_c": 0.0,
    "damping_mismatch_tempco_per_c": 0.0,
    "freq_mismatch_tempco_hz_per_c": 0.0,
}
"""[sim] values that make the twin's gyro the same at every temperature."""


def startup_share_ppm(cfg: Config, split_hz: float, axis_deg: float, lead_in_pairs: int = 3) -> tuple[float, float]:
    """The split's sweep "accuracy" with nothing depending on temperature (NO_TEMPCOS, the other deterministic
    sources off): RMS over pairs j > k of e_j - e_k, e the budget's pair errors, against the analysis' reference
    k = 0 and against k = lead_in_pairs. Pair 0 follows the first step from rest, later pairs the alternating
    steps' periodic state: the difference is the tail's start-up, not a scale-factor change."""
    sim = {**DETERMINISTIC_OFF, **NO_TEMPCOS, **split_sim(split_hz, axis_deg)}
    err = sweep_accuracy(with_overrides(cfg, sim)).pair_errors_ppm

    def rms_from(k: int) -> float:
        rel = [e - err[k] for e in err[k + 1 :]]
        return math.sqrt(sum(r * r for r in rel) / len(rel))

    return rms_from(0), rms_from(lead_in_pairs)


def other_source_requirements(cfg: Config, target_pct_fs: float) -> dict[str, dict[str, float]]:
    """For each non-split source: its value in cfg, the nonlinearity it gives alone there, and the value target
    needs (each source's nonlinearity is linear in its parameter at these sizes).

    * table_rate_ripple_ppm: the once-per-revolution ripple.
    * forcer_cubic_per_v2: beta of the parallel-plate forcer.
    * table_level_error_ppm: a rate error of each level's own sign and size e (bounded by the specification), the
      worst case: residual RMS e RMS(Omega_j) / FS, so e = target FS / RMS(Omega_j).
    * converter_bits: an undithered n-bit converter over +-range carrying the rate output (the HF2 AuxOut, 16 bit
      over +-auxout_range_v): RMS error LSB / sqrt(12), LSB = 2 range / 2^n; the value is the n giving target.
    """
    sim = cfg.sim
    off = DETERMINISTIC_OFF
    out: dict[str, dict[str, float]] = {}
    ripple = with_overrides(cfg, {**off, "table_rate_ripple_ppm": 1000.0})
    per_ppm = sweep_accuracy(ripple).nonlinearity_rms_pct_fs / 1000.0
    out["table_rate_ripple_ppm"] = {
        "value": sim.table_rate_ripple_ppm,
        "alone_pct_fs": per_ppm * sim.table_rate_ripple_ppm,
        "needed": target_pct_fs / per_ppm,
    }
    cubic = with_overrides(cfg, {**off, "forcer_bias_v": sim.forcer_bias_v})
    beta = forcer_cubic_per_v2(cubic)
    nl_cubic = sweep_accuracy(cubic).nonlinearity_rms_pct_fs
    out["forcer_cubic_per_v2"] = {"value": beta, "alone_pct_fs": nl_cubic, "needed": beta * target_pct_fs / nl_cubic}
    rates = cfg.plan.linearity_rates_dps
    fs = max(abs(r) for r in rates)
    rms_rate = math.sqrt(sum(r * r for r in rates) / len(rates))
    out["table_level_error_ppm"] = {
        "value": TABLE_RATE_ACCURACY_PPM,
        "alone_pct_fs": TABLE_RATE_ACCURACY_PPM * 1e-6 * rms_rate / fs * 100.0,
        "needed": target_pct_fs / 100.0 * fs / rms_rate * 1e6,
    }
    span_v = 2.0 * sim.auxout_range_v
    full_v = sim.sf_true_v_per_dps * fs

    def converter_pct(bits: float) -> float:
        return 100.0 * span_v / 2.0**bits / math.sqrt(12.0) / full_v

    out["converter_bits"] = {
        "value": float(sim.auxout_bits),
        "alone_pct_fs": converter_pct(sim.auxout_bits) if sim.auxout_bits else 0.0,
        "needed": math.log2(span_v / (math.sqrt(12.0) * target_pct_fs / 100.0 * full_v)),
    }
    return out


def _markdown(cfg: Config) -> str:
    """The scan's tables (module docstring)."""
    lines = ["### Nonlinearity (% FS) of the split's loop tail, by level protocol (tempco 0)", ""]
    splits = ((0.1, 0.0), (0.3, 0.0), (0.3, 20.0))
    lines.append(
        "| protocol | " + " | ".join(f"{s} Hz at {a:g}°" for s, a in splits) + " | split for 0.25 % (axis 0) |"
    )
    lines.append("|---|" + "---|" * (len(splits) + 1))
    for p in PROTOCOLS:
        cells = [f"{nonlinearity_pct_fs(with_overrides(cfg, split_sim(s, a)), p):.3f}" for s, a in splits]
        need = split_for_nonlinearity_hz(cfg, PAPER_NONLINEARITY_PCT_FS / 2.0, axis_deg=0.0, protocol=p)
        lines.append(f"| {p.name} | " + " | ".join(cells) + f" | {need:.2f} Hz |")
    lines += ["", "### The split each figure needs, and the split tempco the paper campaign then tolerates", ""]
    lines.append(
        "| target (% FS) | axis | split (Hz) | min accuracy (ppm) at tempco (Hz/°C) "
        "| tempco interval for ≤ 525 ppm (Hz/°C) | its width (ppm/°C of f0) |"
    )
    lines.append("|---|---|---|---|---|---|")
    f0 = cfg.sim.f0_hz
    for target in (PAPER_NONLINEARITY_PCT_FS / 2.0, PAPER_NONLINEARITY_PCT_FS):
        for axis in (0.0, 20.0):
            df = split_for_nonlinearity_hz(cfg, target, axis_deg=axis)
            w = accuracy_tempco_window(cfg, df, axis, 1.5 * 350.0)
            interval, width = "none: the minimum is above the bound", "0"
            if not math.isnan(w.low_hz_per_c):
                interval = f"[{w.low_hz_per_c:+.4f}, {w.high_hz_per_c:+.4f}]"
                width = f"{w.width_hz_per_c / f0 * 1e6:.2f}"
            lines.append(
                f"| {target:g} | {axis:g}° | {df:.3f} | {w.min_accuracy_ppm:.0f} at {w.tempco_at_min_hz_per_c:+.4f} "
                f"| {interval} | {width} |"
            )
    lines += ["", "### The split's start-up share: its sweep accuracy with nothing depending on temperature", ""]
    lines.append("| split (Hz), axis 0 | against pair 0 (the analysis) | against pair 3 (a lead-in) |")
    lines.append("|---|---|---|")
    for df in (0.02, 0.1, 0.21, 0.3):
        from0, from3 = startup_share_ppm(cfg, df, 0.0)
        lines.append(f"| {df:g} | {from0:.0f} ppm | {from3:.0f} ppm |")
    lines += ["", "### The other sources: the value 0.5 % FS needs", ""]
    lines.append("| source | default | alone (% FS) | needed for 0.5 % FS |")
    lines.append("|---|---|---|---|")
    for name, row in other_source_requirements(cfg, PAPER_NONLINEARITY_PCT_FS).items():
        lines.append(f"| {name} | {row['value']:.3g} | {row['alone_pct_fs']:.2g} | {row['needed']:.3g} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    """Print the scan for CONFIG (default configs/paper_campaign.toml)."""
    args = sys.argv[1:] if argv is None else argv
    path = Path(args[0]) if args else Path(__file__).resolve().parents[2] / "configs" / "paper_campaign.toml"
    sys.stdout.write(_markdown(load_config(path)[0]))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
