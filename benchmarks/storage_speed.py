"""Run-file write cost and size per campaign hour, for both write patterns, per compression; and the cost of reading
an hour of one column back.

Writes `--minutes` of a realistic 1400 Sa/s campaign stream in 2 s blocks (2800 samples): noisy lock-in columns,
a square dither, 7 CLSF rows/s, a table and a chamber row per block, /truth (a slowly drifting true SF and
temperature, a constant rate) at the lock-in sample times. Two write patterns, as the campaign produces them:

* twins (a twin configuration's file, `new_run_file`: big chunks): the world runs ~1000x real time, so a 1 s
  wall-clock flush and the flush at every completed step carry about a minute of data: a flush every 30 blocks
  (60 s of data);
* hardware (a bench configuration's file: smaller chunks): blocks of 0.5 s (700 samples, lockin.poll_interval_s)
  and a flush every 1 s of data (every second block).

Then the campaign's own recording path per lock-in block (`per_block`): `BlockRecorder.record` as the runner calls
it, for `--blocks` blocks of 2 s at 1800 Sa/s (3600 samples: the paper campaign's twin blocks; a 7 Hz square
dither, 14 CLSF rows, a table and a chamber reading, /truth), a /steps row every 30 blocks (a 60 s dwell) and the
wall-clock `maybe_flush`, into a run file created as `qmg-lab run` creates it (configs/paper_campaign.toml at the
full and at the study storage level). Per block: the campaign thread's CPU time (what recording takes from the
simulation), the process's CPU time (the writer thread's writing and compression included) and the wall time,
medians of `--repeats` runs in this process after a short warm-up (numba's cached kernels loaded).

    python benchmarks/storage_speed.py [--minutes 10] [--blocks 1660] [--repeats 5]

Prints JSON: per case MB per campaign hour, write CPU s per campaign hour (append + flush + close), and the
seconds to read one hour of /lockin/rate_output through qmg_lab.storage.reader.read_run; per_block: microseconds
per block per level.
"""

from __future__ import annotations

import argparse
import json
import statistics
import tempfile
import time
import tomllib
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import tomlkit

from qmg_lab.campaign.pipeline import new_run_file
from qmg_lab.campaign.plan import checked_plan
from qmg_lab.campaign.recorder import BlockRecorder
from qmg_lab.clsf.estimator import ClsfPeriods
from qmg_lab.config.schema import parse_config
from qmg_lab.instruments import INSTRUMENT_NAMES, ChamberReading, LockInBlock, TableReading, TruthBlock
from qmg_lab.storage.writer import read_run

FS = 1400.0
ROOT = Path(__file__).resolve().parents[1]
BLOCK_FS = 1800.0  # the paper campaign's twin: 1800 Sa/s in blocks of 2 s
BLOCK_SAMPLES = 3600
DWELL_BLOCKS = 30
POOL_BLOCKS = 10


def lockin_columns(rng: np.random.Generator, t: np.ndarray) -> dict[str, np.ndarray]:
    """The /lockin columns at times t: noisy demodulator and AuxIn readings, a +-0.3 V 7 Hz square dither, the
    table encoder's A/B word at 200 counts/s."""
    n = t.shape[0]
    return dict(
        time=t,
        x_sense=1e-6 * rng.standard_normal(n),
        y_sense=1e-6 * rng.standard_normal(n),
        rate_output=0.3 + 1e-4 * rng.standard_normal(n),
        drive_amplitude=0.5 + 1e-6 * rng.standard_normal(n),
        drive_frequency=2200.0 + 1e-4 * rng.standard_normal(n),
        dither=0.3 * np.sign(np.sin(2 * np.pi * 7 * t)) + 1e-4 * rng.standard_normal(n),
        table_encoder=np.array([0.0, 1.0, 3.0, 2.0])[np.floor(200.0 * t).astype(np.int64) % 4],  # 5 deg/s A/B
        pll_locked=np.ones(n, dtype=np.uint8),
    )


def write_campaign(path: Path, compression: str, minutes: float, truth: bool, realtime: bool) -> dict[str, float]:
    rng = np.random.default_rng(1)
    # the twins' write pattern is the twins' file (/truth, big chunks); the hardware's a bench file (small chunks)
    assert truth != realtime, "a run file has /truth exactly when its lock-in is a twin"
    text = f"[campaign]\nname='bench'\n[storage]\ncompression = '{compression}'\n"
    cfg = parse_config(text)
    cfg = cfg.with_all_sim() if truth else cfg
    w = new_run_file(path, cfg, text, checked_plan(cfg), software_version="bench")
    block = 700 if realtime else 2800
    flush_every = 2 if realtime else 30
    n_blocks = int(minutes * 60 * FS / block)
    t_cpu = 0.0
    for k in range(n_blocks):
        t = (k * block + np.arange(block)) / FS
        cols = lockin_columns(rng, t)
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
    read_run(path, select=("lockin/rate_output",))
    t_read = time.perf_counter() - t0
    return {
        "mb_per_hour": path.stat().st_size / 1e6 / hours,
        "write_cpu_s_per_hour": t_cpu / hours,
        "read_one_column_s_per_hour": t_read / hours,
    }


def campaign_blocks(n_blocks: int, seed: int = 2) -> Iterator[tuple[np.ndarray, LockInBlock, ClsfPeriods, TruthBlock]]:
    """The lock-in blocks, CLSF periods and truth of n_blocks 2 s blocks of a campaign stream. Their noise comes
    from a pool of POOL_BLOCKS blocks (a few MB, warm in the caches as a block the twin has just produced is; a
    compressed chunk spans fewer blocks than the pool); every block gets its own time arrays."""
    rng = np.random.default_rng(seed)
    t0 = np.arange(BLOCK_SAMPLES) / BLOCK_FS
    pool = [lockin_columns(rng, t0 + j * BLOCK_SAMPLES / BLOCK_FS) for j in range(POOL_BLOCKS)]
    tc0 = (np.arange(14) + 1) / 7.0 - 0.5 / BLOCK_FS
    clsf = [[1e-5 * rng.standard_normal(14) for _ in range(4)] for _ in range(POOL_BLOCKS)]
    for k in range(n_blocks):
        cols, noise = pool[k % POOL_BLOCKS], clsf[k % POOL_BLOCKS]
        t = t0 + k * BLOCK_SAMPLES / BLOCK_FS
        block = LockInBlock(**{**cols, "time": t})
        periods = ClsfPeriods(t[0] + tc0, noise[0], noise[1], 1.0 + noise[2], 0.3 + noise[3])
        truth = TruthBlock(t, 0.06 * (1 + 1e-6 * t / 60), 25 + 1e-3 * t, 5.0 + 0 * t)
        yield t, block, periods, truth


def record_per_block(level: str, n_blocks: int, d: Path) -> dict[str, float]:
    """Microseconds per block of BlockRecorder.record and the /steps rows (and set_status, close at the end) into a
    new run file at `level`; the blocks' construction (timed on its own) is subtracted."""
    doc = tomllib.loads((ROOT / "configs" / "paper_campaign.toml").read_text())
    doc.setdefault("storage", {})["level"] = level
    for name in INSTRUMENT_NAMES:
        doc[name]["sim"] = True
    text = tomlkit.dumps(doc)
    cfg = parse_config(text, "paper_campaign.toml")
    path = d / f"per_block_{level}.h5"
    path.unlink(missing_ok=True)
    writer = new_run_file(path, cfg, text, checked_plan(cfg), software_version="bench")
    recorder = BlockRecorder(writer)
    t_step = 0.0
    start = _clocks()
    for k, (t, block, periods, truth) in enumerate(campaign_blocks(n_blocks)):
        reading = TableReading(5.0 * (-1) ** (k // DWELL_BLOCKS), (2.5 * k) % 360.0, 11)
        recorder.record(
            t, block, periods, reading, reading.rate_dps, ChamberReading(25.0, 25.0), truth, 1 / BLOCK_FS, 0.12
        )
        if k % DWELL_BLOCKS == DWELL_BLOCKS - 1:
            writer.append_step(
                index=k // DWELL_BLOCKS,
                kind="rate",
                t_start=t_step,
                t_end=float(t[-1]),
                table_rate=5.0,
                chamber_setpoint=25.0,
                status="completed",
            )
            t_step = float(t[-1])
    writer.set_status("completed")
    writer.close()
    spent = [end - s for end, s in zip(_clocks(), start, strict=True)]
    start = _clocks()  # the same loop without recording: the blocks' construction, not counted
    for k, _ in enumerate(campaign_blocks(n_blocks)):
        TableReading(5.0 * (-1) ** (k // DWELL_BLOCKS), (2.5 * k) % 360.0, 11)
    made = [end - s for end, s in zip(_clocks(), start, strict=True)]
    wall, main, process = ((x - y) / n_blocks * 1e6 for x, y in zip(spent, made, strict=True))
    return {"main_thread_cpu_us": main, "process_cpu_us": process, "wall_us": wall}


def _clocks() -> list[float]:
    """Wall time, the calling thread's CPU time, the process's CPU time (all threads), s."""
    return [time.perf_counter(), time.thread_time(), time.process_time()]


def per_block(n_blocks: int, repeats: int, d: Path) -> dict[str, object]:
    out: dict[str, object] = {"blocks": n_blocks, "block_samples": BLOCK_SAMPLES, "repeats": repeats}
    runs: dict[str, list[dict[str, float]]] = {"full": [], "study": []}
    for level in runs:  # warm-up: numba's cached kernels (edge tracker, integral) load on first use
        record_per_block(level, DWELL_BLOCKS, d)
    for _ in range(repeats):
        for level, rs in runs.items():
            rs.append(record_per_block(level, n_blocks, d))
    for level, rs in runs.items():
        out[level] = {k: round(statistics.median(r[k] for r in rs), 1) for k in rs[0]}
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--minutes", type=float, default=10.0, help="minutes of campaign data to write per case")
    ap.add_argument("--blocks", type=int, default=1660, help="lock-in blocks recorded per level (per_block)")
    ap.add_argument("--repeats", type=int, default=5, help="runs per level for per_block (median quoted)")
    args = ap.parse_args()
    out: dict[str, object] = {"minutes_written": args.minutes, "sample_rate_hz": FS}
    with tempfile.TemporaryDirectory() as d:
        out["per_block"] = per_block(args.blocks, args.repeats, Path(d))
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
