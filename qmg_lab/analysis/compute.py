"""The paper's results from any run file: true vs CLSF scale factor, CLSF precision, gyro noise, FTR figures.

Procedures (docs/physics.md sections 7-8; docs/hdf5.md for the data):

* Analysis windows. Each completed step contributes [t_start + settle, t_end], settle = max([plan] settle_s of
  the stored configuration, the configured rate loop's time to within e^-5 of the end of a step from its step
  response: 1.33 s critically damped, 0.40 s first order at 2 Hz; qmg_lab/analysis/reductions.py
  analysis_settle_s); sine steps also wait 2 periods. For a
  rate or level step that moves the table, t_start and t_end are the ends of the table's constant-rate plateau
  seen by its encoder on the HF2's clock (/lockin/table_encoder, qmg_lab/analysis/encoder.py) when the file has
  it and [table] encoder_on_dio is on; otherwise the host's step times.
  Means of the rate output are taken over a whole number of dither periods, from a rising edge of the recorded
  dither to a later one (edges located as the CLSF estimator locates them, qmg_lab/clsf/dither_edges.py: within the
  gap between two readings, then refined by a line through 32 edges; the rate output
  integrated with the trapezoid rule between them), so the dither leaking through the rate loop
  (|T(7 Hz)| = 0.23 of the virtual rate with the default critically damped loop) cancels whether or not a
  period is a whole number of samples: the DS345 and the HF2 share no clock.
* True SF from a step pair (a completed "rate" step with Omega > 0 followed by the next-index "rate" step with
  Omega < 0): SF = (O+ - O-)/(Omega+ - Omega-), bias = (O+ + O-)/2; O = mean /lockin/rate_output (V), Omega =
  the encoder's rate over the window (the slope of its count against time), else the median /table/rate_command
  over the window (deg/s; the step's table_rate if no table row falls inside).
* Relative changes against the first pair (SF_ref = SF of pair 0): true e_i = SF_i/SF_ref - 1; CLSF
  c_i = (1 + s_i)/(1 + s_0) - 1 with s_i the mean /clsf/sf_change_estimate over the same two windows; twin truth
  t_i = mean /truth/scale_factor re-referenced the same way. CLSF accuracy = RMS(c_i - e_i) over pairs 1..n-1
  (pair 0 is zero by construction), reported with and without the mean of (c - e) removed.
  truth_check_rms_ppm = RMS(e_i - t_i): the analysis itself checked against the twin; clsf_vs_truth_rms_ppm =
  RMS(c_i - t_i) over pairs 1..n-1: the estimator against the twin's truth, without the table steps' noise.
  The c_i and both RMS figures are `series_accuracy` of /clsf/sf_change_estimate: any other SF-change series
  (a calibrated one) is judged by the same function, and no table step enters the series it judges.
* Table-step noise (predicted): the truth check's expected RMS from the gyro's own noise, read off the ADEV of
  the static segment (below) at each window's length, sqrt(mean_(i >= 1) var_i + var_0) with var_i =
  (sigma_A^2(T+) + sigma_A^2(T-))/(Omega+ - Omega-)^2 (qmg_lab/analysis/table_noise.py): how good the table steps
  can be as a judge.
* CLSF precision: overlapping ADEV of sf_change_estimate (one value per dither period; gaps from CLSF holds are
  closed up), in ppm, with 68 % confidence bounds (qmg_lab/analysis/adev.py). In correct mode the same series is the
  residual of the self-calibrated SF; the ADEV of ln(gain_correction) is given too (the drift it removed).
* Gyro noise: the longest run of consecutive completed "hold" steps (else "soak"): the dither-free
  per-period rate output (/clsf/rate_output_mean, else /lockin/rate_output averaged per dither period) / SF in
  deg/h; ARW = sigma(1 s)/60 deg/sqrt(h), bias instability = min sigma / 0.664 deg/h.
* Bandwidth, settling, linearity: qmg_lab/analysis/characterize.py.
* Completeness: planned steps (root attr planned_steps / planned_step_kinds) minus completed steps = missing.

Why one module of this length: every procedure reads the same loaded run (its context: configuration, steps,
edges, windows) and returns its part of one result; the rendering (render.py) and the characterization
procedures (characterize.py) are already apart.
"""

from __future__ import annotations

import math
import re
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from qmg_lab.analysis.adev import AllanResult, arw_deg_per_rt_h, bias_instability_deg_per_h, overlapping_adev
from qmg_lab.analysis.characterize import (
    BodePoint,
    bandwidth_3db,
    fit_sinusoid,
    linearity,
    moving_average,
    settling_time_s,
)
from qmg_lab.analysis.encoder import EncoderTrack, Plateau, decode_quadrature, plateau, rate_over
from qmg_lab.analysis.reductions import (
    WindowSums,
    analysis_settle_s,
    edges_and_integrals,
    mean_between_edges,
    rate_pairs,
)
from qmg_lab.analysis.table_noise import PairWindows, table_step_noise
from qmg_lab.clsf.dither_edges import edge_threshold_v
from qmg_lab.config.schema import Config, ConfigError, dither_amplitude_vpp, parse_config
from qmg_lab.storage.layout import RUN_CONTEXT_ATTRS
from qmg_lab.storage.reader import RunData, read_run
from qmg_lab.storage.study_level import read_summary

_SINE = re.compile(r"^sine:([0-9.eE+-]+)Hz$")
PPM = 1e6


@dataclass
class StepPair:
    """One +/- rate step pair: times in s since t0, SF in V per deg/s, changes in ppm (NaN if unavailable)."""

    index_plus: int
    index_minus: int
    t_mid_s: float
    temperature_c: float
    sf_v_per_dps: float
    bias_v: float
    true_change_ppm: float = float("nan")
    clsf_change_ppm: float = float("nan")
    truth_change_ppm: float = float("nan")
    gyro_temperature_c: float = float("nan")
    rate_plus_dps: float = float("nan")
    rate_minus_dps: float = float("nan")
    output_plus_v: float = float("nan")
    output_minus_v: float = float("nan")
    window_plus_s: tuple[float, float] = (float("nan"), float("nan"))  # the two analysis windows, s
    window_minus_s: tuple[float, float] = (float("nan"), float("nan"))


@dataclass(frozen=True)
class SeriesAccuracy:
    """How well a series of relative SF changes follows the table steps and the twin's truth (`series_accuracy`),
    ppm; None where there is no truth. n_pairs: the step pairs compared (pair 0 is the reference)."""

    n_pairs: int
    rms_vs_table_ppm: float
    rms_vs_table_ppm_mean_removed: float
    rms_vs_truth_ppm: float | None
    change_ppm: list[float]  # the series' change at each pair, referred to pair 0


def series_accuracy(pairs: list[StepPair], time_s: np.ndarray, sf_change: np.ndarray) -> SeriesAccuracy:
    """Judge an SF-change series (SF/SF0 - 1 at the instants time_s, s on the file's time axis: /clsf's
    sf_change_estimate, or any calibrated series) by the step pairs of `analyze` (AnalysisResult.pairs).

    The table judges and does not teach: the series is taken as given, the steps only read. For each pair i,
    s_i = mean of the series over its two windows (the encoder-timed ones when the file has the encoder),
    c_i = (1 + s_i)/(1 + s_0) - 1; against the table e_i (true_change_ppm), RMS(c_i - e_i) over pairs 1..n-1,
    with and without its mean; against the twin's truth t_i (truth_change_ppm), RMS(c_i - t_i).
    """
    group = {"time": np.asarray(time_s, dtype=np.float64), "s": np.asarray(sf_change, dtype=np.float64)}
    raw = np.array([_mean_in(group, "s", [p.window_plus_s, p.window_minus_s]) for p in pairs])
    if raw.size == 0:
        return SeriesAccuracy(0, float("nan"), float("nan"), None, [])
    c = ((1 + raw) / (1 + raw[0]) - 1) * PPM
    e = np.array([p.true_change_ppm for p in pairs])
    tr = np.array([p.truth_change_ppm for p in pairs])
    d = (c - e)[1:]
    d = d[np.isfinite(d)]
    vs_truth = _rms((c - tr)[1:]) if np.all(np.isfinite(tr)) else None
    return SeriesAccuracy(
        n_pairs=len(pairs),
        rms_vs_table_ppm=_rms(d) if d.size else float("nan"),
        rms_vs_table_ppm_mean_removed=_rms(d - d.mean()) if d.size else float("nan"),
        rms_vs_truth_ppm=vs_truth,
        change_ppm=[float(x) for x in c],
    )


def evaluate_sf_series(path: str | Path, time_s: np.ndarray, sf_change: np.ndarray) -> SeriesAccuracy:
    """`series_accuracy` of a series against the step pairs `analyze(path)` finds in a run file."""
    return series_accuracy(analyze(path).pairs, time_s, sf_change)


@dataclass(frozen=True)
class AnalysisResult:
    """Everything `analyze` found (immutable); `to_json` gives the stable JSON (NaN -> null)."""

    file: str
    status: str
    abort_reason: str
    mode: str
    campaign_kind: str
    clsf_mode: str
    steps_planned: int | None
    steps_completed: int
    missing_steps: list[dict[str, Any]]
    sf_nominal_v_per_dps: float
    #: who ran it, on which device, why: the file's root attributes (storage.layout.RUN_CONTEXT_ATTRS), "" if absent
    run_context: dict[str, str] = field(default_factory=dict)
    sf_measured_v_per_dps: float = float("nan")
    n_step_pairs: int = 0
    pairs: list[StepPair] = field(default_factory=list)
    sf_true_change_ppm: float = float("nan")
    clsf_accuracy_rms_ppm: float = float("nan")
    clsf_accuracy_rms_ppm_mean_removed: float = float("nan")
    sf_tempco_ppm_per_c: float = float("nan")
    clsf_tempco_ppm_per_c: float = float("nan")
    truth_check_rms_ppm: float | None = None
    clsf_vs_truth_rms_ppm: float | None = None
    #: the truth check's expected RMS from the gyro's own noise (qmg_lab/analysis/table_noise.py), ppm: the judge's
    #: noise, with the 68 % bounds of the ADEV it reads and pair 0's share; None without a static segment
    table_step_noise_ppm: float | None = None
    table_step_noise_ppm_low: float | None = None
    table_step_noise_ppm_high: float | None = None
    table_step_noise_pair0_ppm: float | None = None
    adev: list[dict[str, float]] = field(default_factory=list)
    adev_at_60s_ppm: float = float("nan")
    adev_at_2000s_ppm: float = float("nan")
    adev_gain_correction: list[dict[str, float]] = field(default_factory=list)
    gyro_adev_deg_per_h: list[dict[str, float]] = field(default_factory=list)
    arw_deg_per_rt_h: float = float("nan")
    bias_instability_deg_per_h: float = float("nan")
    bode: list[BodePoint] = field(default_factory=list)
    bandwidth_hz: float = float("nan")
    phase_reference: str = ""
    settling_time_s: float = float("nan")
    linearity: dict[str, Any] = field(default_factory=dict)
    levels: list[dict[str, float]] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)

    def to_json(self) -> dict[str, Any]:
        d = asdict(self)
        d["adev"] = [
            {"tau_s": r["tau_s"], "ppm": r["value"], "ppm_low": r["low"], "ppm_high": r["high"]} for r in self.adev
        ]
        return _clean(d)


def _clean(x: Any) -> Any:
    if isinstance(x, dict):
        return {k: _clean(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_clean(v) for v in x]
    if isinstance(x, (float, np.floating)):
        return float(x) if math.isfinite(x) else None
    if isinstance(x, np.integer):
        return int(x)
    if isinstance(x, np.ndarray):
        return _clean(x.tolist())
    return x


@dataclass
class _Found:
    """What one procedure of `analyze` found: AnalysisResult fields by name, its notes, and the rows it collected
    (step pairs, Bode points, linearity levels). `applied_to` gives the result with them."""

    values: dict[str, Any] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)
    pairs: list[StepPair] = field(default_factory=list)
    bode: list[BodePoint] = field(default_factory=list)
    levels: list[dict[str, float]] = field(default_factory=list)

    def applied_to(self, res: AnalysisResult) -> AnalysisResult:
        changes: dict[str, Any] = dict(self.values)
        changes.update((k, v) for k, v in (("pairs", self.pairs), ("bode", self.bode), ("levels", self.levels)) if v)
        return replace(res, **changes, notes=[*res.notes, *self.notes])


# ---------------------------------------------------------------------------------------------------------------


def stored_config(run: RunData) -> tuple[Config, str | None]:
    """The configuration the run was made with (its config_toml attribute), validated; if it cannot be used
    (an older schema, a damaged attribute), the defaults and a note saying so, for the analysis to report."""
    try:
        return parse_config(str(run.attrs.get("config_toml", "")), f"{run.path}:config_toml"), None
    except ConfigError as exc:
        return Config(), f"stored configuration not usable ({exc}); defaults assumed"


@dataclass
class _Ctx:
    run: RunData
    cfg: Config
    fs_hz: float
    period_samples: int  # the nearest whole number of lock-in samples per dither period (1 if no dither)
    settle_s: float
    steps: dict[int, dict[str, Any]]  # completed steps by index
    notes: list[str]
    dither_rising_s: np.ndarray | None = None  # rising edges of the recorded dither, s
    edge_integral: np.ndarray | None = None  # the rate output's trapezoid integral at each rising edge, V s
    windows: dict[int, dict[str, float]] | None = None  # the truth over each step's window (/windows), by index
    study_level: bool = False  # a study-level file: edges and windows from its /edges and /windows
    encoder: EncoderTrack | None = None  # the table's encoder (/lockin/table_encoder), decoded
    plateaus: dict[int, Plateau] = field(default_factory=dict)  # each moving step's plateau, by index


def _load(path: str | Path) -> _Ctx:
    run = read_run(
        path,
        select=["lockin/rate_output", "lockin/dither", "lockin/table_encoder", "clsf", "table", "chamber", "truth"],
    )
    cfg, note = stored_config(run)
    notes: list[str] = [note] if note else []
    t = run.groups["lockin"]["time"]
    fs = 1.0 / float(np.median(np.diff(t))) if t.shape[0] > 2 else cfg.lockin.demod_rate_hz
    period = 1
    if cfg.clsf.mode != "off":
        period = max(1, int(round(fs / cfg.dither.frequency_hz)))
    settle = analysis_settle_s(cfg)
    steps: dict[int, dict[str, Any]] = {}
    s = run.steps
    for i in range(s["index"].shape[0]):
        if s["status"][i] == "completed":
            steps[int(s["index"][i])] = {k: s[k][i] for k in s}
    ctx = _Ctx(run, cfg, fs, period, settle, steps, notes)
    lk = run.groups["lockin"]
    summary = read_summary(run.path)
    if summary is not None:  # study storage level (qmg_lab/campaign/study_level.py): the reductions as written
        ctx.study_level = True
        ctx.windows = summary.window_rows()
        if cfg.clsf.mode != "off":
            ctx.dither_rising_s = summary.edges["time"]
            ctx.edge_integral = summary.edges["rate_integral"]
        notes.append("study-level file: step means from /edges and /windows, settling from its one raw step")
        return ctx
    if cfg.clsf.mode != "off" and "dither" in lk:  # the same reductions over the whole columns
        ctx.dither_rising_s, ctx.edge_integral = edges_and_integrals(
            t, lk["dither"], lk["rate_output"], edge_threshold_v(dither_amplitude_vpp(cfg))
        )
    _find_plateaus(ctx)
    truth = run.groups.get("truth")
    if truth is not None:
        ctx.windows = {i: _truth_window(truth, i, *_window(ctx, step)) for i, step in steps.items()}
    return ctx


def _find_plateaus(ctx: _Ctx) -> None:
    """The table encoder's plateau of every completed rate/level step that moves the table (encoder.py), when
    [table] encoder_on_dio says the encoder is cabled and the file has its column; otherwise a note."""
    lk, tab = ctx.run.groups["lockin"], ctx.cfg.table
    if not tab.encoder_on_dio or "table_encoder" not in lk:
        ctx.notes.append("step windows on the host's step times (no table encoder in the file)")
        return
    track = decode_quadrature(
        lk["time"], lk["table_encoder"], tab.encoder_a_dio_bit, tab.encoder_b_dio_bit, tab.encoder_lines_per_rev
    )
    ctx.encoder = track
    for i, step in ctx.steps.items():
        if step["kind"] in ("rate", "level") and step["table_rate"] != 0:
            p = plateau(track, float(step["t_start"]), float(step["t_end"]))
            if p is not None and p.rate_dps * float(step["table_rate"]) > 0:
                ctx.plateaus[i] = p
    moving = sum(1 for s in ctx.steps.values() if s["kind"] in ("rate", "level") and s["table_rate"] != 0)
    ctx.notes.append(
        f"step windows on the HF2's clock from the table encoder: {len(ctx.plateaus)} of {moving} moving steps"
        + (f"; {track.skipped} encoder counts skipped (too fast for the demod rate)" if track.skipped else "")
    )


def _window(ctx: _Ctx, step: dict[str, Any], extra_settle: float = 0.0) -> tuple[float, float]:
    """A step's analysis window: [start + settle, end], start and end the table encoder's plateau of the step when
    it has one (on the HF2's clock), else the host's step times."""
    p = ctx.plateaus.get(int(step["index"]))
    if p is not None:
        return p.start_s + ctx.settle_s + extra_settle, p.end_s
    return float(step["t_start"]) + ctx.settle_s + extra_settle, float(step["t_end"])


def _truth_window(truth: dict[str, np.ndarray], index: int, t0: float, t1: float) -> dict[str, float]:
    """A step's /windows row from a full file's /truth: its samples in [t0, t1] (the study level's reduction)."""
    i0, i1 = np.searchsorted(truth["time"], t0, side="left"), np.searchsorted(truth["time"], t1, side="right")
    sums = WindowSums(start_s=t0)
    sums.add(truth["time"][i0:i1], truth["scale_factor"][i0:i1], truth["temperature"][i0:i1])
    return sums.row(index, t1)


def _mean_whole_periods(ctx: _Ctx, t0: float, t1: float) -> tuple[float, int]:
    """Mean rate output over [t0, t1] cut to a whole number of dither periods: (V, samples used)."""
    if ctx.dither_rising_s is not None and ctx.edge_integral is not None:
        mean = mean_between_edges(ctx.dither_rising_s, ctx.edge_integral, t0, t1, 1.0 / ctx.fs_hz)
        if not math.isnan(mean):
            return mean, round((t1 - t0) * ctx.fs_hz)
    if ctx.study_level:  # no samples to fall back on
        return float("nan"), 0
    lk = ctx.run.groups["lockin"]
    i0, i1 = np.searchsorted(lk["time"], [t0, t1])
    n = int(i1 - i0)
    if ctx.period_samples > 1 and n >= ctx.period_samples:
        n = (n // ctx.period_samples) * ctx.period_samples
    if n <= 0:
        return float("nan"), 0
    return float(np.mean(lk["rate_output"][i0 : i0 + n])), n


def _mean_in(group: dict[str, np.ndarray] | None, col: str, windows: list[tuple[float, float]]) -> float:
    """Mean of group[col] over the samples with time in the union of the closed windows [a, b].

    The time axis is monotonic (docs/hdf5.md), so each window is one slice found by bisection; overlapping windows
    are merged first, and the slices are taken in time order, so the samples (and their summation order) are those
    of a boolean mask over the whole column, without its pass over every sample per window.
    """
    if group is None or group["time"].shape[0] == 0:
        return float("nan")
    t = group["time"]
    merged: list[list[float]] = []
    for a, b in sorted(windows):
        if merged and a <= merged[-1][1]:
            merged[-1][1] = max(merged[-1][1], b)
        else:
            merged.append([a, b])
    parts = []
    for a, b in merged:
        i0, i1 = np.searchsorted(t, a, side="left"), np.searchsorted(t, b, side="right")
        if i1 > i0:
            parts.append(group[col][i0:i1])
    return float(np.mean(np.concatenate(parts))) if parts else float("nan")


def _truth_mean(ctx: _Ctx, col: str, indices: tuple[int, ...]) -> float:
    """Mean of a /truth column over the steps' analysis windows, from their /windows rows (NaN without them)."""
    if ctx.windows is None:
        return float("nan")
    rows = [ctx.windows.get(i) for i in indices]
    n = sum(r["truth_samples"] for r in rows if r is not None)
    if any(r is None for r in rows) or n == 0:
        return float("nan")
    return sum(r[f"truth_{col}"] * r["truth_samples"] for r in rows if r is not None) / n


def _commanded(ctx: _Ctx, step: dict[str, Any], win: tuple[float, float]) -> float:
    """The table's rate over the window: the encoder's (its count's slope over the window, encoder.rate_over)
    when the step has an encoder plateau, else the median /table/rate_command in the window (robust to a reading
    taken on the step boundary)."""
    if ctx.encoder is not None and int(step["index"]) in ctx.plateaus:
        rate = rate_over(ctx.encoder, *win)
        if math.isfinite(rate):
            return rate
    tab = ctx.run.groups.get("table")
    if tab is not None:
        m = (tab["time"] >= win[0]) & (tab["time"] <= win[1])
        if m.any():
            return float(np.median(tab["rate_command"][m]))
    return float(step["table_rate"])


def _rms(x: np.ndarray) -> float:
    return float(np.sqrt(np.mean(x**2))) if x.size else float("nan")


# ---------------------------------------------------------------------------------------------------------------


def _pairs(ctx: _Ctx, res: AnalysisResult) -> _Found:
    found = _Found()
    g = ctx.run.groups
    clsf, chamber = g.get("clsf"), g.get("chamber")
    for idx in rate_pairs({i: (str(s["kind"]), float(s["table_rate"])) for i, s in ctx.steps.items()}):
        sp, sm = ctx.steps[idx], ctx.steps[idx + 1]
        wp, wm = _window(ctx, sp), _window(ctx, sm)
        op, np_ = _mean_whole_periods(ctx, *wp)
        om, nm = _mean_whole_periods(ctx, *wm)
        if np_ == 0 or nm == 0:
            found.notes.append(f"steps {idx}/{idx + 1}: no samples after the settle time; pair skipped")
            continue
        rp, rm = _commanded(ctx, sp, wp), _commanded(ctx, sm, wm)
        pair = StepPair(
            index_plus=idx,
            index_minus=idx + 1,
            t_mid_s=0.5 * (wp[0] + wm[1]),
            temperature_c=_mean_in(chamber, "temperature", [wp, wm]),
            sf_v_per_dps=(op - om) / (rp - rm),
            bias_v=0.5 * (op + om),
            rate_plus_dps=rp,
            rate_minus_dps=rm,
            output_plus_v=op,
            output_minus_v=om,
            window_plus_s=wp,
            window_minus_s=wm,
        )
        pair.truth_change_ppm = _truth_mean(ctx, "scale_factor", (idx, idx + 1))  # raw SF for now
        pair.gyro_temperature_c = _truth_mean(ctx, "temperature", (idx, idx + 1))
        found.pairs.append(pair)
    found.values["n_step_pairs"] = len(found.pairs)
    if not found.pairs:
        return found
    ref = found.pairs[0]
    sf_ref, tr_ref = ref.sf_v_per_dps, ref.truth_change_ppm
    for p in found.pairs:
        p.true_change_ppm = (p.sf_v_per_dps / sf_ref - 1) * PPM
        p.truth_change_ppm = (p.truth_change_ppm / tr_ref - 1) * PPM
    found.values["sf_measured_v_per_dps"] = sf_ref
    e = np.array([p.true_change_ppm for p in found.pairs])
    tr = np.array([p.truth_change_ppm for p in found.pairs])
    found.values["sf_true_change_ppm"] = float(np.ptp(e))
    found.notes.append("relative SF changes are referred to the first step pair (SF_ref = pair 0)")
    have_truth = (ctx.run.has_truth or ctx.windows is not None) and bool(np.all(np.isfinite(tr)))
    empty = np.empty(0)
    acc = series_accuracy(
        found.pairs,
        clsf["time"] if clsf is not None else empty,
        clsf["sf_change_estimate"] if clsf is not None else empty,
    )
    for p, c_i in zip(found.pairs, acc.change_ppm, strict=True):
        p.clsf_change_ppm = c_i
    c = np.array(acc.change_ppm)
    if math.isfinite(acc.rms_vs_table_ppm):
        found.values["clsf_accuracy_rms_ppm"] = acc.rms_vs_table_ppm
        found.values["clsf_accuracy_rms_ppm_mean_removed"] = acc.rms_vs_table_ppm_mean_removed
    if have_truth:
        found.values["truth_check_rms_ppm"] = _rms(e - tr)
        found.values["clsf_vs_truth_rms_ppm"] = acc.rms_vs_truth_ppm
    temps = np.array([p.temperature_c for p in found.pairs])
    ok = np.isfinite(temps)
    if ok.sum() >= 3 and np.ptp(temps[ok]) > 0.5:
        found.values["sf_tempco_ppm_per_c"] = float(np.polyfit(temps[ok], e[ok], 1)[0])
        okc = ok & np.isfinite(c)
        if okc.sum() >= 3:
            found.values["clsf_tempco_ppm_per_c"] = float(np.polyfit(temps[okc], c[okc], 1)[0])
    return found


def _clsf_adev(ctx: _Ctx, res: AnalysisResult) -> _Found:
    found = _Found()
    clsf = ctx.run.groups.get("clsf")
    if clsf is None or clsf["time"].shape[0] < 6:
        found.notes.append("CLSF ADEV: fewer than 6 CLSF periods in the file")
        return found
    rate = 1.0 / float(np.median(np.diff(clsf["time"])))
    r = overlapping_adev(clsf["sf_change_estimate"], rate)
    found.values["adev"] = r.rows(PPM)
    found.values["adev_at_60s_ppm"] = r.at(60.0) * PPM
    found.values["adev_at_2000s_ppm"] = r.at(2000.0) * PPM  # NaN unless the run is long enough (the paper: 1 ppm)
    if ctx.cfg.clsf.mode == "correct":
        g = clsf["gain_correction"]
        if np.all(g > 0):
            found.values["adev_gain_correction"] = overlapping_adev(np.log(g), rate).rows(PPM)
    return found


def _static_runs(ctx: _Ctx) -> list[tuple[float, float]]:
    for kind in ("hold", "soak"):
        runs: list[tuple[float, float]] = []
        prev = None
        for idx in sorted(ctx.steps):
            s = ctx.steps[idx]
            if s["kind"] != kind:
                prev = None
                continue
            a, b = _window(ctx, s)
            if prev is not None and prev == idx - 1 and runs:
                runs[-1] = (runs[-1][0], b)
            else:
                runs.append((a, b))
            prev = idx
        runs = [r for r in runs if r[1] > r[0]]
        if runs:
            return runs
    return []


def _gyro_noise(ctx: _Ctx, res: AnalysisResult, sf: float) -> _Found:
    found = _Found()
    runs = _static_runs(ctx)
    if not runs:
        found.notes.append("gyro ARW/bias instability: no completed hold or soak step")
        if res.pairs:
            found.notes.append("table-step noise (predicted): the run has no hold or soak step to measure it on")
        return found
    a, b = max(runs, key=lambda r: r[1] - r[0])
    clsf = ctx.run.groups.get("clsf")
    y: np.ndarray
    if clsf is not None and "rate_output_mean" in clsf and clsf["time"].shape[0]:
        m = (clsf["time"] >= a) & (clsf["time"] <= b)
        y, rate = clsf["rate_output_mean"][m], 0.0
        if m.sum() > 2:
            rate = 1.0 / float(np.median(np.diff(clsf["time"][m])))
    else:
        y, rate = np.empty(0), 0.0
    if y.shape[0] < 6:
        lk = ctx.run.groups["lockin"]
        i0, i1 = np.searchsorted(lk["time"], [a, b])
        per = ctx.period_samples if ctx.period_samples > 1 else max(1, int(round(ctx.fs_hz / 10)))
        n = (int(i1 - i0) // per) * per
        y = lk["rate_output"][i0 : i0 + n].reshape(-1, per).mean(axis=1)
        rate = ctx.fs_hz / per
    if y.shape[0] < 6 or not rate > 0:
        found.notes.append("gyro ARW/bias instability: static segment too short")
        return found
    r: AllanResult = overlapping_adev(y / sf * 3600.0, rate)
    found.values["gyro_adev_deg_per_h"] = r.rows()
    found.values["arw_deg_per_rt_h"] = arw_deg_per_rt_h(r)
    found.values["bias_instability_deg_per_h"] = bias_instability_deg_per_h(r)
    found.notes.append(f"gyro noise from the static segment {a:.1f}-{b:.1f} s")
    if res.pairs:
        windows = [PairWindows(p.window_plus_s, p.window_minus_s, p.rate_plus_dps, p.rate_minus_dps) for p in res.pairs]
        judge = table_step_noise(windows, r)
        if judge is None:
            found.notes.append(
                "table-step noise (predicted): needs two step pairs and the gyro ADEV at the windows' length "
                f"(the static segment's ADEV reaches {r.tau_s[-1] if r.tau_s.size else 0:.3g} s)"
            )
        else:
            found.values["table_step_noise_ppm"] = judge.rms_ppm
            found.values["table_step_noise_ppm_low"] = judge.rms_ppm_low
            found.values["table_step_noise_ppm_high"] = judge.rms_ppm_high
            found.values["table_step_noise_pair0_ppm"] = judge.pair0_ppm
    return found


def _dc_sf(ctx: _Ctx, res: AnalysisResult) -> float:
    """SF for scaling: measured pair SF, else the first rate step against the following rest, else nominal."""
    if math.isfinite(res.sf_measured_v_per_dps):
        return res.sf_measured_v_per_dps
    for idx in sorted(ctx.steps):
        s, nxt = ctx.steps[idx], ctx.steps.get(idx + 1)
        if s["kind"] == "rate" and s["table_rate"] != 0 and nxt is not None and nxt["table_rate"] == 0:
            w1, w0 = _window(ctx, s), _window(ctx, nxt)
            o1, n1 = _mean_whole_periods(ctx, *w1)
            o0, n0 = _mean_whole_periods(ctx, *w0)
            if n1 and n0:
                return (o1 - o0) / (_commanded(ctx, s, w1) - _commanded(ctx, nxt, w0))
    return res.sf_nominal_v_per_dps


def _bandwidth(ctx: _Ctx, res: AnalysisResult, sf: float) -> _Found:
    found = _Found()
    sines = [(idx, s, m) for idx, s in sorted(ctx.steps.items()) if (m := _SINE.match(str(s["kind"])))]
    if not sines:
        return found
    lk, truth = ctx.run.groups["lockin"], ctx.run.groups.get("truth")
    f_d = ctx.cfg.dither.frequency_hz
    nuisance = (f_d, 3 * f_d, 5 * f_d) if ctx.cfg.clsf.mode != "off" else ()
    found.values["phase_reference"] = (
        "twin /truth/rate"
        if truth is not None and truth["time"].shape[0]
        else "command A sin(2 pi f (t - t_start)): phase zero assumed at the step start"
    )
    for idx, s, kind_match in sines:
        f = float(kind_match.group(1))
        t0, t1 = _window(ctx, s, extra_settle=2.0 / f)
        n_cyc = math.floor((t1 - t0) * f)
        if n_cyc < 1:
            found.notes.append(f"step {idx} ({s['kind']}): shorter than one period after settling; skipped")
            continue
        t1 = t0 + n_cyc / f
        i0, i1 = np.searchsorted(lk["time"], [t0, t1])
        t = lk["time"][i0:i1]
        out = fit_sinusoid(t, lk["rate_output"][i0:i1], f, nuisance) / sf
        if truth is not None and truth["time"].shape[0]:
            j0, j1 = np.searchsorted(truth["time"], [t0, t1])
            ref = fit_sinusoid(truth["time"][j0:j1], truth["rate"][j0:j1], f)
        else:
            ts = float(s["t_start"])
            ref = complex(float(s["table_rate"]) * np.exp(-0.5j * np.pi - 2j * np.pi * f * ts))
        h = out / ref
        found.bode.append(
            BodePoint(
                frequency_hz=f,
                amplitude_ratio=abs(h),
                gain_db=20 * math.log10(abs(h)),
                phase_deg=math.degrees(math.atan2(h.imag, h.real)),
            )
        )
    found.values["bandwidth_hz"] = bandwidth_3db(found.bode)
    return found


def _settling(ctx: _Ctx, res: AnalysisResult) -> _Found:
    found = _Found()
    lk = ctx.run.groups["lockin"]
    for idx in sorted(ctx.steps):
        s, prev = ctx.steps[idx], ctx.steps.get(idx - 1)
        if prev is None and idx == min(ctx.steps):
            prev = {"table_rate": 0.0, "kind": "rest"}  # the first step starts from rest
        if (
            s["kind"] in ("rate", "level")
            and prev is not None
            and s["table_rate"] != prev["table_rate"]
            and not _SINE.match(str(prev["kind"]))
        ):
            a, b = float(s["t_start"]), float(s["t_end"])
            per = ctx.period_samples
            i0, i1 = np.searchsorted(lk["time"], [a - 1.0, b])
            i0 = max(0, i0 - per)
            if i1 - i0 <= per:  # a study-level file that never reached its settling step
                found.notes.append(f"settling time: no lock-in samples around step {idx}")
                return found
            y = moving_average(lk["rate_output"][i0:i1], per)
            ok = slice(per // 2, y.shape[0] - (per - per // 2)) if per > 1 else slice(None)  # full boxcars only
            t = lk["time"][i0:i1][ok]
            found.values["settling_time_s"] = settling_time_s(t, y[ok], a, min(b, float(t[-1])) if t.size else b)
            found.notes.append(f"settling time from step {idx} ({prev['table_rate']:g} -> {s['table_rate']:g} deg/s)")
            return found
    return found


def _linearity(ctx: _Ctx, res: AnalysisResult) -> _Found:
    found = _Found()
    levels = [(idx, s) for idx, s in sorted(ctx.steps.items()) if s["kind"] == "level"]
    rates, outs = [], []
    for idx, s in levels:
        w = _window(ctx, s)
        o, n = _mean_whole_periods(ctx, *w)
        if n:
            rates.append(_commanded(ctx, s, w))
            outs.append(o)
            found.levels.append({"index": idx, "rate_dps": rates[-1], "output_v": o})
    if len(set(rates)) >= 2:
        lin = linearity(np.array(rates), np.array(outs))
        found.values["linearity"] = {k: v for k, v in asdict(lin).items() if k != "residuals_v"}
        for row, r in zip(found.levels, lin.residuals_v, strict=True):
            row["residual_v"] = float(r)
    return found


def _completeness(ctx: _Ctx, res: AnalysisResult) -> _Found:
    found = _Found()
    planned = int(ctx.run.attrs.get("planned_steps", -1))
    kinds = ctx.run.planned_step_kinds
    if planned < 0:
        found.notes.append("the file does not record the planned steps; missing steps unknown")
        return found
    found.values["steps_planned"] = planned
    found.values["missing_steps"] = [
        {"index": i, "kind": kinds[i] if i < len(kinds) else ""} for i in range(planned) if i not in ctx.steps
    ]
    return found


def analyze(path: str | Path) -> AnalysisResult:
    """Analyse a run file (complete, aborted or killed; simulated or hardware). See the module docstring."""
    ctx = _load(path)
    a, cfg = ctx.run.attrs, ctx.cfg
    unclosed = ["the file was not closed by its writer (killed, or still being written)"] if ctx.run.writer_open else []
    res = AnalysisResult(
        file=str(ctx.run.path),
        status=str(a.get("status", "")),
        abort_reason=str(a.get("abort_reason", "")),
        mode=str(a.get("mode", "")),
        campaign_kind=cfg.campaign.kind,
        clsf_mode=cfg.clsf.mode,
        steps_planned=None,
        steps_completed=len(ctx.steps),
        missing_steps=[],
        sf_nominal_v_per_dps=cfg.device.sf_nominal_v_per_dps,
        run_context={k: str(a.get(k, "")) for k in RUN_CONTEXT_ATTRS},
        notes=[*ctx.notes, *unclosed],
    )
    res = _completeness(ctx, res).applied_to(res)
    if ctx.run.groups["lockin"]["time"].shape[0] == 0 and not ctx.study_level:
        return replace(res, notes=[*res.notes, "no lock-in samples in the file"])
    res = _pairs(ctx, res).applied_to(res)
    res = _clsf_adev(ctx, res).applied_to(res)
    sf = _dc_sf(ctx, res)
    res = _gyro_noise(ctx, res, sf).applied_to(res)
    res = _bandwidth(ctx, res, sf).applied_to(res)
    res = _settling(ctx, res).applied_to(res)
    return _linearity(ctx, res).applied_to(res)
