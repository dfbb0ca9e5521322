"""Speed, memory and compile time of the QMG twin (sims/gyro.py, sims/carrier.py); prints figures, --json: one object.

Every loop (PLL, AGC, rate, quadrature), every noise source (ARW, bias instability, pickoff) and every
deterministic non-ideality at its default (forcer cubic, feedthrough, Q and damping drift, mode split and its
tempco; the carrier model's 2-omega demodulator ripple) is on, with the 7 Hz square-wave dither and a slow
temperature ramp, so every per-step term is exercised.

* averaged: dt = 1/1800 s (the HF2 power-on rate the campaigns use), blocks of 0.5 s (the [lockin]
  poll_interval_s a real HF2 is polled at), of 2 s (sim_poll_interval_s: the block the HF2 twin runs the gyro in
  during a simulated campaign) and of 60 s; real-time factor = simulated seconds per wall second, and per second
  of this process's CPU time (`*_cpu_*`, all threads: less sensitive to other processes on a shared machine;
  the two agree on an idle one), and the CPU time of the calling thread alone
  (`averaged_cpu_ns_per_step_main_thread`).
* averaged, where the CPU time of a 0.5 s block goes: the compiled kernel alone, the per-step
  normal draws alone, and the rest of GyroSim.run (Python per block).
* carrier: 32 samples per 2.2 kHz cycle (70.4 kS/s), blocks of 0.5 s.
* memory: a 1-hour and a 4-hour averaged run, each in its own process (0.5 s blocks, outputs discarded as the
  HF2 twin would after converting them), peak RSS from resource.getrusage(RUSAGE_SELF).ru_maxrss.
* compile: a fresh process with an empty NUMBA_CACHE_DIR (cold: compile both kernels and run one block each),
  then another with the cache just written (warm).
* HF2 poll path (`hf2_poll_*`, alone with `--hf2-poll-only`): what a simulated campaign's block costs from
  `HF2LI.poll(2 s)` to the arrays it returns, through zhinst-toolkit's Session to the HF2 twin (the world's block
  inputs, the gyro block, the twin's samples and read-only nodes, the driver's arrays): the paper campaign's
  configuration, the 7 Hz square dither, the chamber ramping and the table alternating +-5 deg/s every 60 s.
  Per block: wall time, the time inside the compiled gyro kernel (timed around GyroSim._kernel), and the rest,
  "outside the kernel" (wall, and the calling thread's CPU time); medians over runs of 300 blocks.
* World block (`world_advance_*`, also with `--hf2-poll-only`): `World.advance` alone (sims/world_kernel.py
  `block_inputs`: ramps, table rate with its ripple, chamber lags, the DS345's timebase and exact dither means)
  with the paper's settings (the 7 Hz square dither, the table ramping to 5 deg/s with its 100 ppm ripple, the
  chamber ramping), for 2 s and 10 s blocks: the calling thread's CPU ns per step, median of 7 runs of 100 blocks.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

DT = 1.0 / 1800.0


def _loops():
    from qmg_lab.campaign.loops import lockin_setup
    from qmg_lab.config.schema import Config
    from sims.gyro import LoopSettings, PidSettings, PllSettings

    su = lockin_setup(Config())
    return LoopSettings(
        pll=PllSettings.from_gains(su.pll),
        agc=PidSettings.from_gains(su.agc),
        rate=PidSettings.from_gains(su.rate),
        quadrature=PidSettings.from_gains(su.quadrature),
    )


def _inputs(n: int, dt: float, t0: float):
    """Square-wave dither (7 Hz, 0.3 V = 5 deg/s virtual rate), temperature ramping 1 deg C per hour."""
    from sims.gyro import held_inputs

    t = t0 + dt * np.arange(n)
    square = np.where(np.floor(7.0 * t * 2.0) % 2 == 0, 0.3, -0.3)
    return held_inputs(n, dt, dither_v=square, temperature_c=25.0 + t / 3600.0, t0_s=t0)


def _rt_factors(sim, dt: float, block_s: float, sim_seconds: float) -> tuple[float, float, float]:
    """(wall-clock, process-CPU-time, calling-thread-CPU-time) real-time factors of sim.run over sim_seconds in
    blocks of block_s.

    The CPU-time figure counts only the time this process ran (all its threads), so it moves less than the
    wall-clock one when other processes share the cores (both are equal on an idle machine)."""
    loops = _loops()
    n = int(round(block_s / dt))
    blocks = max(1, int(sim_seconds / block_s))
    pre = [_inputs(n, dt, k * block_s) for k in range(min(blocks, 8))]
    sim.run(pre[0], loops)  # compile / warm up
    t0, c0, th0 = time.perf_counter(), time.process_time(), time.thread_time()
    for k in range(blocks):
        sim.run(pre[k % len(pre)], loops)
    wall, cpu, thread = time.perf_counter() - t0, time.process_time() - c0, time.thread_time() - th0
    return blocks * n * dt / wall, blocks * n * dt / cpu, blocks * n * dt / thread


def _rt_factor(sim, dt: float, block_s: float, sim_seconds: float) -> tuple[float, float]:
    """(wall-clock, process-CPU-time) real-time factors (_rt_factors)."""
    wall, cpu, _ = _rt_factors(sim, dt, block_s, sim_seconds)
    return wall, cpu


def _breakdown(block_s: float = 0.5, blocks: int = 400) -> dict[str, float]:
    """CPU ns per averaged step, split: the compiled kernel alone (noise drawn once
    beforehand), the per-step normal draws alone (NoiseStream.steps), and the rest of GyroSim.run (Python per
    block: input checks, loop vector, bias draws, output block), measured as run minus the two."""
    from sims.gyro import GyroSim
    from sims.noise import NoiseStream
    from tests.support.twin_params import paper_gyro_params

    loops = _loops()
    n = int(round(block_s / DT))
    inp = _inputs(n, DT, 0.0)
    sim = GyroSim(paper_gyro_params(), DT, seed=1)
    sim.run(inp, loops)
    stream = NoiseStream(2, 6, 16)
    noise = stream.steps(n)
    gm = np.zeros((n // sim.gm_steps + 2, 16))
    out = np.empty((11, n))
    lvec = sim._loops_vector(loops)
    temp, rate, dither = inp.gyro_c, inp.table_rate_dps, inp.dither_v

    def cpu_ns(step) -> float:
        c0 = time.process_time()
        for _ in range(blocks):
            step()
        return 1e9 * (time.process_time() - c0) / (blocks * n)

    kernel = cpu_ns(lambda: sim._kernel(temp, rate, dither, noise, gm, out, lvec))
    draws = cpu_ns(lambda: stream.steps(n))
    run = cpu_ns(lambda: sim.run(inp, loops))
    return {
        "averaged_cpu_ns_per_step_kernel": kernel,
        "averaged_cpu_ns_per_step_noise_draws": draws,
        "averaged_cpu_ns_per_step_python": run - kernel - draws,
    }


def _hf2_lockin():
    """The HF2LI driver on the HF2 twin (the paper campaign's configuration, every instrument simulated), loops
    configured, streaming, the DS345's 7 Hz square wave on, the chamber ramping to 35 degC, the table at 5 deg/s."""
    import tomllib

    import tomlkit

    from qmg_lab.campaign.loops import lockin_setup
    from qmg_lab.config.schema import parse_config
    from qmg_lab.instruments import INSTRUMENT_NAMES
    from qmg_lab.station import connect_instrument
    from sims.world import DITHER_SQUARE

    doc = tomllib.loads((ROOT / "configs" / "paper_campaign.toml").read_text())
    for name in INSTRUMENT_NAMES:
        doc[name]["sim"] = True
    cfg = parse_config(tomlkit.dumps(doc))
    connected = connect_instrument(cfg, "lockin")
    lockin = connected.instrument
    world = lockin._session.daq_server.world  # the twin's world: the benchmark plays the other instruments
    lockin.configure(lockin_setup(cfg))
    world.set_dither(function=DITHER_SQUARE, frequency_hz=cfg.dither.frequency_hz, amplitude_vpp=0.6)
    world.set_chamber(35.0, cfg.plan.chamber_ramp_c_per_min)
    world.set_table_rate(cfg.plan.table_rate_dps, cfg.plan.table_accel_dps2)
    lockin.start_stream()
    return connected, lockin, world, cfg


def hf2_poll_costs(blocks: int = 300, runs: int = 5, block_s: float = 2.0) -> dict[str, float]:
    """Per-block cost of the HF2 path of a simulated campaign (module docstring), us: medians over `runs` runs of
    `blocks` polls."""
    import statistics

    from sims.gyro import GyroSim

    res: dict[str, float] = {}
    original = GyroSim._kernel
    spent = {"wall": 0.0, "thread": 0.0}

    def timed_kernel(self, *args):
        t0, c0 = time.perf_counter(), time.thread_time()
        out = original(self, *args)
        spent["wall"] += time.perf_counter() - t0
        spent["thread"] += time.thread_time() - c0
        return out

    GyroSim._kernel = timed_kernel  # the benchmark's stopwatch around the compiled kernel, removed below
    try:
        connected, lockin, world, cfg = _hf2_lockin()
        rate = cfg.plan.table_rate_dps
        dwell_blocks = max(1, int(round(cfg.plan.dwell_s / block_s)))
        for _ in range(20):  # warm up: compiled code loaded, the loops settled
            lockin.poll(block_s)
            world.drain_truth()
        walls, kernels, outside, outside_thread = [], [], [], []
        count = 0
        for _ in range(runs):
            spent["wall"] = spent["thread"] = 0.0
            t0, c0 = time.perf_counter(), time.thread_time()
            for _ in range(blocks):
                lockin.poll(block_s)
                world.drain_truth()  # what the recorder does with the truth every block
                count += 1
                if count % dwell_blocks == 0:
                    rate = -rate
                    world.set_table_rate(rate, cfg.plan.table_accel_dps2)
            wall = (time.perf_counter() - t0) / blocks * 1e6
            thread = (time.thread_time() - c0) / blocks * 1e6
            walls.append(wall)
            kernels.append(spent["wall"] / blocks * 1e6)
            outside.append(wall - spent["wall"] / blocks * 1e6)
            outside_thread.append(thread - spent["thread"] / blocks * 1e6)
        connected.close()
        res["hf2_poll_us_per_block"] = statistics.median(walls)
        res["hf2_poll_kernel_us_per_block"] = statistics.median(kernels)
        res["hf2_poll_outside_kernel_us_per_block"] = statistics.median(outside)
        res["hf2_poll_outside_kernel_thread_cpu_us_per_block"] = statistics.median(outside_thread)
    finally:
        GyroSim._kernel = original
    res["hf2_poll_block_s"] = block_s
    return res


def world_advance_costs(runs: int = 7, blocks: int = 100) -> dict[str, float]:
    """CPU ns per step of World.advance for 2 s and 10 s blocks at DT (module docstring): medians over `runs`."""
    import statistics

    from sims.world import DITHER_SQUARE
    from tests.support.twin_params import paper_world

    res: dict[str, float] = {}
    for block_s in (2.0, 10.0):
        world = paper_world()
        world.set_dither(function=DITHER_SQUARE, frequency_hz=7.0, amplitude_vpp=0.6)
        world.set_table_rate(5.0, 10.0)
        world.set_chamber(35.0, 0.25)
        n = int(round(block_s / DT))
        for _ in range(5):  # compiled code loaded
            world.advance(n, DT)
        per_step = []
        for _ in range(runs):
            c0 = time.thread_time()
            for _ in range(blocks):
                world.advance(n, DT)
            per_step.append((time.thread_time() - c0) / (blocks * n) * 1e9)
        res[f"world_advance_cpu_ns_per_step_{block_s:g}s_blocks"] = statistics.median(per_step)
    return res


def _child_memory(hours: float) -> None:
    import resource  # POSIX only: the memory figures are not measured on Windows

    from sims.gyro import GyroSim
    from tests.support.twin_params import paper_gyro_params

    loops = _loops()
    sim = GyroSim(paper_gyro_params(), DT, seed=1)
    n = int(round(0.5 / DT))
    acc = 0.0
    for k in range(int(hours * 3600 / 0.5)):
        b = sim.run(_inputs(n, DT, k * 0.5), loops)
        acc += float(b.rate_output_v[-1])
    print(json.dumps({"maxrss_kb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss, "check": acc}))


def _child_compile() -> None:
    t0 = time.perf_counter()
    from sims.carrier import CarrierGyroSim
    from sims.gyro import GyroSim
    from tests.support.twin_params import paper_gyro_params

    loops = _loops()
    GyroSim(paper_gyro_params(), DT, seed=1).run(_inputs(10, DT, 0.0), loops)
    c = CarrierGyroSim(paper_gyro_params(), 1.0 / (32 * 2200.0), seed=1)
    c.run(_inputs(10, c.demod_interval_s, 0.0), loops)
    print(json.dumps({"seconds": time.perf_counter() - t0}))


def _run_child(args: list[str], env: dict[str, str] | None = None) -> dict[str, float]:
    out = subprocess.run(
        [sys.executable, str(Path(__file__).resolve()), *args],
        capture_output=True,
        text=True,
        env=env,
        check=True,
        cwd=str(ROOT),
    )
    return json.loads(out.stdout.strip().splitlines()[-1])


def measure(memory_hours: tuple[float, float] = (1.0, 4.0)) -> dict[str, float | int | str]:
    from sims.carrier import CarrierGyroSim
    from sims.gyro import GyroSim
    from tests.support.twin_params import paper_gyro_params

    res: dict[str, float | int | str] = {}
    env = dict(os.environ)
    with tempfile.TemporaryDirectory() as cache:
        env["NUMBA_CACHE_DIR"] = cache
        res["compile_cold_s"] = _run_child(["--child-compile"], env)["seconds"]
        res["compile_warm_s"] = _run_child(["--child-compile"], env)["seconds"]

    rt_avg, cpu_avg, main_avg = _rt_factors(GyroSim(paper_gyro_params(), DT, seed=1), DT, 0.5, 600.0)
    res["averaged_realtime_factor"] = rt_avg
    res["averaged_steps_per_s"] = rt_avg / DT
    res["averaged_ns_per_step"] = 1e9 * DT / rt_avg
    res["averaged_cpu_realtime_factor"] = cpu_avg
    res["averaged_cpu_ns_per_step"] = 1e9 * DT / cpu_avg
    res["averaged_cpu_ns_per_step_main_thread"] = 1e9 * DT / main_avg
    rt2, cpu2 = _rt_factor(GyroSim(paper_gyro_params(), DT, seed=1), DT, 2.0, 600.0)
    res["averaged_realtime_factor_2s_blocks"] = rt2
    res["averaged_cpu_realtime_factor_2s_blocks"] = cpu2
    rt60, cpu60 = _rt_factor(GyroSim(paper_gyro_params(), DT, seed=1), DT, 60.0, 1200.0)
    res["averaged_realtime_factor_60s_blocks"] = rt60
    res["averaged_cpu_realtime_factor_60s_blocks"] = cpu60
    res.update(_breakdown())
    car = CarrierGyroSim(paper_gyro_params(), 1.0 / (32 * 2200.0), seed=1)
    rt_car, cpu_car = _rt_factor(car, car.demod_interval_s, 0.5, 20.0)
    res["carrier_realtime_factor"] = rt_car
    res["carrier_samples_per_s"] = rt_car * 32 * 2200.0
    res["carrier_cpu_realtime_factor"] = cpu_car

    res.update(hf2_poll_costs())
    res.update(world_advance_costs())
    short, long_ = memory_hours
    m1 = _run_child(["--child-memory", str(short)])["maxrss_kb"]
    m4 = _run_child(["--child-memory", str(long_)])["maxrss_kb"]
    res[f"peak_rss_{short:g}h_mb"] = m1 / 1024.0
    res[f"peak_rss_{long_:g}h_mb"] = m4 / 1024.0
    res["peak_rss_ratio_long_over_short"] = m4 / m1
    res["cpu_count"] = os.cpu_count() or 0
    res["load_average_1min"] = os.getloadavg()[0]
    return res


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", action="store_true", help="print one JSON object")
    ap.add_argument("--child-memory", type=float, default=None, help=argparse.SUPPRESS)
    ap.add_argument("--child-compile", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--hf2-poll-only", action="store_true", help="only the HF2 poll path figures (hf2_poll_*)")
    a = ap.parse_args(argv)
    if a.child_memory is not None:
        _child_memory(a.child_memory)
        return 0
    if a.child_compile:
        _child_compile()
        return 0
    res: dict[str, float | int | str] = dict(hf2_poll_costs()) if a.hf2_poll_only else measure()
    if a.hf2_poll_only:
        res.update(world_advance_costs())
        res["load_average_1min"] = os.getloadavg()[0]
    if a.json:
        print(json.dumps(res))
    else:
        for k, v in res.items():
            print(f"{k:40s} {v:.4g}" if isinstance(v, float) else f"{k:40s} {v}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
