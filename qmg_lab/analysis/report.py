"""Figures of a run file, after the paper's Figs. 2-7 (matplotlib, Agg backend; PNG, SVG or PDF).

fig1_time_series     SF change against run time: the CLSF estimate's centred 60 s mean (each dither period's
                     estimate faint behind it) and the true SF from each +-rate step pair, both referred to the
                     first pair, with the chamber temperature on a second axis; in correct mode a second panel
                     with the gain correction g_c
fig2_rate_response   rate output vs table rate from the level steps of a linearity characterization with the
                     linear fit, and the residuals in % of full scale (never from a sweep's +-rate steps: their
                     spread is the SF's temperature drift, not nonlinearity)
fig3_bandwidth       Bode plot of rate_output/SF vs table rate from the sine steps, with the -3 dB line
fig4_clsf_io         CLSF input (recorded dither) and output (c_y) over 4 dither periods
fig5_rate_steps      rate output (dither-free, per dither period) over the +-rate steps, chamber temperature
fig6_sf_true_vs_clsf (a) true, CLSF (and twin truth) SF change vs temperature; (b) CLSF minus true
fig7_allan           Allan deviation of the CLSF SF estimate with 68 % confidence intervals
fig8_gyro_allan      Allan deviation of the gyro rate in a static segment, with the ARW (-1/2) line read at
                     tau = 1 s and the bias-instability floor 0.664 B (IEEE 952)

A figure whose data the file lacks is skipped with a reason (`FigureSet.skipped`), never an error.
Every figure is titled with the run file and its configuration (campaign name, kind, CLSF mode); legends sit
beside the axes, outside the data.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from matplotlib.ticker import LogLocator, NullFormatter, ScalarFormatter

from qmg_lab.analysis.compute import AnalysisResult, analyze, stored_config
from qmg_lab.clsf.moving_mean import SF_MEAN_WINDOW_S as MOVING_MEAN_S
from qmg_lab.clsf.moving_mean import centred_mean
from qmg_lab.data.decimate import minmax
from qmg_lab.storage.reader import read_run, read_window

MAX_POINTS = 20000
FORMATS = ("png", "svg", "pdf")
FigureFormat = Literal["png", "svg", "pdf"]
PPM = 1e6
RAMP_CAVEAT_C = 0.5  # a chamber that moved more than this during the run makes the long-tau ADEV a drift


@dataclass
class FigureSet:
    written: list[Path] = field(default_factory=list)
    skipped: dict[str, str] = field(default_factory=dict)


@dataclass(frozen=True)
class _Out:
    """Where and how figures are written: folder, format, the run's title line, what was written/skipped."""

    outdir: Path
    fmt: str
    title: str
    figures: FigureSet


def _legend(ax: plt.Axes, *more: plt.Axes) -> None:
    """One legend for ax (and its twin axes) beside the plot, right of the axes: it never covers data."""
    handles, labels = ax.get_legend_handles_labels()
    for other in more:
        h, lab = other.get_legend_handles_labels()
        handles, labels = handles + h, labels + lab
    ax.legend(handles, labels, loc="upper left", bbox_to_anchor=(1.02 + 0.1 * len(more), 1.0), fontsize="small")


def _save(fig: plt.Figure, o: _Out, name: str) -> None:
    path = o.outdir / f"{name}.{o.fmt}"
    fig.suptitle(o.title, fontsize="medium")
    fig.tight_layout()
    fig.savefig(path, dpi=110, bbox_inches="tight")  # "tight" keeps the legends beside the axes in the file
    plt.close(fig)
    o.figures.written.append(path)


def _fig1(
    r: AnalysisResult,
    clsf: dict[str, np.ndarray] | None,
    chamber: dict[str, np.ndarray] | None,
    o: _Out,
) -> None:
    if clsf is None or clsf["time"].shape[0] < 2:
        o.figures.skipped["fig1_time_series"] = "no CLSF periods in the file (CLSF off, or the run stopped early)"
        return
    t, s = clsf["time"], clsf["sf_change_estimate"]
    smooth = centred_mean(t, s, MOVING_MEAN_S)
    # both curves referred to the first step pair: the CLSF estimate to its mean over pair 0's span (the half
    # distance to pair 1 either side of its middle, else 30 s), the true SF as compute.py refers it
    ref, note = 0.0, "as recorded (SF/SF0 - 1)"
    if r.pairs:
        half = 0.5 * (r.pairs[1].t_mid_s - r.pairs[0].t_mid_s) if len(r.pairs) > 1 else 30.0
        near = np.abs(t - r.pairs[0].t_mid_s) <= half
        if near.any():
            ref, note = float(np.mean(s[near])), "referred to step pair 0"

    def rel(x: np.ndarray) -> np.ndarray:
        return ((1 + x) / (1 + ref) - 1) * PPM

    correct = r.clsf_mode == "correct" and "gain_correction" in clsf
    fig, axes = plt.subplots(2 if correct else 1, 1, figsize=(9, 6.5 if correct else 4.5), sharex=True, squeeze=False)
    ax = axes[0][0]
    td, sd = minmax(t, rel(s), MAX_POINTS // 4)
    ax.plot(td, sd, "-", color="0.8", lw=0.5, label="CLSF estimate, each dither period")
    ax.plot(t, rel(smooth), "-", color="C0", lw=1.5, label=f"CLSF estimate, centred {MOVING_MEAN_S:.0f} s mean")
    if r.pairs:
        ax.plot(
            [p.t_mid_s for p in r.pairs],
            [p.true_change_ppm for p in r.pairs],
            "o",
            color="C3",
            label="true SF from each +-rate step pair",
        )
    ax.set_ylabel(f"SF change [ppm], {note}")
    ax.grid(True)
    twins: list[plt.Axes] = []
    if chamber is not None and chamber["time"].shape[0]:
        ax2 = ax.twinx()
        tc, yc = minmax(chamber["time"], chamber["temperature"], MAX_POINTS // 4)
        ax2.plot(tc, yc, "-", color="C2", lw=1.0, label="chamber air temperature")
        ax2.set_ylabel("temperature [degC]", color="C2")
        twins.append(ax2)
    _legend(ax, *twins)
    if correct:
        axg = axes[1][0]
        tg, gd = minmax(t, (clsf["gain_correction"] - 1.0) * PPM, MAX_POINTS // 4)
        axg.plot(tg, gd, "-", color="C1", label="gain correction g_c - 1")
        axg.set_ylabel("g_c - 1 [ppm]")
        axg.grid(True)
        _legend(axg)
    axes[-1][0].set_xlabel("run time [s]")
    _save(fig, o, "fig1_time_series")


def _fig2(r: AnalysisResult, o: _Out) -> None:
    if not (r.levels and r.linearity):
        o.figures.skipped["fig2_rate_response"] = (
            "no level steps: the linearity figure needs a linearity characterization (qmg-lab characterize "
            "linearity); a sweep's +-rate steps show the SF's temperature drift, not its nonlinearity"
        )
        return
    rates = np.array([x["rate_dps"] for x in r.levels])
    outs = np.array([x["output_v"] for x in r.levels])
    sf, b = r.linearity["sf_v_per_dps"], r.linearity["bias_v"]
    label = "level steps"
    fs = float(np.max(np.abs(rates)))
    fig, (ax1, ax2) = plt.subplots(2, 1, figsize=(9.5, 6), sharex=True)
    ax1.plot(rates, outs, "o", label=label)
    xs = np.linspace(-fs, fs, 3)
    ax1.plot(xs, sf * xs + b, "-", label=f"fit: SF = {sf:.5g} V/(deg/s)")
    ax1.set_ylabel("rate output f_y [V]")
    _legend(ax1)
    ax1.grid(True)
    ax2.plot(rates, 100 * (outs - (sf * rates + b)) / abs(sf * fs), "o-", label="residual")
    ax2.set_xlabel("table rate [deg/s]")
    ax2.set_ylabel("residual [% FS]")
    _legend(ax2)
    ax2.grid(True)
    _save(fig, o, "fig2_rate_response")


def _log_frequency_ticks(ax: plt.Axes) -> None:
    """Frequency ticks at 1, 2, 5 x 10^k in plain numbers, no minor labels: they never overlap."""
    ax.xaxis.set_major_locator(LogLocator(base=10.0, subs=(1.0, 2.0, 5.0)))
    fmt = ScalarFormatter()
    fmt.set_scientific(False)
    ax.xaxis.set_major_formatter(fmt)
    ax.xaxis.set_minor_formatter(NullFormatter())


def _fig3(r: AnalysisResult, o: _Out) -> None:
    if not r.bode:
        o.figures.skipped["fig3_bandwidth"] = "no sine (bandwidth) steps"
        return
    f = np.array([b.frequency_hz for b in r.bode])
    fig, (ax1, ax2) = plt.subplots(2, 1, figsize=(9.5, 6), sharex=True)
    ax1.semilogx(f, [b.gain_db for b in r.bode], "o-", label="measured |H|")
    ax1.axhline(-3.01, color="r", ls="--", label="-3 dB")
    if math.isfinite(r.bandwidth_hz):
        ax1.axvline(r.bandwidth_hz, color="g", ls=":", label=f"bandwidth {r.bandwidth_hz:.2f} Hz")
    ax1.set_ylabel("gain [dB]")
    _legend(ax1)
    ax1.grid(True, which="both")
    ax2.semilogx(f, [b.phase_deg for b in r.bode], "o-", label=f"phase (ref: {r.phase_reference.split(':')[0]})")
    ax2.set_xlabel("frequency [Hz]")
    ax2.set_ylabel("phase [deg]")
    _legend(ax2)
    ax2.grid(True, which="both")
    _log_frequency_ticks(ax2)
    _save(fig, o, "fig3_bandwidth")


def _fig4(path: Path, r: AnalysisResult, o: _Out, dither_hz: float, t_from: float) -> None:
    if r.clsf_mode == "off":
        o.figures.skipped["fig4_clsf_io"] = "CLSF off: no dither in this run"
        return
    w = read_window(path, "lockin", t_from, t_from + 4.0 / dither_hz, ["dither", "x_sense"])
    if w["time"].shape[0] < 10 or np.ptp(w["dither"]) == 0:
        o.figures.skipped["fig4_clsf_io"] = "no dither recorded"
        return
    t = w["time"] - w["time"][0]
    tri = np.cumsum(w["dither"] - w["dither"].mean())
    tri -= tri.mean()
    fig, (ax1, ax2) = plt.subplots(2, 1, figsize=(9.5, 5), sharex=True)
    ax1.plot(t, w["dither"], label="CLSF input: dither (virtual rate)")
    ax1.set_ylabel("dither [V]")
    _legend(ax1)
    ax1.grid(True)
    ax2.plot(t, w["x_sense"] * 1e3, label="CLSF output: c_y")
    scale = np.std(w["x_sense"]) / np.std(tri) if np.std(tri) > 0 else 0.0
    ax2.plot(t, (w["x_sense"].mean() + scale * tri) * 1e3, "--", label="triangle reference (scaled)")
    ax2.set_xlabel("time [s]")
    ax2.set_ylabel("c_y [mV]")
    _legend(ax2)
    ax2.grid(True)
    _save(fig, o, "fig4_clsf_io")


def _fig5(
    run_clsf: dict[str, np.ndarray] | None,
    chamber: dict[str, np.ndarray] | None,
    o: _Out,
    r: AnalysisResult,
) -> None:
    if not r.pairs or run_clsf is None or "rate_output_mean" not in run_clsf or run_clsf["time"].shape[0] == 0:
        o.figures.skipped["fig5_rate_steps"] = "no +-rate step pairs with per-period rate output"
        return
    t, y = run_clsf["time"], run_clsf["rate_output_mean"]
    step = max(1, t.shape[0] // MAX_POINTS)
    fig, ax = plt.subplots(figsize=(9, 4))
    ax.plot(t[::step], y[::step], ".", ms=2, label="rate output (dither-period mean)")
    ax.set_xlabel("run time [s]")
    ax.set_ylabel("rate output [V]")
    ax.grid(True)
    twins: list[plt.Axes] = []
    if chamber is not None and chamber["time"].shape[0]:
        ax2 = ax.twinx()
        ax2.plot(chamber["time"], chamber["temperature"], "r-", label="chamber temperature")
        ax2.set_ylabel("temperature [degC]")
        twins.append(ax2)
    _legend(ax, *twins)
    _save(fig, o, "fig5_rate_steps")


def _fig6(r: AnalysisResult, o: _Out) -> None:
    if len(r.pairs) < 2:
        o.figures.skipped["fig6_sf_true_vs_clsf"] = "fewer than two +-rate step pairs"
        return
    x = np.array([p.temperature_c for p in r.pairs])
    xlabel = "chamber temperature [degC]"
    if not np.all(np.isfinite(x)) or np.ptp(x) < 0.1:
        x, xlabel = np.array([p.t_mid_s for p in r.pairs]), "time [s]"
    e = np.array([p.true_change_ppm for p in r.pairs])
    c = np.array([p.clsf_change_ppm for p in r.pairs])
    tr = np.array([p.truth_change_ppm for p in r.pairs])
    fig, (ax1, ax2) = plt.subplots(2, 1, figsize=(9.5, 6), sharex=True)
    ax1.plot(x, e, "o-", label="true SF change (table)")
    if np.any(np.isfinite(c)):
        ax1.plot(x, c, "s--", label="CLSF estimate")
    if r.truth_check_rms_ppm is not None:
        ax1.plot(x, tr, "k:", label="twin truth")
    ax1.set_ylabel("SF change vs pair 0 [ppm]")
    _legend(ax1)
    ax1.grid(True)
    ax2.plot(x, c - e, "o-", label=f"CLSF - true (RMS {r.clsf_accuracy_rms_ppm:.0f} ppm)")
    if r.truth_check_rms_ppm is not None:
        ax2.plot(x, c - tr, "k:", label="CLSF - twin truth")
    ax2.set_xlabel(xlabel)
    ax2.set_ylabel("difference [ppm]")
    _legend(ax2)
    ax2.grid(True)
    _save(fig, o, "fig6_sf_true_vs_clsf")


def _allan_plot(rows: list[dict[str, float]], label: str) -> tuple[plt.Figure, plt.Axes, np.ndarray, np.ndarray]:
    """A log-log Allan-deviation figure of rows {tau_s, value, low, high} with their 68 % intervals."""
    tau = np.array([a["tau_s"] for a in rows])
    dev = np.array([a["value"] for a in rows])
    lo = np.array([a["low"] for a in rows])
    hi = np.array([a["high"] for a in rows])
    fig, ax = plt.subplots(figsize=(9.5, 4.8))
    ax.errorbar(tau, dev, yerr=[dev - lo, hi - dev], fmt="o-", capsize=2, label=label)
    return fig, ax, tau, dev


def _finish_allan(ax: plt.Axes, ylabel: str) -> None:
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("averaging time tau [s]")
    ax.set_ylabel(ylabel)
    ax.grid(True, which="both")
    _legend(ax)


def _fig7(r: AnalysisResult, chamber: dict[str, np.ndarray] | None, o: _Out) -> None:
    if not r.adev:
        o.figures.skipped["fig7_allan"] = "not enough CLSF periods for an Allan deviation"
        return
    fig, ax, tau, dev = _allan_plot(r.adev, f"CLSF SF estimate ({r.clsf_mode} mode), 68 % CI")
    if r.adev_gain_correction:
        ax.loglog(
            [a["tau_s"] for a in r.adev_gain_correction],
            [a["value"] for a in r.adev_gain_correction],
            "s--",
            label="gain correction ln g_c",
        )
    ax.loglog(tau, dev[0] * np.sqrt(tau[0] / tau), "k:", label="slope -1/2 (white)")
    _finish_allan(ax, "Allan deviation [ppm]")
    moved = float(np.ptp(chamber["temperature"])) if chamber is not None and chamber["time"].shape[0] else 0.0
    if moved > RAMP_CAVEAT_C:
        ax.set_title(
            f"caveat: the chamber moved {moved:.1f} degC during the run; at long tau this is the SF's\n"
            "temperature drift as the CLSF tracks it, not the estimator's stability",
            fontsize="small",
            color="C3",
        )
    _save(fig, o, "fig7_allan")


def _fig8(r: AnalysisResult, o: _Out) -> None:
    if not r.gyro_adev_deg_per_h:
        o.figures.skipped["fig8_gyro_allan"] = "no static segment long enough for the gyro's Allan deviation"
        return
    fig, ax, tau, _ = _allan_plot(r.gyro_adev_deg_per_h, "gyro rate, 68 % CI")
    if math.isfinite(r.arw_deg_per_rt_h):
        # sigma(tau) = N / sqrt(tau), N in deg/h/sqrt(Hz) = 60 x ARW in deg/sqrt(h)
        ax.loglog(
            tau, 60.0 * r.arw_deg_per_rt_h / np.sqrt(tau), "k:", label=f"ARW {r.arw_deg_per_rt_h:.4f} deg/sqrt(h)"
        )
    if math.isfinite(r.bias_instability_deg_per_h):
        ax.axhline(
            0.664 * r.bias_instability_deg_per_h,
            color="r",
            ls="--",
            label=f"0.664 B, B = {r.bias_instability_deg_per_h:.3f} deg/h",
        )
    _finish_allan(ax, "Allan deviation of rate [deg/h]")
    _save(fig, o, "fig8_gyro_allan")


def make_figures(
    path: str | Path, outdir: str | Path, result: AnalysisResult | None = None, fmt: FigureFormat = "png"
) -> FigureSet:
    """Write every figure the file has data for (as fmt: png, svg or pdf); return what was written and why
    others were skipped."""
    if fmt not in FORMATS:
        raise ValueError(f"figure format {fmt!r}: use one of {', '.join(FORMATS)}")
    p, od = Path(path), Path(outdir)
    od.mkdir(parents=True, exist_ok=True)
    r = result if result is not None else analyze(p)
    run = read_run(p, select=["clsf", "chamber", "lockin/time"])
    cfg, _ = stored_config(run)
    out = FigureSet()
    title = f"{p.name}: {cfg.campaign.name} ({cfg.campaign.kind}, CLSF {cfg.clsf.mode}), {run.status}"
    o = _Out(od, fmt, title, out)
    # a quiet window for Fig. 4: the middle of the first hold/soak/level/rate step after the dither started
    t_from = 0.0
    for i in range(run.steps["index"].shape[0]):
        if run.steps["kind"][i] in ("hold", "soak", "rate", "level") and run.steps["status"][i] == "completed":
            t_from = 0.5 * (run.steps["t_start"][i] + run.steps["t_end"][i])
            break
    else:
        t = run.groups["lockin"]["time"]
        t_from = float(t[t.shape[0] // 2]) if t.shape[0] else 0.0
    clsf, chamber = run.groups.get("clsf"), run.groups.get("chamber")
    _fig1(r, clsf, chamber, o)
    _fig2(r, o)
    _fig3(r, o)
    _fig4(p, r, o, cfg.dither.frequency_hz, t_from)
    _fig5(clsf, chamber, o, r)
    _fig6(r, o)
    _fig7(r, chamber, o)
    _fig8(r, o)
    return out


def write_figures(path: str | Path, outdir: str | Path, fmt: FigureFormat = "png") -> list[Path]:
    """Figures after the paper's Figs. 2-7 into outdir (png, svg or pdf); figures without data are skipped (see
    make_figures)."""
    return make_figures(path, outdir, fmt=fmt).written
