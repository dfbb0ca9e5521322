"""The analysis on a terminal: a rich table of the headline figures of an AnalysisResult (qmg_lab/analysis/compute.py
computes; this module only formats, `qmg-lab analyze` prints)."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

from rich.table import Table

from qmg_lab.analysis.compute import AnalysisResult


def _missing(v: Any) -> bool:
    return v is None or (isinstance(v, float) and not math.isfinite(v))


def why_missing(r: AnalysisResult) -> dict[str, str]:
    """A word or two on why each figure the table may show as '-' is missing, from what the run contains."""
    no_pairs = "no +-rate step pairs" if not r.pairs else ""
    clsf = "CLSF off" if r.clsf_mode == "off" else ("no CLSF periods" if not r.adev else "run too short")
    static = "no hold/soak step" if not r.gyro_adev_deg_per_h else "no ADEV minimum"
    return {
        "steps_planned": "not recorded",
        "sf_measured": no_pairs or "not measured",
        "sf_true_change": no_pairs or "one pair",
        "tempco": (no_pairs or "< 3 pairs or < 0.5 degC span") if len(r.pairs) < 3 else "< 0.5 degC span",
        "accuracy": "CLSF off" if r.clsf_mode == "off" else (no_pairs or "< 2 pairs"),
        "truth": "bench: no truth" if r.mode == "hardware" else (no_pairs or "no truth"),
        "judge": no_pairs or ("no hold/soak step" if not r.gyro_adev_deg_per_h else "ADEV too short"),
        "adev_60": clsf,
        "adev_2000": clsf,
        "adev_min": "CLSF off" if r.clsf_mode == "off" else "no CLSF periods",
        "arw": static if not r.gyro_adev_deg_per_h else "no tau = 1 s",
        "bias_instability": static,
        "bandwidth": "no sine steps" if not r.bode else "-3 dB not crossed",
        "settling": "no table step",
        "linearity": "no level steps" if not r.levels else "< 2 rates",
    }


def render_table(result: AnalysisResult) -> Table:
    """A rich Table of the headline figures; a missing value is '-' with a word or two on why (why_missing)."""
    r = result
    why = why_missing(r)

    def f(v: Any, fmt: str = "{:.4g}", reason: str = "") -> str:
        if _missing(v):
            return f"- ({why[reason]})" if reason else "-"
        return fmt.format(v) if isinstance(v, (int, float)) else str(v)

    tab = Table(title=f"qmg-lab analysis: {Path(r.file).name} ({r.status})", show_header=True)
    tab.add_column("quantity")
    tab.add_column("value", justify="right")
    tab.add_column("unit")
    rows: list[tuple[str, str, str]] = [
        ("campaign / CLSF mode", f"{r.campaign_kind} / {r.clsf_mode}", ""),
        *((k.replace("_", " "), v, "") for k, v in r.run_context.items() if v),
        ("steps completed / planned", f"{r.steps_completed} / {f(r.steps_planned, reason='steps_planned')}", ""),
        (
            "missing steps",
            ", ".join(f"{m['index']}:{m['kind']}" for m in r.missing_steps[:8])
            + (" ..." if len(r.missing_steps) > 8 else "")
            or "none",
            "",
        ),
        (
            "SF nominal / measured",
            f"{f(r.sf_nominal_v_per_dps)} / {f(r.sf_measured_v_per_dps, '{:.6g}', 'sf_measured')}",
            "V/(deg/s)",
        ),
        ("step pairs", f(r.n_step_pairs), ""),
        ("true SF change (p-p)", f(r.sf_true_change_ppm, "{:.1f}", "sf_true_change"), "ppm"),
        (
            "SF tempco true / CLSF",
            _pair(f(r.sf_tempco_ppm_per_c, "{:.1f}"), f(r.clsf_tempco_ppm_per_c, "{:.1f}"), why["tempco"]),
            "ppm/degC",
        ),
        ("CLSF accuracy RMS", f(r.clsf_accuracy_rms_ppm, "{:.1f}", "accuracy"), "ppm"),
        ("CLSF accuracy RMS, mean removed", f(r.clsf_accuracy_rms_ppm_mean_removed, "{:.1f}", "accuracy"), "ppm"),
        ("truth check RMS", f(r.truth_check_rms_ppm, "{:.2f}", "truth"), "ppm"),
        ("table-step noise (predicted)", _judge_noise(r, f(r.table_step_noise_ppm, "{:.2f}", "judge")), "ppm RMS"),
        ("CLSF vs truth RMS", f(r.clsf_vs_truth_rms_ppm, "{:.2f}", "truth"), "ppm"),
        ("CLSF ADEV at 60 s", f(r.adev_at_60s_ppm, "{:.2f}", "adev_60"), "ppm"),
        ("CLSF ADEV at 2000 s", f(r.adev_at_2000s_ppm, "{:.2f}", "adev_2000"), "ppm"),
        ("CLSF ADEV minimum", f(min((x["value"] for x in r.adev), default=None), "{:.2f}", "adev_min"), "ppm"),
        ("ARW", f(r.arw_deg_per_rt_h, "{:.4f}", "arw"), "deg/sqrt(h)"),
        ("bias instability", f(r.bias_instability_deg_per_h, "{:.3f}", "bias_instability"), "deg/h"),
        ("FTR bandwidth (-3 dB)", f(r.bandwidth_hz, "{:.3f}", "bandwidth"), "Hz"),
        ("2 % settling time", f(r.settling_time_s, "{:.3f}", "settling"), "s"),
        (
            "nonlinearity max / RMS",
            _pair(
                f(r.linearity.get("nonlinearity_max_pct_fs"), "{:.3f}"),
                f(r.linearity.get("nonlinearity_rms_pct_fs"), "{:.3f}"),
                why["linearity"],
            ),
            "% FS",
        ),
        ("asymmetry", f(r.linearity.get("asymmetry_ppm"), "{:.0f}", "linearity"), "ppm"),
    ]
    for row in rows:
        tab.add_row(*row)
    return tab


def _judge_noise(r: AnalysisResult, value: str) -> str:
    """The predicted table-step noise with its 68 % range and pair 0's share (qmg_lab/analysis/table_noise.py)."""
    if r.table_step_noise_ppm is None:
        return value
    return (
        f"{value} (68 %: {r.table_step_noise_ppm_low:.2f}-{r.table_step_noise_ppm_high:.2f}; "
        f"pair 0's share {r.table_step_noise_pair0_ppm:.2f})"
    )


def _pair(a: str, b: str, reason: str) -> str:
    """ "a / b"; when both are missing, one '-' with the reason."""
    if a == "-" and b == "-":
        return f"- ({reason})"
    return f"{a} / {b}"
