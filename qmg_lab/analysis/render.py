"""The analysis on a terminal: a rich table of the headline figures of an AnalysisResult (qmg_lab/analysis/compute.py
computes; this module only formats, `qmg-lab analyze` prints)."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

from rich.table import Table

from qmg_lab.analysis.compute import AnalysisResult


def render_table(result: AnalysisResult) -> Table:
    """A rich Table of the headline figures (missing values shown as '-')."""

    def f(v: Any, fmt: str = "{:.4g}") -> str:
        if v is None or (isinstance(v, float) and not math.isfinite(v)):
            return "-"
        return fmt.format(v) if isinstance(v, (int, float)) else str(v)

    r = result
    tab = Table(title=f"qmg-lab analysis: {Path(r.file).name} ({r.status})", show_header=True)
    tab.add_column("quantity")
    tab.add_column("value", justify="right")
    tab.add_column("unit")
    rows: list[tuple[str, str, str]] = [
        ("campaign / CLSF mode", f"{r.campaign_kind} / {r.clsf_mode}", ""),
        ("steps completed / planned", f"{r.steps_completed} / {f(r.steps_planned)}", ""),
        (
            "missing steps",
            ", ".join(f"{m['index']}:{m['kind']}" for m in r.missing_steps[:8])
            + (" ..." if len(r.missing_steps) > 8 else "")
            or "none",
            "",
        ),
        ("SF nominal / measured", f"{f(r.sf_nominal_v_per_dps)} / {f(r.sf_measured_v_per_dps, '{:.6g}')}", "V/(deg/s)"),
        ("step pairs", f(r.n_step_pairs), ""),
        ("true SF change (p-p)", f(r.sf_true_change_ppm, "{:.1f}"), "ppm"),
        (
            "SF tempco true / CLSF",
            f"{f(r.sf_tempco_ppm_per_c, '{:.1f}')} / {f(r.clsf_tempco_ppm_per_c, '{:.1f}')}",
            "ppm/degC",
        ),
        ("CLSF accuracy RMS", f(r.clsf_accuracy_rms_ppm, "{:.1f}"), "ppm"),
        ("CLSF accuracy RMS, mean removed", f(r.clsf_accuracy_rms_ppm_mean_removed, "{:.1f}"), "ppm"),
        ("truth check RMS", f(r.truth_check_rms_ppm, "{:.2f}"), "ppm"),
        ("CLSF vs truth RMS", f(r.clsf_vs_truth_rms_ppm, "{:.2f}"), "ppm"),
        ("CLSF ADEV at 60 s", f(r.adev_at_60s_ppm, "{:.2f}"), "ppm"),
        ("CLSF ADEV at 2000 s", f(r.adev_at_2000s_ppm, "{:.2f}"), "ppm"),
        ("CLSF ADEV minimum", f(min((x["value"] for x in r.adev), default=None), "{:.2f}"), "ppm"),
        ("ARW", f(r.arw_deg_per_rt_h, "{:.4f}"), "deg/sqrt(h)"),
        ("bias instability", f(r.bias_instability_deg_per_h, "{:.3f}"), "deg/h"),
        ("FTR bandwidth (-3 dB)", f(r.bandwidth_hz, "{:.3f}"), "Hz"),
        ("2 % settling time", f(r.settling_time_s, "{:.3f}"), "s"),
        (
            "nonlinearity max / RMS",
            f"{f(r.linearity.get('nonlinearity_max_pct_fs'), '{:.3f}')} / "
            f"{f(r.linearity.get('nonlinearity_rms_pct_fs'), '{:.3f}')}",
            "% FS",
        ),
        ("asymmetry", f(r.linearity.get("asymmetry_ppm"), "{:.0f}"), "ppm"),
    ]
    for row in rows:
        tab.add_row(*row)
    return tab
