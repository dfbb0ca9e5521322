"""A study directory's results: DIR/results.csv (and .parquet), DIR/figures/, and the summary table.

results.csv has one row per point (grid cell and seed), in grid order: point, index, seed, one column per axis
(named by its configuration key), status (ok | failed | lost | missing), error, wall_s, simulated_s, then every
scalar of `qmg-lab analyze --json` (the analysis's own "status" is renamed run_status). A Parquet copy is written
when pyarrow is installed.

Figures: for each metric that varies and each axis, the metric against the axis: one line per combination of the
other axes, the mean over seeds with the spread over seeds (min to max) as error bars; log scales where the values
span a decade or more, and then the fitted log-log slope of each line in its legend (a power law's exponent).
"""

from __future__ import annotations

import csv
import importlib.util
import io
import json
import math
from collections import defaultdict
from pathlib import Path
from typing import Any

import numpy as np

from qmg_lab.study.task import read_record, record_path, write_atomic

BASE_COLUMNS = ("point", "index", "seed")
RUN_COLUMNS = ("status", "error", "wall_s", "simulated_s")
#: the study's own timing: differs between two runs of the same study
WALL_COLUMNS = ("wall_s",)
#: metrics plotted first and shown in the summary table when present
HEADLINE = (
    "clsf_accuracy_rms_ppm",
    "clsf_vs_truth_rms_ppm",
    "adev_at_60s_ppm",
    "adev_at_2000s_ppm",
    "truth_check_rms_ppm",
    "table_step_noise_ppm",
    "sf_true_change_ppm",
    "arw_deg_per_rt_h",
)


def load_meta(out_dir: Path) -> dict[str, Any]:
    """DIR/study.json (written when the study started)."""
    path = out_dir / "study.json"
    if not path.is_file():
        raise FileNotFoundError(f"{out_dir}: not a study directory (no study.json)")
    return dict(json.loads(path.read_text(encoding="utf-8")))


def collect_rows(out_dir: Path) -> tuple[list[str], list[dict[str, Any]]]:
    """(columns, rows) of results.csv from DIR/study.json and the point records; points without a record are
    rows with status "missing"."""
    meta = load_meta(out_dir)
    axes: list[str] = list(meta["axes"])
    rows: list[dict[str, Any]] = []
    metric_names: dict[str, None] = {}  # insertion-ordered set
    for p in meta["points"]:
        path = record_path(out_dir, p["id"])
        rec: dict[str, Any] = read_record(path) if path.exists() else {"status": "missing", "error": "", "metrics": {}}
        row: dict[str, Any] = {"point": p["id"], "index": p["index"], "seed": p["seed"]}
        row.update({a: p["axes"][a] for a in axes})
        row.update({c: rec.get(c) for c in RUN_COLUMNS})
        for k, v in rec.get("metrics", {}).items():
            name = "run_status" if k == "status" else k
            metric_names[name] = None
            row[name] = v
        rows.append(row)
    columns = [*BASE_COLUMNS, *axes, *RUN_COLUMNS, *metric_names]
    return columns, rows


def write_results(out_dir: Path) -> list[Path]:
    """DIR/results.csv, and DIR/results.parquet if pyarrow is installed; returns the files written."""
    columns, rows = collect_rows(out_dir)
    lines: list[list[str]] = [columns]
    for r in rows:
        lines.append(
            ["" if r.get(c) is None else (repr(r[c]) if isinstance(r[c], float) else str(r[c])) for c in columns]
        )
    buf = io.StringIO()
    csv.writer(buf, lineterminator="\n").writerows(lines)
    written = [out_dir / "results.csv"]
    write_atomic(written[0], buf.getvalue())
    if importlib.util.find_spec("pyarrow") is not None:
        import pyarrow as pa
        import pyarrow.parquet as pq

        table = pa.Table.from_pylist([{c: r.get(c) for c in columns} for r in rows])
        pq.write_table(table, out_dir / "results.parquet")
        written.append(out_dir / "results.parquet")
    return written


def numeric_metrics(columns: list[str], rows: list[dict[str, Any]], axes: list[str]) -> list[str]:
    """Metric columns with finite numbers that vary between points (headline metrics first)."""
    skip = {*BASE_COLUMNS, *axes, *RUN_COLUMNS}
    found = []
    for c in columns:
        if c in skip:
            continue
        vals = [r.get(c) for r in rows]
        nums = [float(v) for v in vals if isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)]
        if len(nums) >= 2 and max(nums) > min(nums):
            found.append(c)
    return sorted(found, key=lambda c: (HEADLINE.index(c) if c in HEADLINE else len(HEADLINE), c))


def _spans_decade(values: list[float]) -> bool:
    pos = [v for v in values if v > 0]
    return len(pos) == len(values) and len(pos) >= 2 and max(pos) / min(pos) >= 10.0


def series(
    rows: list[dict[str, Any]], metric: str, axis: str, axes: list[str]
) -> dict[tuple[tuple[str, Any], ...], list[tuple[float, float, float, float, int]]]:
    """For each combination of the other axes: [(x, mean, min, max, n seeds)] over the axis values, from the "ok"
    rows with a finite metric."""
    groups: dict[tuple[tuple[str, Any], ...], dict[float, list[float]]] = defaultdict(lambda: defaultdict(list))
    for r in rows:
        v = r.get(metric)
        if r.get("status") != "ok" or not isinstance(v, (int, float)) or not math.isfinite(v):
            continue
        x = r.get(axis)
        if not isinstance(x, (int, float)) or isinstance(x, bool):
            continue
        key = tuple((a, r.get(a)) for a in axes if a != axis)
        groups[key][float(x)].append(float(v))
    out = {}
    for key, by_x in groups.items():
        out[key] = [(x, float(np.mean(v)), float(np.min(v)), float(np.max(v)), len(v)) for x, v in sorted(by_x.items())]
    return out


def loglog_slope(points: list[tuple[float, float, float, float, int]]) -> float:
    """Least-squares slope of log(mean) against log(x): the exponent of a power law y ∝ x^slope (NaN if < 2)."""
    xy = [(x, m) for x, m, *_ in points if x > 0 and m > 0]
    if len(xy) < 2:
        return float("nan")
    lx, ly = np.log([p[0] for p in xy]), np.log([p[1] for p in xy])
    return float(np.polyfit(lx, ly, 1)[0])


def write_figures(out_dir: Path) -> list[Path]:
    """DIR/figures/<metric>__vs__<axis>.png for every varying metric and every numeric axis."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    meta = load_meta(out_dir)
    axes: list[str] = list(meta["axes"])
    columns, rows = collect_rows(out_dir)
    fig_dir = out_dir / "figures"
    fig_dir.mkdir(exist_ok=True)
    written = []
    for metric in numeric_metrics(columns, rows, axes):
        for axis in axes:
            lines = series(rows, metric, axis, axes)
            if not lines:
                continue
            xs = sorted({p[0] for pts in lines.values() for p in pts})
            ys = [p[1] for pts in lines.values() for p in pts]
            logx, logy = _spans_decade(xs), _spans_decade(ys)
            fig, ax = plt.subplots(figsize=(6.4, 4.4))
            for key, pts in sorted(lines.items(), key=lambda kv: repr(kv[0])):
                x = np.array([p[0] for p in pts])
                m = np.array([p[1] for p in pts])
                err = np.array([[p[1] - p[2] for p in pts], [p[3] - p[1] for p in pts]])
                label = ", ".join(f"{a.split('.')[-1]}={v:g}" if isinstance(v, float) else f"{a}={v}" for a, v in key)
                if logx and logy:
                    label = f"{label + ': ' if label else ''}slope {loglog_slope(pts):+.2f}"
                ax.errorbar(x, m, yerr=err, marker="o", capsize=3, label=label or None)
            ax.set_xscale("log" if logx else "linear")
            ax.set_yscale("log" if logy else "linear")
            ax.set_xlabel(axis)
            ax.set_ylabel(metric)
            n_seeds = len(meta["seeds"])
            ax.set_title(f"{meta['name']}: {metric} (mean of {n_seeds} seeds, bars min-max)", fontsize=9)
            ax.grid(True, which="both", alpha=0.3)
            if any(k for k in lines) or (logx and logy):
                ax.legend(fontsize=7)
            fig.tight_layout()
            path = fig_dir / f"{metric}__vs__{axis}.png"
            fig.savefig(path, dpi=110)
            plt.close(fig)
            written.append(path)
    return written


def summary_table(out_dir: Path) -> Any:
    """A rich Table: one row per grid cell, the status count and the headline metrics' mean ± std over seeds."""
    from rich.table import Table

    meta = load_meta(out_dir)
    axes: list[str] = list(meta["axes"])
    columns, rows = collect_rows(out_dir)
    finite = {c for c in columns for r in rows if isinstance(r.get(c), float) and math.isfinite(r[c])}
    metrics = [m for m in HEADLINE if m in finite][:5]
    by_cell: dict[int, list[dict[str, Any]]] = defaultdict(list)
    for r in rows:
        by_cell[int(r["index"])].append(r)
    counts: dict[str, int] = defaultdict(int)
    for r in rows:
        counts[r["status"]] += 1
    status = ", ".join(f"{n} {s}" for s, n in sorted(counts.items()))
    tab = Table(title=f"study {meta['name']}: {len(rows)} points ({status})")
    for a in axes:
        tab.add_column(a, justify="right")
    tab.add_column("ok/seeds", justify="right")
    for m in metrics:
        tab.add_column(m, justify="right")
    for _, cell in sorted(by_cell.items()):
        ok = [r for r in cell if r["status"] == "ok"]
        vals = []
        for m in metrics:
            v = [float(r[m]) for r in ok if isinstance(r.get(m), (int, float)) and math.isfinite(r[m])]
            vals.append("-" if not v else f"{np.mean(v):.4g}" + (f" ± {np.std(v, ddof=1):.2g}" if len(v) > 1 else ""))
        tab.add_row(*[f"{cell[0][a]}" for a in axes], f"{len(ok)}/{len(cell)}", *vals)
    failed = [r for r in rows if r["status"] in ("failed", "lost")]
    if failed:
        tab.caption = "; ".join(f"{r['point']}: {r['error']}" for r in failed[:5]) + (" ..." if len(failed) > 5 else "")
    return tab
