"""Peak memory of the data API (`qmg_lab.open_run(p).to_xarray()`) on a long run file: lazy against eager.

Each case runs in its own child process (`python benchmarks/data_api_memory.py --case NAME RUN.h5`), so that its
peak is its own; the child reports its peak resident set size: `resource.getrusage(RUSAGE_SELF).ru_maxrss`
(KiB on Linux) where the module exists, psutil's `memory_info().peak_wset` on Windows. The cases:

    floor        import qmg_lab, open_run (root attributes, steps, events, snapshots): what every case pays
    lazy         open_run(p).to_xarray(): the tree, no column read (the valid-rows scan of each time column only)
    lazy_mean    to_xarray()["clsf"]["sf_change_estimate"].mean(): xarray's lazy indexing reads that column
    dask_mean    the same with to_xarray(chunks={}): dask over the file's own chunks
    eager_mean   to_xarray(["clsf"]).load() and its mean: the column read whole, the figure to agree with
    eager        to_xarray().load(): every group read into memory (what to_xarray did before it was lazy)

The means are printed with their difference from eager_mean. A 12-hour twin run to measure on (2.4 GB, a few
minutes on two cores):

    sed 's/^duration_s = .*/duration_s = 43200.0/' configs/clsf_adev.toml > /tmp/adev12h.toml
    qmg-lab run /tmp/adev12h.toml --sim -o /tmp/adev12h.h5
    python benchmarks/data_api_memory.py /tmp/adev12h.h5 [--skip-eager] [--json]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

CASES = ("floor", "lazy", "lazy_mean", "dask_mean", "eager_mean", "eager")
VARIABLE = ("clsf", "sf_change_estimate")


def peak_rss_mb() -> float:
    """This process's peak resident set size, MB (10^6 bytes)."""
    try:
        import resource  # POSIX only
    except ImportError:
        import psutil

        return float(psutil.Process().memory_info().peak_wset) / 1e6
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024 / 1e6


def run_case(case: str, path: Path) -> dict[str, Any]:
    """One case in this process: its peak RSS, wall time and (for the means) the mean."""
    import qmg_lab

    group, var = VARIABLE
    t0 = time.perf_counter()
    mean = None
    with qmg_lab.open_run(path) as run:
        if case == "lazy":
            run.to_xarray()
        elif case == "lazy_mean":
            mean = float(run.to_xarray()[group][var].mean())
        elif case == "dask_mean":
            mean = float(run.to_xarray(chunks={})[group][var].mean().compute())
        elif case == "eager_mean":
            mean = float(run.to_xarray([group]).load()[group][var].mean())
        elif case == "eager":
            run.to_xarray().load()
    return {"case": case, "peak_rss_mb": peak_rss_mb(), "wall_s": time.perf_counter() - t0, "mean": mean}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("run_file", type=Path)
    ap.add_argument("--case", choices=CASES, help="run one case in this process (what the parent asks a child)")
    ap.add_argument("--skip-eager", action="store_true", help="leave out the whole-file eager load (GB)")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    if args.case:
        print(json.dumps(run_case(args.case, args.run_file)))
        return
    results = []
    for case in CASES:
        if case == "eager" and args.skip_eager:
            continue
        done = subprocess.run(
            [sys.executable, __file__, str(args.run_file), "--case", case], capture_output=True, text=True, check=True
        )
        results.append(json.loads(done.stdout.strip().splitlines()[-1]))
    eager_mean = next(r["mean"] for r in results if r["case"] == "eager_mean")
    for r in results:
        r["mean_minus_eager"] = None if r["mean"] is None else r["mean"] - eager_mean
    size_gb = args.run_file.stat().st_size / 1e9
    if args.json:
        print(json.dumps({"file": str(args.run_file), "file_gb": size_gb, "cases": results}, indent=2))
        return
    print(f"{args.run_file} ({size_gb:.2f} GB); mean of /{'/'.join(VARIABLE)}")
    print(f"{'case':<12} {'peak RSS MB':>12} {'wall s':>8} {'mean':>14} {'- eager mean':>13}")
    for r in results:
        mean = "" if r["mean"] is None else f"{r['mean']:.6e}"
        diff = "" if r["mean_minus_eager"] is None else f"{r['mean_minus_eager']:.1e}"
        print(f"{r['case']:<12} {r['peak_rss_mb']:>12.0f} {r['wall_s']:>8.1f} {mean:>14} {diff:>13}")


if __name__ == "__main__":
    main()
