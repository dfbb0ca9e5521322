"""Run-file write cost and size per campaign hour, for both write patterns, per compression; and the cost of reading
an hour of one column back.

Writes `--minutes` of a realistic 1400 Sa/s campaign stream in 2 s blocks (2800 samples): noisy lock-in columns,
a square dither, 7 CLSF rows/s, a table and a chamber row per block, /truth (a slowly drifting true SF and
temperature, a constant rate) at the lock-in sample times. Two write patterns, as the campaign produces them:

* twins (`RunWriter.create(realtime=False)`): the world runs ~1000x real time, so a 1 s wall-clock flush and the
  flush at every completed step carry about a minute of data: a flush every 30 blocks (60 s of data);
* hardware (`realtime=True`, smaller chunks): blocks of 0.5 s (700 samples, lockin.poll_interval_s) and a flush
  every 1 s of data (every second block).

    python benchmarks/storage_speed.py [--minutes 10]

Prints JSON: per case MB per campaign hour, write CPU s per campaign hour (append + flush + close), and the
seconds to read one hour of /lockin/rate_output with plain h5py.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import tempfile
import time
from pathlib import Path

import h5py
import numpy as np

from qmg_lab.storage.writer import RunWriter

FS = 1400.0


def write_campaign(path: Path, compression: str, minutes: float, truth: bool, realtime: bool) -> dict[str, float]:
    rng = np.random.default_rng(1)
    text = "[campaign]\nname='bench'\n"
    w = RunWriter.create(
        path,
        config_text=text,
        config_sha256=hashlib.sha256(text.encode()).hexdigest(),
        mode="sim",
        software_version="bench",
        t0_unix=time.time(),
        compression=compression,
        truth=truth,
        flush_interval_s=1e9,
        realtime=realtime,
    )
    block = 700 if realtime else 2800
    flush_every = 2 if realtime else 30
    n_blocks = int(minutes * 60 * FS / block)
    t_cpu = 0.0
    for k in range(n_blocks):
        t = (k * block + np.arange(block)) / FS
        cols = dict(
            time=t,
            x_sense=1e-6 * rng.standard_normal(block),
            y_sense=1e-6 * rng.standard_normal(block),
            rate_output=0.3 + 1e-4 * rng.standard_normal(block),
            drive_amplitude=0.5 + 1e-6 * rng.standard_normal(block),
            drive_frequency=2200.0 + 1e-4 * rng.standard_normal(block),
            dither=0.3 * np.sign(np.sin(2 * np.pi * 7 * t)) + 1e-4 * rng.standard_normal(block),
        )
        n_clsf = block // 200
        tc = t[199::200][:n_clsf]
        tr = dict(time=t, scale_factor=0.06 * (1 + 1e-6 * t / 60), temperature=25 + 1e-3 * t, rate=5.0 + 0 * t)
        t0 = time.perf_counter()
        w.append("lockin", **cols)
        w.append(
            "clsf",
            time=tc,
            eta=1e-5 * rng.standard_normal(n_clsf),
            sf_change_estimate=1e-5 * rng.standard_normal(n_clsf),
            gain_correction=np.ones(n_clsf),
            rate_output_mean=0.3 + 1e-5 * rng.standard_normal(n_clsf),
        )
        w.append(
            "table",
            time=[t[-1]],
            rate_command=[5.0],
            rate_measured=[5.0 + 1e-4 * rng.standard_normal()],
            position=[k * 2.5 % 360],
        )
        w.append("chamber", time=[t[-1]], setpoint=[25.0], temperature=[25 + 1e-3 * rng.standard_normal()])
        if truth:
            w.append("truth", **tr)
        if k % flush_every == flush_every - 1:
            w.flush()
        t_cpu += time.perf_counter() - t0
    t0 = time.perf_counter()
    w.close()
    t_cpu += time.perf_counter() - t0
    hours = n_blocks * block / FS / 3600
    t0 = time.perf_counter()
    with h5py.File(path, "r") as f:
        f["lockin/rate_output"][:]
    t_read = time.perf_counter() - t0
    return {
        "mb_per_hour": path.stat().st_size / 1e6 / hours,
        "write_cpu_s_per_hour": t_cpu / hours,
        "read_one_column_s_per_hour": t_read / hours,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--minutes", type=float, default=10.0, help="minutes of campaign data to write per case")
    args = ap.parse_args()
    out: dict[str, object] = {"minutes_written": args.minutes, "sample_rate_hz": FS}
    with tempfile.TemporaryDirectory() as d:
        for pattern, realtime, truth in (("twins", False, True), ("hardware", True, False)):
            for comp in ("none", "lzf", "gzip"):
                key = f"{pattern}_{comp}{'_with_truth' if truth else ''}"
                out[key] = {
                    k: round(v, 3)
                    for k, v in write_campaign(Path(d) / f"{key}.h5", comp, args.minutes, truth, realtime).items()
                }
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
