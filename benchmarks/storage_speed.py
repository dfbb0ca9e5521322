"""Run-file write speed and size: samples/s appended and MB per hour of a 1400 Sa/s campaign, per compression.

Writes `--minutes` of a realistic campaign stream (noisy lock-in columns, 7 CLSF rows/s, table/chamber rows,
/truth at the lock-in rate) in 0.5 s blocks of 700 samples, flushing once per second of data (the hardware
case: flush_interval_s = 1 s of wall time = 1 s of data), and prints JSON figures.

    /work/venv/bin/python benchmarks/storage_speed.py [--minutes 5]
"""

from __future__ import annotations

import argparse
import hashlib
import json
import tempfile
import time
from pathlib import Path

import numpy as np

from qmg_lab.storage import RunWriter, read_run

FS = 1400.0
BLOCK = 700


def write_campaign(path: Path, compression: str, minutes: float, truth: bool) -> dict[str, float]:
    rng = np.random.default_rng(1)
    text = "[campaign]\nname='bench'\n"
    w = RunWriter.create(path, config_text=text, config_sha256=hashlib.sha256(text.encode()).hexdigest(),
                         mode="sim", software_version="bench", t0_unix=time.time(), compression=compression,
                         truth=truth, flush_interval_s=1e9)
    n_blocks = int(minutes * 60 * FS / BLOCK)
    t_cpu = 0.0
    for k in range(n_blocks):
        t = (k * BLOCK + np.arange(BLOCK)) / FS
        cols = dict(time=t, x_sense=1e-6 * rng.standard_normal(BLOCK), y_sense=1e-6 * rng.standard_normal(BLOCK),
                    rate_output=0.3 + 1e-4 * rng.standard_normal(BLOCK),
                    drive_amplitude=0.5 + 1e-6 * rng.standard_normal(BLOCK),
                    drive_frequency=2200.0 + 1e-4 * rng.standard_normal(BLOCK),
                    dither=0.3 * np.sign(np.sin(2 * np.pi * 7 * t)) + 1e-4 * rng.standard_normal(BLOCK))
        tc = np.arange(1, 4) / 7 + k * 0.5
        tr = dict(time=t, scale_factor=0.06 + 1e-9 * t, temperature=25 + 1e-4 * t, rate=5.0 + 0 * t)
        t0 = time.perf_counter()
        w.append("lockin", **cols)
        w.append("clsf", time=tc, eta=1e-5 * rng.standard_normal(3), sf_change_estimate=1e-5 * rng.standard_normal(3),
                 gain_correction=np.ones(3), rate_output_mean=0.3 + 1e-5 * rng.standard_normal(3))
        w.append("table", time=[t[-1]], rate_command=[5.0], rate_measured=[5.0 + 1e-4 * rng.standard_normal()],
                 position=[k * 2.5 % 360])
        w.append("chamber", time=[t[-1]], setpoint=[25.0], temperature=[25 + 1e-3 * rng.standard_normal()])
        if truth:
            w.append("truth", **tr)
        if k % 2 == 1:
            w.flush()
        t_cpu += time.perf_counter() - t0
    t0 = time.perf_counter()
    w.close()
    t_cpu += time.perf_counter() - t0
    size = path.stat().st_size
    t0 = time.perf_counter()
    read_run(path, select=["lockin/rate_output"])
    t_read = time.perf_counter() - t0
    samples = n_blocks * BLOCK
    hours = samples / FS / 3600
    return {"lockin_samples_per_s_written": samples / t_cpu, "realtime_factor": samples / FS / t_cpu,
            "mb_per_hour": size / 1e6 / hours, "raw_mb_per_hour_lockin_only": 7 * 8 * FS * 3600 / 1e6,
            "read_rate_output_s_per_hour": t_read / hours}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--minutes", type=float, default=5.0, help="minutes of campaign data to write per case")
    args = ap.parse_args()
    out: dict[str, object] = {"minutes_written": args.minutes, "block_samples": BLOCK, "flush_every_s_of_data": 1.0}
    with tempfile.TemporaryDirectory() as d:
        for truth in (False, True):
            for comp in ("none", "lzf", "gzip"):
                key = f"{comp}{'_with_truth' if truth else ''}"
                out[key] = {k: round(v, 3) for k, v in
                            write_campaign(Path(d) / f"{key}.h5", comp, args.minutes, truth).items()}
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
