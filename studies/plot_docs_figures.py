"""The figures of docs/studies.md, from the results of the two shipped studies.

    qmg-lab study studies/virtual_rate.toml -o studies-out/virtual_rate
    qmg-lab study studies/robustness.toml -o studies-out/robustness
    python studies/plot_docs_figures.py studies-out/virtual_rate studies-out/robustness docs/figures

virtual_rate.png: CLSF precision (ADEV of the self-calibrated scale factor at 60 s and 2000 s) against the
virtual-rate amplitude Omega_v, log-log, mean and min-max over seeds per CLSF time constant, the fitted slope of
each line, and the white-rate-noise reference sigma_Omega(tau) / Omega_v with sigma_Omega(tau) = N / sqrt(tau) from
the twin's angle random walk N ([sim] arw_deg_per_rt_h): what an open-loop estimator that sees only the gyro's white
rate noise against a square virtual rate would reach.

robustness.png: CLSF accuracy (RMS of CLSF minus the twin's true scale-factor change, ppm) over lock-in rate x
dither frequency, one panel per DS345 timebase offset.
"""

from __future__ import annotations

import csv
import math
import sys
import tomllib
from collections import defaultdict
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def rows(out_dir: Path) -> list[dict[str, str]]:
    with (out_dir / "results.csv").open() as f:
        return [r for r in csv.DictReader(f) if r["status"] == "ok"]


def value(r: dict[str, str], key: str) -> float:
    return float(r[key]) if r.get(key) else math.nan


def virtual_rate(out_dir: Path, png: Path) -> list[str]:
    data = rows(out_dir)
    base = tomllib.loads((ROOT / "configs" / "clsf_adev.toml").read_text())
    arw = float(base.get("sim", {}).get("arw_deg_per_rt_h", 0.02))  # the twin's default if the base leaves it
    n_dps = arw * 60.0 / 3600.0  # deg/sqrt(h) -> (deg/s)/sqrt(Hz)
    fig, axes = plt.subplots(1, 2, figsize=(10, 4.2), sharex=True)
    lines = []
    for ax, metric, tau in zip(axes, ("adev_at_60s_ppm", "adev_at_2000s_ppm"), (60.0, 2000.0), strict=True):
        by_tc: dict[float, dict[float, list[float]]] = defaultdict(lambda: defaultdict(list))
        for r in data:
            v = value(r, metric)
            if math.isfinite(v):
                by_tc[value(r, "clsf.time_constant_s")][value(r, "dither.virtual_rate_dps")].append(v)
        omegas = sorted({w for d in by_tc.values() for w in d})
        for tc, d in sorted(by_tc.items()):
            x = np.array(sorted(d))
            m = np.array([np.mean(d[w]) for w in x])
            lo = m - np.array([min(d[w]) for w in x])
            hi = np.array([max(d[w]) for w in x]) - m
            slope = float(np.polyfit(np.log(x), np.log(m), 1)[0]) if x.size >= 2 else math.nan
            ax.errorbar(
                x, m, yerr=[lo, hi], marker="o", capsize=3, label=f"CLSF time constant {tc:g} s: slope {slope:+.2f}"
            )
            lines.append(
                f"{metric} tc={tc:g} s: "
                + ", ".join(f"{w:g} deg/s -> {v:.3g} ppm" for w, v in zip(x, m, strict=True))
                + f" (slope {slope:+.3f})"
            )
        if omegas:
            w = np.array(omegas)
            floor = n_dps / math.sqrt(tau) / w * 1e6
            ax.plot(w, floor, "k:", label=f"white rate noise N/(Omega_v sqrt(tau)), N = ARW {arw:g} deg/sqrt(h)")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xticks(omegas, [f"{w:g}" for w in omegas], minor=False)
        ax.set_xticks([], minor=True)
        ax.set_xlabel("virtual-rate amplitude Omega_v (deg/s)")
        ax.set_ylabel(f"CLSF ADEV at {tau:g} s (ppm)")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7)
    seeds = len({r["seed"] for r in data})
    fig.suptitle(
        f"CLSF precision against the virtual rate (studies/virtual_rate.toml; {seeds} seed(s): mean, min-max)",
        fontsize=9,
    )
    fig.tight_layout()
    fig.savefig(png, dpi=110)
    plt.close(fig)
    return lines


def robustness(out_dir: Path, png: Path) -> list[str]:
    data = rows(out_dir)
    rates = sorted({value(r, "lockin.demod_rate_hz") for r in data})
    dithers = sorted({value(r, "dither.frequency_hz") for r in data})
    offsets = sorted({value(r, "sim.ds345_timebase_offset_ppm") for r in data})
    metric = "clsf_vs_truth_rms_ppm"
    vmax = max(value(r, metric) for r in data)
    fig, axes = plt.subplots(
        1, len(offsets), figsize=(4.0 * len(offsets) + 1.0, 3.8), squeeze=False, layout="constrained"
    )
    lines = []
    for ax, off in zip(axes[0], offsets, strict=True):
        grid = np.full((len(dithers), len(rates)), np.nan)
        for r in data:
            if value(r, "sim.ds345_timebase_offset_ppm") == off:
                grid[dithers.index(value(r, "dither.frequency_hz")), rates.index(value(r, "lockin.demod_rate_hz"))] = (
                    value(r, metric)
                )
        im = ax.imshow(grid, origin="lower", cmap="viridis", vmin=0.0, vmax=vmax, aspect="auto")
        for i in range(len(dithers)):
            for j in range(len(rates)):
                ax.text(j, i, f"{grid[i, j]:.1f}", ha="center", va="center", fontsize=7, color="w")
        ax.set_xticks(range(len(rates)), [f"{x:g}" for x in rates])
        ax.set_yticks(range(len(dithers)), [f"{x:g}" for x in dithers])
        ax.set_xlabel("lock-in rate (Sa/s)")
        if off == offsets[0]:
            ax.set_ylabel("dither frequency (Hz)")
        ax.set_title(f"DS345 timebase offset {off:+g} ppm", fontsize=9)
        lines.append(f"offset {off:+g} ppm: worst {np.nanmax(grid):.2f} ppm, median {np.nanmedian(grid):.2f} ppm")
    fig.colorbar(im, ax=axes[0].tolist(), label="CLSF vs truth, RMS (ppm)")
    fig.suptitle(
        "CLSF accuracy: RMS of CLSF minus true SF change over the step pairs (studies/robustness.toml)", fontsize=9
    )
    fig.savefig(png, dpi=110)
    plt.close(fig)
    return lines


def main() -> None:
    vr_dir, rob_dir, fig_dir = (Path(a) for a in sys.argv[1:4])
    fig_dir.mkdir(parents=True, exist_ok=True)
    if (vr_dir / "results.csv").exists():
        print("\n".join(virtual_rate(vr_dir, fig_dir / "study_virtual_rate.png")))
    if (rob_dir / "results.csv").exists():
        print("\n".join(robustness(rob_dir, fig_dir / "study_robustness.png")))


if __name__ == "__main__":
    main()
