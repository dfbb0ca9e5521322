"""PNG figures of a run file, after the paper's Figs. 2-7 (matplotlib, Agg backend).

fig2_rate_response   rate output vs table rate (level steps, else the +-rate step means) with the linear fit,
                     and the residuals in % of full scale
fig3_bandwidth       Bode plot of rate_output/SF vs table rate from the sine steps, with the -3 dB line
fig4_clsf_io         CLSF input (recorded dither) and output (c_y) over 4 dither periods
fig5_rate_steps      rate output (dither-free, per dither period) over the +-rate steps, chamber temperature
fig6_sf_true_vs_clsf (a) true, CLSF (and twin truth) SF change vs temperature; (b) CLSF minus true
fig7_allan           Allan deviation of the CLSF SF estimate with 68 % confidence intervals
fig8_gyro_allan      Allan deviation of the gyro rate in a static segment, with the ARW (-1/2) line read at
                     tau = 1 s and the bias-instability floor 0.664 B (IEEE 952)

A figure whose data the file lacks is skipped with a reason (`FigureSet.skipped`), never an error.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from qmg_lab.analysis.compute import AnalysisResult, analyze, stored_config
from qmg_lab.storage.writer import read_run, read_window

MAX_POINTS = 20000


@dataclass
class FigureSet:
    written: list[Path] = field(default_factory=list)
    skipped: dict[str, str] = field(default_factory=dict)


def _save(fig: plt.Figure, outdir: Path, name: str, out: FigureSet) -> None:
    path = outdir / f"{name}.png"
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    out.written.append(path)


def _fig2(r: AnalysisResult, outdir: Path, out: FigureSet) -> None:
    if r.levels and r.linearity:
        rates = np.array([x["rate_dps"] for x in r.levels])
        outs = np.array([x["output_v"] for x in r.levels])
        sf, b = r.linearity["sf_v_per_dps"], r.linearity["bias_v"]
        label = "level steps"
    elif r.pairs:
        sf = float(np.mean([p.sf_v_per_dps for p in r.pairs]))
        b = float(np.mean([p.bias_v for p in r.pairs]))
        rates = np.array([x for p in r.pairs for x in (p.rate_plus_dps, p.rate_minus_dps)])
        outs = np.array([x for p in r.pairs for x in (p.output_plus_v, p.output_minus_v)])
        label = "+-rate steps (all pairs)"
    else:
        out.skipped["fig2_rate_response"] = "no level steps and no +-rate step pairs"
        return
    fs = float(np.max(np.abs(rates)))
    fig, (ax1, ax2) = plt.subplots(2, 1, figsize=(6, 6), sharex=True)
    ax1.plot(rates, outs, "o", label=label)
    xs = np.linspace(-fs, fs, 3)
    ax1.plot(xs, sf * xs + b, "-", label=f"fit: SF = {sf:.5g} V/(deg/s)")
    ax1.set_ylabel("rate output f_y [V]")
    ax1.legend()
    ax1.grid(True)
    ax2.plot(rates, 100 * (outs - (sf * rates + b)) / abs(sf * fs), "o-", label="residual")
    ax2.set_xlabel("table rate [deg/s]")
    ax2.set_ylabel("residual [% FS]")
    ax2.legend()
    ax2.grid(True)
    _save(fig, outdir, "fig2_rate_response", out)


def _fig3(r: AnalysisResult, outdir: Path, out: FigureSet) -> None:
    if not r.bode:
        out.skipped["fig3_bandwidth"] = "no sine (bandwidth) steps"
        return
    f = np.array([b.frequency_hz for b in r.bode])
    fig, (ax1, ax2) = plt.subplots(2, 1, figsize=(6, 6), sharex=True)
    ax1.semilogx(f, [b.gain_db for b in r.bode], "o-", label="measured |H|")
    ax1.axhline(-3.01, color="r", ls="--", label="-3 dB")
    if math.isfinite(r.bandwidth_hz):
        ax1.axvline(r.bandwidth_hz, color="g", ls=":", label=f"bandwidth {r.bandwidth_hz:.2f} Hz")
    ax1.set_ylabel("gain [dB]")
    ax1.legend()
    ax1.grid(True, which="both")
    ax2.semilogx(f, [b.phase_deg for b in r.bode], "o-", label=f"phase (ref: {r.phase_reference.split(':')[0]})")
    ax2.set_xlabel("frequency [Hz]")
    ax2.set_ylabel("phase [deg]")
    ax2.legend()
    ax2.grid(True, which="both")
    _save(fig, outdir, "fig3_bandwidth", out)


def _fig4(path: Path, r: AnalysisResult, outdir: Path, out: FigureSet, dither_hz: float, t_from: float) -> None:
    if r.clsf_mode == "off":
        out.skipped["fig4_clsf_io"] = "CLSF off: no dither in this run"
        return
    w = read_window(path, "lockin", t_from, t_from + 4.0 / dither_hz, ["dither", "x_sense"])
    if w["time"].shape[0] < 10 or np.ptp(w["dither"]) == 0:
        out.skipped["fig4_clsf_io"] = "no dither recorded"
        return
    t = w["time"] - w["time"][0]
    tri = np.cumsum(w["dither"] - w["dither"].mean())
    tri -= tri.mean()
    fig, (ax1, ax2) = plt.subplots(2, 1, figsize=(6, 5), sharex=True)
    ax1.plot(t, w["dither"], label="CLSF input: dither (virtual rate)")
    ax1.set_ylabel("dither [V]")
    ax1.legend(loc="upper right")
    ax1.grid(True)
    ax2.plot(t, w["x_sense"] * 1e3, label="CLSF output: c_y")
    scale = np.std(w["x_sense"]) / np.std(tri) if np.std(tri) > 0 else 0.0
    ax2.plot(t, (w["x_sense"].mean() + scale * tri) * 1e3, "--", label="triangle reference (scaled)")
    ax2.set_xlabel("time [s]")
    ax2.set_ylabel("c_y [mV]")
    ax2.legend(loc="upper right")
    ax2.grid(True)
    _save(fig, outdir, "fig4_clsf_io", out)


def _fig5(
    run_clsf: dict[str, np.ndarray] | None,
    chamber: dict[str, np.ndarray] | None,
    outdir: Path,
    out: FigureSet,
    r: AnalysisResult,
) -> None:
    if not r.pairs or run_clsf is None or "rate_output_mean" not in run_clsf or run_clsf["time"].shape[0] == 0:
        out.skipped["fig5_rate_steps"] = "no +-rate step pairs with per-period rate output"
        return
    t, y = run_clsf["time"], run_clsf["rate_output_mean"]
    step = max(1, t.shape[0] // MAX_POINTS)
    fig, ax = plt.subplots(figsize=(8, 4))
    ax.plot(t[::step], y[::step], ".", ms=2, label="rate output (dither-period mean)")
    ax.set_xlabel("time [s]")
    ax.set_ylabel("rate output [V]")
    ax.grid(True)
    if chamber is not None and chamber["time"].shape[0]:
        ax2 = ax.twinx()
        ax2.plot(chamber["time"], chamber["temperature"], "r-", label="chamber temperature")
        ax2.set_ylabel("temperature [degC]")
        ax2.legend(loc="lower right")
    ax.legend(loc="upper left")
    _save(fig, outdir, "fig5_rate_steps", out)


def _fig6(r: AnalysisResult, outdir: Path, out: FigureSet) -> None:
    if len(r.pairs) < 2:
        out.skipped["fig6_sf_true_vs_clsf"] = "fewer than two +-rate step pairs"
        return
    x = np.array([p.temperature_c for p in r.pairs])
    xlabel = "chamber temperature [degC]"
    if not np.all(np.isfinite(x)) or np.ptp(x) < 0.1:
        x, xlabel = np.array([p.t_mid_s for p in r.pairs]), "time [s]"
    e = np.array([p.true_change_ppm for p in r.pairs])
    c = np.array([p.clsf_change_ppm for p in r.pairs])
    tr = np.array([p.truth_change_ppm for p in r.pairs])
    fig, (ax1, ax2) = plt.subplots(2, 1, figsize=(6, 6), sharex=True)
    ax1.plot(x, e, "o-", label="true SF change (table)")
    if np.any(np.isfinite(c)):
        ax1.plot(x, c, "s--", label="CLSF estimate")
    if r.truth_check_rms_ppm is not None:
        ax1.plot(x, tr, "k:", label="twin truth")
    ax1.set_ylabel("SF change vs pair 0 [ppm]")
    ax1.legend()
    ax1.grid(True)
    ax2.plot(x, c - e, "o-", label=f"CLSF - true (RMS {r.clsf_accuracy_rms_ppm:.0f} ppm)")
    if r.truth_check_rms_ppm is not None:
        ax2.plot(x, c - tr, "k:", label="CLSF - twin truth")
    ax2.set_xlabel(xlabel)
    ax2.set_ylabel("difference [ppm]")
    ax2.legend()
    ax2.grid(True)
    _save(fig, outdir, "fig6_sf_true_vs_clsf", out)


def _allan_plot(rows: list[dict[str, float]], label: str) -> tuple[plt.Figure, plt.Axes, np.ndarray, np.ndarray]:
    """A log-log Allan-deviation figure of rows {tau_s, value, low, high} with their 68 % intervals."""
    tau = np.array([a["tau_s"] for a in rows])
    dev = np.array([a["value"] for a in rows])
    lo = np.array([a["low"] for a in rows])
    hi = np.array([a["high"] for a in rows])
    fig, ax = plt.subplots(figsize=(6, 4.5))
    ax.errorbar(tau, dev, yerr=[dev - lo, hi - dev], fmt="o-", capsize=2, label=label)
    return fig, ax, tau, dev


def _finish_allan(ax: plt.Axes, ylabel: str) -> None:
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("averaging time tau [s]")
    ax.set_ylabel(ylabel)
    ax.grid(True, which="both")
    ax.legend()


def _fig7(r: AnalysisResult, outdir: Path, out: FigureSet) -> None:
    if not r.adev:
        out.skipped["fig7_allan"] = "not enough CLSF periods for an Allan deviation"
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
    _save(fig, outdir, "fig7_allan", out)


def _fig8(r: AnalysisResult, outdir: Path, out: FigureSet) -> None:
    if not r.gyro_adev_deg_per_h:
        out.skipped["fig8_gyro_allan"] = "no static segment long enough for the gyro's Allan deviation"
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
    _save(fig, outdir, "fig8_gyro_allan", out)


def make_figures(path: str | Path, outdir: str | Path, result: AnalysisResult | None = None) -> FigureSet:
    """Write every figure the file has data for; return what was written and why others were skipped."""
    p, od = Path(path), Path(outdir)
    od.mkdir(parents=True, exist_ok=True)
    r = result if result is not None else analyze(p)
    run = read_run(p, select=["clsf", "chamber", "lockin/time"])
    out = FigureSet()
    cfg, _ = stored_config(run)
    # a quiet window for Fig. 4: the middle of the first hold/soak/level/rate step after the dither started
    t_from = 0.0
    for i in range(run.steps["index"].shape[0]):
        if run.steps["kind"][i] in ("hold", "soak", "rate", "level") and run.steps["status"][i] == "completed":
            t_from = 0.5 * (run.steps["t_start"][i] + run.steps["t_end"][i])
            break
    else:
        t = run.groups["lockin"]["time"]
        t_from = float(t[t.shape[0] // 2]) if t.shape[0] else 0.0
    _fig2(r, od, out)
    _fig3(r, od, out)
    _fig4(p, r, od, out, cfg.dither.frequency_hz, t_from)
    _fig5(run.groups.get("clsf"), run.groups.get("chamber"), od, out, r)
    _fig6(r, od, out)
    _fig7(r, od, out)
    _fig8(r, od, out)
    return out


def write_figures(path: str | Path, outdir: str | Path) -> list[Path]:
    """PNG figures after the paper's Figs. 2-7 into outdir; figures without data are skipped (see make_figures)."""
    return make_figures(path, outdir).written
