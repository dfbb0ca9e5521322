"""Soak run: many short simulated campaigns under randomly injected faults, plus SIGKILLed runs that are resumed.

    python benchmarks/faults.py --json [--campaigns 60] [--kills 8] [--seed 1]

Part 1 (in-process, qmg_lab.campaign on the twins): each campaign gets a random [sim.faults] drawn from --seed
(per-reply serial/VISA timeouts and garbles, a link drop of the table, chamber or generator lasting 1-45 s,
sometimes an interlock trip, a chamber overshoot, a sensor dropout, HF2 sample loss, a PLL unlock). A fault
ends "recovered" when its campaign completes, else the campaign must have aborted with the station safe
(checked on the twins' World: table commanded to 0, DS345 muted, chamber at its safe setpoint).
Part 2 (subprocesses): `qmg-lab run` is SIGKILLed at a random step, the file is opened with h5py, then
`--resume` finishes it.

Figures (JSON): faults_injected, campaigns_completed, campaigns_aborted, safe_state_reached (of the aborted),
faults_unresolved (neither recovered nor safe: must be 0), files_unreadable (must be 0), samples_lost (samples
missing from /lockin/time of the final files that no injected HF2 sample loss explains: must be 0),
kills, resumed_completed, unflushed_at_kill_s_max (wall time between the file's last write and the kill:
at most about storage.flush_interval_s), wall_s.
"""

from __future__ import annotations

import argparse
import json
import os
import random
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import h5py
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from qmg_lab.campaign import CampaignRunner  # noqa: E402
from qmg_lab.config import config_fingerprint, parse_config  # noqa: E402
from qmg_lab.station import build_station, make_world  # noqa: E402
from qmg_lab.storage import RunWriter, read_run  # noqa: E402

SAFE_C = 20.0
BASE = f"""
[campaign]
name = "soak"
[loops]
lock_settle_s = 2.0
[clsf]
reference_periods = 21
[plan]
chamber_start_c = 25.0
chamber_end_c = 26.0
chamber_ramp_c_per_min = 2.0
chamber_soak_s = 20.0
chamber_end_hold_s = {{hold}}
dwell_s = 10.0
settle_s = 2.0
[chamber]
sim = true
safe_setpoint_c = {SAFE_C}
[lockin]
sim = true
[generator]
sim = true
[table]
sim = true
[storage]
flush_interval_s = 1.0
"""


def random_faults(rng: random.Random) -> str:
    """One campaign's [sim.faults] section."""
    lines = [f"serial_timeout_prob = {rng.uniform(0, 0.03):.4f}", f"serial_garble_prob = {rng.uniform(0, 0.03):.4f}",
             f"visa_timeout_prob = {rng.uniform(0, 0.05):.4f}", f"visa_garble_prob = {rng.uniform(0, 0.05):.4f}"]
    if rng.random() < 0.6:
        who = rng.choice(["table", "chamber", "generator"])
        at = rng.uniform(1.0, 8.0) if who == "generator" else rng.uniform(5.0, 100.0)
        lines += [f"disconnect_instrument = '{who}'", f"disconnect_at_s = [{at:.2f}]",
                  f"disconnect_duration_s = {rng.choice([1.0, 4.0, 8.0, 20.0, 45.0])}"]
    if rng.random() < 0.1:
        lines.append(f"interlock_trip_at_s = {rng.uniform(10.0, 100.0):.2f}")
    if rng.random() < 0.3:
        lines += [f"chamber_overshoot_at_s = {rng.uniform(10.0, 90.0):.2f}",
                  f"chamber_overshoot_c = {rng.uniform(1.0, 6.0):.2f}"]
    if rng.random() < 0.3:
        lines += [f"chamber_dropout_at_s = {rng.uniform(10.0, 90.0):.2f}",
                  f"chamber_dropout_duration_s = {rng.uniform(1.0, 8.0):.2f}"]
    losses = [f"{rng.uniform(5.0, 100.0):.2f}" for _ in range(rng.randint(0, 2))]
    if losses:
        lines += [f"sample_loss_at_s = [{', '.join(losses)}]", f"sample_loss_count = {rng.randint(1, 500)}"]
    if rng.random() < 0.3:
        lines += [f"pll_unlock_at_s = {rng.uniform(10.0, 90.0):.2f}",
                  f"pll_unlock_duration_s = {rng.uniform(0.5, 5.0):.2f}"]
    return "\n".join(lines)


def missing_samples(path: Path, injected: int) -> int:
    """Samples absent from /lockin/time (gaps of more than one period) beyond the `injected` HF2 losses."""
    with h5py.File(path, "r", swmr=True, libver="latest") as h5:
        t = h5["lockin/time"][:]
    if len(t) < 2:
        return 0
    dt = float(np.median(np.diff(t)))
    gaps = np.diff(t)
    lost = int(np.sum(np.round(gaps[gaps > 1.5 * dt] / dt) - 1))
    return max(0, lost - injected)


def soak(n: int, seed: int, tmp: Path) -> dict[str, int]:
    rng = random.Random(seed)
    fig = dict(faults_injected=0, campaigns_completed=0, campaigns_aborted=0, safe_state_reached=0,
               faults_unresolved=0, files_unreadable=0, samples_lost=0)
    for i in range(n):
        text = BASE.format(hold=50.0) + f"[sim]\nseed = {seed * 1000 + i}\n[sim.faults]\n{random_faults(rng)}\n"
        cfg = parse_config(text)
        world = make_world(cfg)
        station = build_station(cfg, world)
        path = tmp / f"soak{i}.h5"
        writer = RunWriter.create(path, config_text=text, config_sha256=config_fingerprint(text), mode="sim",
                                  software_version="bench", t0_unix=time.time(), compression="none", truth=True,
                                  flush_interval_s=cfg.storage.flush_interval_s)
        runner = CampaignRunner(cfg, station, writer)
        try:
            summary = runner.run()
        except Exception as exc:  # noqa: BLE001 - aborts are expected outcomes here
            summary = runner.summary("aborted", str(exc))
        finally:
            station.close()
            writer.close()
        faults = summary.faults_injected
        n_faults = sum(1 for f in faults if f["kind"] != "link_restored")
        fig["faults_injected"] += n_faults
        safe = (world.table.rate_command_dps == 0.0 and world.dither.amplitude_vpp == 0.0
                and world.chamber.target_c == SAFE_C)
        if summary.status == "completed":
            fig["campaigns_completed"] += 1
        else:
            fig["campaigns_aborted"] += 1
            fig["safe_state_reached"] += int(safe)
            if not safe:
                fig["faults_unresolved"] += n_faults
        try:
            read_run(path)
            injected = sum(int(f["detail"].split()[0]) for f in faults if f["kind"] == "sample_loss")
            fig["samples_lost"] += missing_samples(path, injected)
        except Exception:  # noqa: BLE001
            fig["files_unreadable"] += 1
    return fig


def completed_steps(path: Path) -> int:
    try:
        with h5py.File(path, "r", swmr=True, libver="latest") as h5:
            return int(h5.attrs["completed_steps"])
    except (OSError, KeyError):
        return -1


def kills(n: int, seed: int, tmp: Path) -> dict[str, float]:
    rng = random.Random(seed + 7)
    cfg_path = tmp / "kill.toml"
    cfg_path.write_text(BASE.format(hold=300.0) + f"[sim]\nseed = {seed}\n")  # 38 steps, about 2 s of wall time
    cmd = [sys.executable, "-m", "qmg_lab", "run", str(cfg_path), "-q"]
    fig: dict[str, float] = dict(kills=0, resumed_completed=0, files_unreadable=0, samples_lost=0,
                                 unflushed_at_kill_s_max=0.0)
    for i in range(n):
        path = tmp / f"kill{i}.h5"
        proc = subprocess.Popen([*cmd, "-o", str(path)], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        target = rng.randint(1, 30)
        while completed_steps(path) < target and proc.poll() is None:
            try:
                proc.wait(timeout=0.01)
            except subprocess.TimeoutExpired:
                pass
        try:  # a random moment inside the step, not just at its checkpoint
            proc.wait(timeout=rng.uniform(0.0, 0.1))
        except subprocess.TimeoutExpired:
            pass
        if proc.poll() is not None:
            continue  # finished before the kill: not a kill
        os.kill(proc.pid, signal.SIGKILL)
        killed_at = time.time()
        proc.wait()
        fig["kills"] += 1
        fig["unflushed_at_kill_s_max"] = max(fig["unflushed_at_kill_s_max"], killed_at - path.stat().st_mtime)
        try:
            with h5py.File(path, "r", swmr=True, libver="latest") as h5:
                t = h5["lockin/time"][:]
                if len(t) > 1 and not np.all(np.diff(t) > 0):
                    raise ValueError("time not monotonic")
        except Exception:  # noqa: BLE001
            fig["files_unreadable"] += 1
            continue
        done = subprocess.run([*cmd, "--resume", str(path)], capture_output=True, timeout=300)
        if done.returncode == 0 and read_run(path).status == "completed":
            fig["resumed_completed"] += 1
        fig["samples_lost"] += missing_samples(path, 0)
    return fig


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--json", action="store_true", help="print one JSON object")
    ap.add_argument("--campaigns", type=int, default=60)
    ap.add_argument("--kills", type=int, default=8)
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args()
    t0 = time.monotonic()
    with tempfile.TemporaryDirectory(prefix="qmg-faults-") as d:
        tmp = Path(d)
        s = soak(args.campaigns, args.seed, tmp)
        k = kills(args.kills, args.seed, tmp)
    result = {**s, "files_unreadable": s["files_unreadable"] + int(k["files_unreadable"]),
              "samples_lost": s["samples_lost"] + int(k["samples_lost"]), "kills": int(k["kills"]),
              "resumed_completed": int(k["resumed_completed"]),
              "unflushed_at_kill_s_max": round(k["unflushed_at_kill_s_max"], 3),
              "campaigns": args.campaigns, "seed": args.seed, "wall_s": round(time.monotonic() - t0, 1)}
    if args.json:
        print(json.dumps(result))
    else:
        for key, v in result.items():
            print(f"{key:28s} {v}")


if __name__ == "__main__":
    main()
