"""Campaign plans: the list of steps a configuration asks for, and every command checked against the limits.

A plan is built and shown (`qmg-lab check`) before anything moves. Step kinds (stored in /steps/kind):

    lock      configure the lock-in, wait for PLL lock and settled loops
    dither    start the DS345 square wave; the CLSF reference level forms during this step
    soak      chamber to the start temperature, table at rest
    rate      a table dwell at table_rate_dps (the paper campaign alternates +R/-R while the chamber ramps)
    hold      table at rest, logging (Allan-deviation campaign)
    sine      sinusoidal table rate of amplitude table_rate_dps at sine_frequency_hz (bandwidth
              characterization; stored in the run file as "sine:<f>Hz")
    level     one constant rate of a linearity sweep
    return    table back to rest
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import StrEnum

from qmg_lab.config.schema import ALLAN_SEGMENT_S, Config, dither_amplitude_vpp
from qmg_lab.instruments import LimitError

# ALLAN_SEGMENT_S: checkpoint granularity of a long constant-temperature hold (defined beside the schema's bound
# of the plan's size, qmg_lab.config.schema.plan_step_bound)


class StepKind(StrEnum):
    """What a step does (the module docstring describes each kind)."""

    LOCK = "lock"
    DITHER = "dither"
    SOAK = "soak"
    RATE = "rate"
    HOLD = "hold"
    SINE = "sine"
    LEVEL = "level"
    RETURN = "return"


TABLE_MOVING_KINDS = frozenset({StepKind.RATE, StepKind.LEVEL, StepKind.RETURN, StepKind.SINE})


@dataclass(frozen=True)
class Step:
    """One checkpointed step. Times in s, rates in deg/s, temperatures in deg C, the sine frequency in Hz
    (0 unless kind is SINE)."""

    index: int
    kind: StepKind
    duration_s: float
    chamber_target_c: float
    chamber_ramp_c_per_min: float
    table_rate_dps: float = 0.0
    sine_frequency_hz: float = 0.0
    settle_s: float = 0.0

    @property
    def moves_table(self) -> bool:
        return self.kind in TABLE_MOVING_KINDS

    @property
    def label(self) -> str:
        """The step's name in /steps/kind of the run file: the kind, "sine:<f>Hz" for a sine step."""
        return f"sine:{self.sine_frequency_hz:.3f}Hz" if self.kind is StepKind.SINE else self.kind.value


@dataclass(frozen=True)
class _Draft:
    """A step before its index and the campaign-wide chamber ramp are known."""

    kind: StepKind
    duration_s: float
    target_c: float
    rate_dps: float = 0.0
    sine_frequency_hz: float = 0.0
    settle_s: float = 0.0


@dataclass(frozen=True)
class LimitCheck:
    what: str
    value: float
    low: float
    high: float
    unit: str

    @property
    def ok(self) -> bool:
        return self.low <= self.value <= self.high

    def describe(self) -> str:
        """The check in words: "table rate = 500 deg/s outside [0, 100] deg/s" ("within" when it passes)."""
        where = "within" if self.ok else "outside"
        return f"{self.what} = {self.value:g} {self.unit} {where} [{self.low:g}, {self.high:g}] {self.unit}"


def ramp_time_s(cfg: Config) -> float:
    """Chamber ramp duration: |T_end - T_start| / rate."""
    p = cfg.plan
    return abs(p.chamber_end_c - p.chamber_start_c) / p.chamber_ramp_c_per_min * 60.0


def build_plan(cfg: Config) -> list[Step]:
    """The steps of the campaign the configuration describes."""
    p, kind = cfg.plan, cfg.campaign.kind
    t_start, ramp = p.chamber_start_c, p.chamber_ramp_c_per_min
    steps = [_Draft(StepKind.LOCK, cfg.loops.lock_settle_s, t_start)]
    if cfg.clsf.mode != "off":
        ref_s = cfg.clsf.reference_periods / cfg.dither.frequency_hz + 2.0
        steps.append(_Draft(StepKind.DITHER, ref_s, t_start))
    if p.chamber_soak_s > 0:
        steps.append(_Draft(StepKind.SOAK, p.chamber_soak_s, t_start))
    if kind == "temperature_sweep":
        n_pairs = max(1, math.ceil((ramp_time_s(cfg) + p.chamber_end_hold_s) / (2.0 * p.dwell_s)))
        for _ in range(n_pairs):
            for sign in (1.0, -1.0):
                steps.append(
                    _Draft(StepKind.RATE, p.dwell_s, p.chamber_end_c, sign * p.table_rate_dps, 0.0, p.settle_s)
                )
    elif kind == "allan":
        remaining = p.duration_s
        pair = 2.0 * p.dwell_s if p.table_step_interval_s > 0 else 0.0
        seg = p.table_step_interval_s if p.table_step_interval_s > 0 else ALLAN_SEGMENT_S
        while remaining > 1e-9:
            hold = min(remaining, max(seg - pair, 0.0)) if pair else min(remaining, seg)
            if hold > 0:
                steps.append(_Draft(StepKind.HOLD, hold, t_start))
                remaining -= hold
            if pair and remaining > 1e-9:
                for sign in (1.0, -1.0):
                    d = min(p.dwell_s, remaining)
                    if d <= 0:
                        break
                    settle = min(p.settle_s, 0.5 * d)
                    steps.append(_Draft(StepKind.RATE, d, t_start, sign * p.table_rate_dps, 0.0, settle))
                    remaining -= d
                steps.append(_Draft(StepKind.RETURN, _return_s(cfg), t_start))
    elif kind == "bandwidth":
        steps.append(_Draft(StepKind.RATE, p.dwell_s, t_start, p.bandwidth_amplitude_dps, 0.0, p.settle_s))
        steps.append(_Draft(StepKind.RETURN, p.dwell_s, t_start))
        for f in p.bandwidth_frequencies_hz:
            dur = p.bandwidth_cycles / f + max(p.settle_s, 2.0 / f)
            settle = max(p.settle_s, 2.0 / f)
            steps.append(_Draft(StepKind.SINE, dur, t_start, p.bandwidth_amplitude_dps, f, settle))
    elif kind == "linearity":
        for r in p.linearity_rates_dps:
            steps.append(_Draft(StepKind.LEVEL, p.dwell_s, t_start, r, 0.0, p.settle_s))
    end_c = cfg.chamber.safe_setpoint_c if kind == "temperature_sweep" else t_start
    steps.append(_Draft(StepKind.RETURN, _return_s(cfg), end_c))
    # merge: a "return" directly after another "return" adds nothing
    out: list[Step] = []
    for draft in steps:
        if out and draft.kind is StepKind.RETURN and out[-1].kind is StepKind.RETURN:
            continue
        out.append(
            Step(
                index=len(out),
                kind=draft.kind,
                duration_s=float(draft.duration_s),
                chamber_target_c=float(draft.target_c),
                chamber_ramp_c_per_min=ramp,
                table_rate_dps=float(draft.rate_dps),
                sine_frequency_hz=float(draft.sine_frequency_hz),
                settle_s=float(draft.settle_s),
            )
        )
    return out


def _return_s(cfg: Config) -> float:
    """Long enough to decelerate from the largest rate and let the loop settle."""
    return max(2.0, cfg.plan.table_rate_dps / cfg.plan.table_accel_dps2 + 2.0)


def plan_duration_s(steps: list[Step]) -> float:
    return float(sum(s.duration_s for s in steps))


def limit_checks(cfg: Config, steps: list[Step]) -> list[LimitCheck]:
    """Every command of the plan against the instruments' limits (nothing is sent)."""
    t, c, g, p = cfg.table, cfg.chamber, cfg.generator, cfg.plan
    checks: list[LimitCheck] = []
    rates = [abs(s.table_rate_dps) for s in steps if s.moves_table]
    max_rate = max(rates, default=0.0)
    checks.append(LimitCheck("table rate", max_rate, 0.0, t.max_rate_dps, "deg/s"))
    checks.append(LimitCheck("table acceleration", p.table_accel_dps2, 0.0, t.max_accel_dps2, "deg/s^2"))
    for s in steps:
        if s.sine_frequency_hz > 0:
            acc = abs(s.table_rate_dps) * 2 * math.pi * s.sine_frequency_hz
            checks.append(
                LimitCheck(
                    f"step {s.index} sinusoid peak acceleration",
                    acc,
                    0.0,
                    min(t.max_accel_dps2, p.table_accel_dps2),
                    "deg/s^2",
                )
            )
    targets = sorted({s.chamber_target_c for s in steps} | {c.safe_setpoint_c})
    checks.append(LimitCheck("chamber setpoint (lowest)", targets[0], c.min_c, c.max_c, "degC"))
    checks.append(LimitCheck("chamber setpoint (highest)", targets[-1], c.min_c, c.max_c, "degC"))
    checks.append(LimitCheck("chamber ramp", p.chamber_ramp_c_per_min, 0.0, c.max_ramp_c_per_min, "degC/min"))
    if cfg.clsf.mode != "off":
        vpp = dither_amplitude_vpp(cfg)
        checks.append(LimitCheck("dither amplitude", vpp, 0.01, min(10.0, g.max_amplitude_vpp), "Vpp"))
        checks.append(LimitCheck("dither frequency", cfg.dither.frequency_hz, 1e-6, 30.2e6, "Hz"))
    sf = cfg.device.sf_nominal_v_per_dps
    peak_forcer = sf * (max_rate + (cfg.dither.virtual_rate_dps if cfg.clsf.mode != "off" else 0.0))
    checks.append(LimitCheck("peak forcer command (rate + dither)", peak_forcer, 0.0, cfg.device.max_forcer_v, "V"))
    return checks


@dataclass(frozen=True)
class CheckedPlan:
    """A configuration's steps that passed every limit check (made only by `checked_plan`): what a campaign
    runner executes. Checked once, where the plan is made, before any instrument is touched."""

    steps: tuple[Step, ...]

    @property
    def duration_s(self) -> float:
        return plan_duration_s(list(self.steps))


def checked_plan(cfg: Config) -> CheckedPlan:
    """build_plan, then assert_within_limits: LimitError names every limit the plan would break."""
    steps = build_plan(cfg)
    assert_within_limits(cfg, steps)
    return CheckedPlan(tuple(steps))


def assert_within_limits(cfg: Config, steps: list[Step]) -> None:
    """Raise LimitError naming every limit the plan would break."""
    bad = [ch for ch in limit_checks(cfg, steps) if not ch.ok]
    if bad:
        raise LimitError("the plan breaks instrument limits: " + "; ".join(ch.describe() for ch in bad))


__all__ = [
    "CheckedPlan",
    "LimitCheck",
    "Step",
    "assert_within_limits",
    "build_plan",
    "checked_plan",
    "limit_checks",
    "plan_duration_s",
    "ramp_time_s",
]
