"""What the child-process structure walk of `open_run_file` (qmg_lab/storage/runfile.py, step 3) costs a user of
the data API: `qmg_lab.open_run(p)`, `.to_xarray()` and the mean of one CLSF variable, as a notebook's first cell
runs them, in a fresh process each time.

Two cases, side by side, each in its own fresh process (`--runs` rounds, alternating):

    probe      the code as it is: open_run has the file walked once by its structure worker (started at the
               process's first file: a Python start with h5py)
    no_probe   the same with the file registered as walked beforehand (runfile's per-process record of walked
               files), so that no child is started: the walk's cost is the difference

and the walk alone: `_probe_in_child` timed in this process (`--runs` times; it keeps no record). The reads run
outside `with`, where each read opens the file for itself (qmg_lab/data/run.py `_RunFile`), and inside it.

Then the price of that per-read open: in one fresh process, the dask mean of /lockin/rate_output over the file's
own chunks (`to_xarray(["lockin"], chunks={})`, one read per chunk), outside and inside `with`, alternating,
`--runs` times each.

    python benchmarks/data_api_probe.py RUN.h5 [--runs N] [--json]

A finished paper campaign to measure on:

    qmg-lab run configs/paper_campaign.toml --sim -o /tmp/paper.h5
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

CASES = ("probe", "no_probe")
VARIABLE = ("clsf", "sf_change_estimate")


def run_case(case: str, path: Path, held: bool) -> dict[str, Any]:
    """One case in this process: the wall time of open_run, to_xarray and the mean (s)."""
    import qmg_lab
    from qmg_lab.storage import runfile

    group, var = VARIABLE
    if case == "no_probe":
        runfile._PROBED.add(runfile._file_key(path))
    t0 = time.perf_counter()
    run = qmg_lab.open_run(path)
    t1 = time.perf_counter()
    if held:
        run.__enter__()
    tree = run.to_xarray()
    t2 = time.perf_counter()
    mean = float(tree[group][var].mean())
    t3 = time.perf_counter()
    run.close()
    return {
        "case": case,
        "held": held,
        "open_run_s": t1 - t0,
        "to_xarray_s": t2 - t1,
        "mean_s": t3 - t2,
        "total_s": t3 - t0,
        "mean": mean,
    }


def dask_mean(path: Path, runs: int) -> dict[str, Any]:
    """Wall time (s) of the dask mean of /lockin/rate_output outside and inside `with` (module doc)."""
    import qmg_lab

    qmg_lab.open_run(path).to_xarray(["clsf"], chunks={})  # imports xarray and dask before any timing
    times: dict[str, list[float]] = {"outside_with": [], "inside_with": []}
    chunks = rows = 0
    for _ in range(runs):
        for held in (False, True):
            run = qmg_lab.open_run(path)
            if held:
                run.__enter__()
            arr = run.to_xarray(["lockin"], chunks={})["lockin"]["rate_output"]
            chunks, rows = int(arr.data.numblocks[0]), int(arr.shape[0])
            t0 = time.perf_counter()
            float(arr.mean().compute())
            times["inside_with" if held else "outside_with"].append(time.perf_counter() - t0)
            run.close()
    return {"chunks": chunks, "rows": rows, **{k: statistics.median(v) for k, v in times.items()}}


def probe_alone(path: Path, runs: int) -> list[float]:
    """Wall time (s) of the child walk alone, `runs` times."""
    from qmg_lab.storage import runfile

    times = []
    for _ in range(runs):
        t0 = time.perf_counter()
        runfile._probe_in_child(path, runfile.PROBE_TIMEOUT_S)
        times.append(time.perf_counter() - t0)
    return times


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("run_file", type=Path)
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--case", choices=CASES, help="run one case in this process (what the parent asks a child)")
    ap.add_argument("--held", action="store_true", help="with --case: read inside `with open_run(...)`")
    ap.add_argument("--dask", action="store_true", help="run the dask part in this process (the parent asks)")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    if args.case:
        print(json.dumps(run_case(args.case, args.run_file, args.held)))
        return
    if args.dask:
        print(json.dumps(dask_mean(args.run_file, args.runs)))
        return
    results: dict[tuple[str, bool], list[dict[str, Any]]] = {(c, h): [] for c in CASES for h in (False, True)}
    for k in range(args.runs):
        order = CASES if k % 2 == 0 else CASES[::-1]
        for held in (False, True):
            for case in order:
                argv = [sys.executable, __file__, str(args.run_file), "--case", case] + (["--held"] if held else [])
                done = subprocess.run(argv, capture_output=True, text=True, check=True)
                results[(case, held)].append(json.loads(done.stdout.strip().splitlines()[-1]))
    alone = probe_alone(args.run_file, args.runs)
    argv = [sys.executable, __file__, str(args.run_file), "--dask", "--runs", str(args.runs)]
    dask = json.loads(subprocess.run(argv, capture_output=True, text=True, check=True).stdout.strip().splitlines()[-1])
    keys = ("open_run_s", "to_xarray_s", "mean_s", "total_s")
    medians = {
        f"{c}{'_held' if h else ''}": {k: statistics.median(r[k] for r in rs) for k in keys}
        for (c, h), rs in results.items()
    }
    out = {
        "file": str(args.run_file),
        "file_mb": args.run_file.stat().st_size / 1e6,
        "runs": args.runs,
        "median_s": medians,
        "probe_alone_median_s": statistics.median(alone),
        "means_agree": len({r["mean"] for rs in results.values() for r in rs}) == 1,
        "dask_mean_lockin_s": dask,
    }
    if args.json:
        print(json.dumps(out, indent=2))
        return
    print(f"{args.run_file} ({out['file_mb']:.0f} MB), medians of {args.runs} fresh processes, s")
    print(f"{'case':<16}" + "".join(f"{k:>13}" for k in keys))
    for name, m in medians.items():
        print(f"{name:<16}" + "".join(f"{m[k]:>13.3f}" for k in keys))
    for held in ("", "_held"):
        p, n = medians[f"probe{held}"]["total_s"], medians[f"no_probe{held}"]["total_s"]
        print(f"probe / no_probe{held or ' (outside with)'}: {p / n:.2f}x ({p - n:+.3f} s)")
    print(f"the child walk alone: {out['probe_alone_median_s']:.3f} s; the means agree: {out['means_agree']}")
    print(
        f"dask mean of /lockin/rate_output ({dask['chunks']} chunks, {dask['rows']} rows): outside with "
        f"{dask['outside_with']:.2f} s, inside with {dask['inside_with']:.2f} s "
        f"({dask['outside_with'] / dask['inside_with']:.1f}x)"
    )


if __name__ == "__main__":
    main()
