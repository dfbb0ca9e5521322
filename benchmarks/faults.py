"""Soak run: many short simulated campaigns under randomly injected faults, plus kill -9 / --resume runs compared
with uninterrupted runs of the same seed.

    python benchmarks/faults.py --json [--campaigns 60] [--kills 56] [--resume-kills 24] [--disk-full 8] [--seed 1]

Part 1 (in-process, qmg_lab.campaign.runner on the twins): each campaign gets a random [sim.faults] drawn from --seed
(per-reply serial/VISA timeouts and garbles, a link drop of the table, chamber or generator lasting 1-45 s,
sometimes an interlock trip, a chamber overshoot, a sensor dropout, HF2 sample loss, a PLL unlock). A fault
ends "recovered" when its campaign completes, else the campaign must have aborted with the station safe
(checked on the twins' World: table commanded to 0, DS345 muted, chamber at its safe setpoint).

Part 2 (subprocesses): `qmg-lab run` is killed with SIGKILL at random instants, cycling through the phases
lock (the first lock), dither (its start), table_move (right after a rate command, while the table ramps),
step (a random block of a random step), suspension (while the campaign is suspended by an injected chamber
overshoot or PLL unlock), end (the last step or the safe state at the end), close (inside the final
RunWriter.close) and anywhere (an external kill after a random wall time, which can land inside HDF5 itself).
The in-phase kills are armed by hooks in the child process (this script with --child): at the chosen point a
timer thread sends SIGKILL to its own process after 0-3 ms (or at once), i.e. at a random instant of whatever
runs next. Each killed file is then resumed with a plain `qmg-lab run CONFIG --resume FILE` and compared, group
by group, with an uninterrupted run of the same configuration and seed:
- steps identical: index, kind, table rate, chamber setpoint and status of every planned step, each once, no
  step shorter than planned, no step starting before the previous one ended;
- every time axis continuous and aligned: /lockin sampled at the stream's own sample period (that of the
  uninterrupted run: the HF2 applies its own rate) from 0 to its end, the resume point included; /truth/time
  equal to /lockin/time sample for sample; /table and /chamber at lock-in sample times, one per block; /clsf
  increasing and inside the lock-in record (a dither period ends at a dither edge, between samples);
- the truth check equal to the uninterrupted run's within its noise: |a - b| <= 3 b / sqrt(pairs) + 0.5 ppm (b / sqrt
  of the pairs: the standard error of an RMS of that many pair errors, 3 of them, + 0.5 ppm of rounding), with each
  step's table rate taken as the delivered one (mean /truth/rate over its window, `_truth_checks`): the analysed
  truth check carries the table's once-per-revolution rate ripple, which its encoder does not see and whose bias
  depends on the angles a step covers, and a resumed run continues from the angle where the table stood. Both
  figures are reported.
A kill that lands after the run wrote status "completed" (the end of close) leaves nothing to resume: --resume
must refuse it with exit 2 "already completed"; it counts as resumed ("already_completed").

Part 3 (subprocesses): kills inside `--resume`. A run is killed with SIGKILL in a random step (as in part 2);
then its `--resume` is killed 1-3 times in a row, each at a random instant of its first seconds: half of them
by an external SIGKILL 0-2.5 s after the process starts (start-up, station connect, the file's repair on reopen,
the first blocks), half inside the repair itself, right after its k-th dataset resize (k random: fill values
written, the new extent not yet flushed). A plain `--resume` then finishes the file, which is compared with
the uninterrupted run exactly as in part 2. Also counted: restarts (a checkpoint that a plain resume of the
killed file keeps, lost or rerun: the resume started over instead of continuing), hangs (a process that did not
end within 600 s) and crashes (a traceback, or an end by a signal other than the SIGKILL sent).

Part 4 (subprocesses): disk full. A run gets a file size limit (RLIMIT_FSIZE, what `ulimit -f` sets: the kernel
refuses HDF5's write past it as it refuses one on a full disk, errno EFBIG) at a random fraction of its file's
size; it must end with exit 3, its message saying how much space it needs, no traceback, no crash; then a
`--resume` without the limit (the space freed) must complete it, compared with the uninterrupted run.

Figures (JSON): faults_injected, campaigns_completed, campaigns_aborted, safe_state_reached (of the aborted),
faults_unresolved (neither recovered nor safe: must be 0), files_unreadable (must be 0), samples_lost (samples
missing from /lockin/time of the final files that no injected HF2 sample loss explains: must be 0),
kills, kills_by_phase, resumed (resumed_completed + already_completed: must equal kills), mismatches (must be 0,
with mismatch_details), unflushed_at_kill_s_max (wall time between the file's last write and an external
kill: at most about storage.flush_interval_s), resume_kills (cases, kills_inside_resume, by kind), and
disk_full (runs, exit_3, resumed_completed): each with mismatches, restarts, hangs and crashes (all must be 0),
damaged_files (part 5: `analyze` and `run --resume` of copies cut at 100 B, 4 KiB, 1 %, 50 %, size - 4 KiB: exit
code, expected 2, and wall time of each), wall_s.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import random
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from qmg_lab.campaign.pipeline import run_campaign  # noqa: E402 - imported after sys.path points at this checkout
from qmg_lab.campaign.plan import build_plan  # noqa: E402 - imported after sys.path points at this checkout
from qmg_lab.config.schema import parse_config  # noqa: E402 - imported after sys.path points at this checkout
from qmg_lab.station import build_station, make_world  # noqa: E402 - imported after sys.path points at this checkout
from qmg_lab.storage.writer import read_run  # noqa: E402 - imported after sys.path points at this checkout

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
    lines = [
        f"serial_timeout_prob = {rng.uniform(0, 0.03):.4f}",
        f"serial_garble_prob = {rng.uniform(0, 0.03):.4f}",
        f"visa_timeout_prob = {rng.uniform(0, 0.05):.4f}",
        f"visa_garble_prob = {rng.uniform(0, 0.05):.4f}",
    ]
    if rng.random() < 0.6:
        who = rng.choice(["table", "chamber", "generator"])
        at = rng.uniform(1.0, 8.0) if who == "generator" else rng.uniform(5.0, 100.0)
        lines += [
            f"disconnect_instrument = '{who}'",
            f"disconnect_at_s = [{at:.2f}]",
            f"disconnect_duration_s = {rng.choice([1.0, 4.0, 8.0, 20.0, 45.0])}",
        ]
    if rng.random() < 0.1:
        lines.append(f"interlock_trip_at_s = {rng.uniform(10.0, 100.0):.2f}")
    if rng.random() < 0.3:
        lines += [
            f"chamber_overshoot_at_s = {rng.uniform(10.0, 90.0):.2f}",
            f"chamber_overshoot_c = {rng.uniform(1.0, 6.0):.2f}",
        ]
    if rng.random() < 0.3:
        lines += [
            f"chamber_dropout_at_s = {rng.uniform(10.0, 90.0):.2f}",
            f"chamber_dropout_duration_s = {rng.uniform(1.0, 8.0):.2f}",
        ]
    losses = [f"{rng.uniform(5.0, 100.0):.2f}" for _ in range(rng.randint(0, 2))]
    if losses:
        lines += [f"sample_loss_at_s = [{', '.join(losses)}]", f"sample_loss_count = {rng.randint(1, 500)}"]
    if rng.random() < 0.3:
        lines += [
            f"pll_unlock_at_s = {rng.uniform(10.0, 90.0):.2f}",
            f"pll_unlock_duration_s = {rng.uniform(0.5, 5.0):.2f}",
        ]
    return "\n".join(lines)


def missing_samples(path: Path, injected: int) -> int:
    """Samples absent from /lockin/time (gaps of more than one period) beyond the `injected` HF2 losses."""
    t = read_run(path, select=("lockin/time",)).groups["lockin"]["time"]
    if len(t) < 2:
        return 0
    dt = float(np.median(np.diff(t)))
    gaps = np.diff(t)
    lost = int(np.sum(np.round(gaps[gaps > 1.5 * dt] / dt) - 1))
    return max(0, lost - injected)


def soak(n: int, seed: int, tmp: Path) -> dict[str, int]:
    rng = random.Random(seed)
    fig = dict(
        faults_injected=0,
        campaigns_completed=0,
        campaigns_aborted=0,
        safe_state_reached=0,
        faults_unresolved=0,
        files_unreadable=0,
        samples_lost=0,
    )
    for i in range(n):
        text = BASE.format(hold=50.0) + f"[sim]\nseed = {seed * 1000 + i}\n[sim.faults]\n{random_faults(rng)}\n"
        cfg = parse_config(text)
        world = make_world(cfg)
        station = build_station(cfg, world)
        path = tmp / f"soak{i}.h5"
        try:
            end = run_campaign(cfg, text, path, station=station, software_version="bench")
        finally:
            station.close()
        summary = end.summary
        assert summary is not None, end.message  # the checks before the run passed
        faults = summary.faults_injected
        n_faults = sum(1 for f in faults if f["kind"] != "link_restored")
        fig["faults_injected"] += n_faults
        safe = (
            world.table.rate_command_dps == 0.0
            and world.dither.amplitude_vpp == 0.0
            and world.chamber.target_c == SAFE_C
        )
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
        except Exception:
            fig["files_unreadable"] += 1
    return fig


KILL_CONFIG = (
    BASE.format(hold=100.0)
    + """
[sim]
seed = {seed}
[sim.faults]
chamber_overshoot_at_s = {overshoot_at:.2f}
chamber_overshoot_c = 4.0
pll_unlock_at_s = {unlock_at:.2f}
pll_unlock_duration_s = 2.0
"""
)
PHASES = ("lock", "dither", "table_move", "step", "suspension", "end", "close", "anywhere")


def kill_config(seed: int) -> str:
    """A short campaign (about 190 s simulated) with one chamber overshoot and one PLL unlock: suspensions."""
    rng = random.Random(seed)
    return KILL_CONFIG.format(seed=seed, overshoot_at=rng.uniform(40.0, 120.0), unlock_at=rng.uniform(40.0, 150.0))


def child(phase: str, nth: int, delay_s: float, argv: list[str]) -> None:
    """--child: run the CLI in this process with a hook that SIGKILLs it at the chosen point of `phase`."""
    import threading

    from qmg_lab.campaign import runner as cmp
    from qmg_lab.cli import main as cli
    from qmg_lab.storage import writer as storage

    sys.setswitchinterval(1e-4)  # let the timer thread in between the main thread's bytecodes
    seen = [0]

    def arm() -> None:
        if delay_s <= 0:
            os.kill(os.getpid(), signal.SIGKILL)
        threading.Timer(delay_s, os.kill, (os.getpid(), signal.SIGKILL)).start()

    def count() -> None:
        seen[0] += 1
        if seen[0] == nth:
            arm()

    block, apply_, dither, finish, close = (
        cmp.CampaignRunner._block,
        cmp.CampaignRunner._apply,
        cmp.CampaignRunner._start_dither,
        cmp.CampaignRunner._finish,
        storage.RunWriter.close,
    )

    def hooked_block(self, step, elapsed, want):
        if (
            (phase == "lock" and step.kind == "lock" and step.index == 0)
            or (phase == "step" and step.index >= 0 and step.index == self._kill_step)
            or (phase == "suspension" and self._suspended)
            or (phase == "end" and step.index == len(self.steps) - 1 and nth <= 3)
        ):
            arm() if phase == "end" else count()
        return block(self, step, elapsed, want)

    def hooked_apply(self, step):
        apply_(self, step)
        if phase == "table_move" and step.moves_table:
            count()

    def hooked_dither(self):
        dither(self)
        if phase == "dither":
            count()

    def hooked_finish(self, status, reason):
        if phase == "end" and nth > 3:  # half of the 'end' kills land in the final safe state
            arm()
        return finish(self, status, reason)

    def hooked_close(self):
        if phase == "close":
            arm()
        return close(self)

    if phase == "open":  # killed delay_s after the file is opened for writing (before SWMR, repair, first rows)
        opened = storage._open_for_writing

        def open_and_arm(p, what):
            h5 = opened(p, what)
            arm()
            return h5

        storage._open_for_writing = open_and_arm
    if phase == "repair":  # killed right after the nth dataset resize of the repair on reopen
        import h5py as _h5py

        resize = _h5py.Dataset.resize

        def killing_resize(self, size, axis=None):
            resize(self, size) if axis is None else resize(self, size, axis)
            count()

        _h5py.Dataset.resize = killing_resize
    cmp.CampaignRunner._block = hooked_block
    cmp.CampaignRunner._apply = hooked_apply
    cmp.CampaignRunner._start_dither = hooked_dither
    cmp.CampaignRunner._finish = hooked_finish
    cmp.CampaignRunner._kill_step = random.Random(nth).randint(3, 20)
    storage.RunWriter.close = hooked_close
    sys.argv = ["qmg-lab", *argv]
    cli.main()


def check_against(path: Path, ref: Path, dt: float, poll_s: float) -> list[str]:
    """Differences between a resumed file and the uninterrupted run (see the module docstring)."""
    bad: list[str] = []
    run, want = read_run(path), read_run(ref)
    s, r = run.steps, want.steps
    order = np.argsort(s["index"], kind="stable")
    for col in ("index", "kind", "table_rate", "chamber_setpoint", "status"):
        if s[col][order].tolist() != r[col].tolist():
            bad.append(f"steps/{col} differ")
    if set(s["status"]) != {"completed"}:
        bad.append(f"step statuses {sorted(set(s['status']))}")
    planned = build_plan(parse_config(run.attrs["config_toml"]))
    dur = (s["t_end"] - s["t_start"])[order]
    short = [p.index for p, d in zip(planned, dur, strict=False) if p.kind != "lock" and d < p.duration_s - dt]
    if short:
        bad.append(f"steps {short} shorter than planned")
    ts, te = s["t_start"][order], s["t_end"][order]
    if len(ts) > 1 and np.any(ts[1:] < te[:-1]):
        bad.append("steps overlap")
    g = run.groups
    tl = g["lockin"]["time"]
    if tl[0] != 0.0 or not np.allclose(np.diff(tl), dt, rtol=1e-6, atol=0):
        gaps = np.diff(tl)
        bad.append(f"/lockin/time not continuous (gaps {gaps.min():.6g}..{gaps.max():.6g} s)")
    if not np.array_equal(g["truth"]["time"], tl):
        bad.append(f"/truth/time not equal to /lockin/time ({len(g['truth']['time'])} vs {len(tl)} rows)")
    for grp in ("table", "chamber", "clsf"):
        t = g[grp]["time"]
        if not np.all(np.diff(t) > 0):
            bad.append(f"/{grp}/time not increasing")
        if grp == "clsf":
            if t.size and (t[0] < tl[0] or t[-1] > tl[-1] + dt):
                bad.append("/clsf/time outside the lock-in record")
            continue
        on_grid = np.abs((t - tl[0]) / dt - np.rint((t - tl[0]) / dt)) < 1e-3
        if not on_grid.all():
            bad.append(f"/{grp}/time not at lock-in sample times")
    for grp in ("table", "chamber"):
        if np.diff(g[grp]["time"]).max() > poll_s + dt * 1.5:
            bad.append(f"/{grp} has a gap longer than one block")
    if te.max() > tl[-1]:
        bad.append("a step ends after the data")
    nan_rows = {f"{grp}/{c}": int(np.isnan(v).sum()) for grp, cols in g.items() for c, v in cols.items()}
    if any(nan_rows.values()):  # fill values (NaN) are never data: none may be left in a resumed file
        bad.append(f"NaN rows { ({k: v for k, v in nan_rows.items() if v}) }")
    a, b = _truth_checks(path), _truth_checks(ref)
    TRUTH_CHECKS.append({"file": str(path), "plain_ppm": a[0], "delivered_rates_ppm": a[1], "ref": b})
    if not (np.isfinite(a[1]) and np.isfinite(b[1])):
        bad.append("no truth check")
    else:
        tol = 3.0 * b[1] / np.sqrt(max(b[2], 1)) + 0.5
        if abs(a[1] - b[1]) > tol:
            bad.append(
                f"truth check with the delivered table rates {a[1]:.2f} ppm vs {b[1]:.2f} ppm (tolerance {tol:.2f}); "
                f"as analysed {a[0]:.2f} vs {b[0]:.2f} ppm"
            )
    return bad


#: every comparison's truth checks (as analysed and with the delivered table rates), for the figures
TRUTH_CHECKS: list[dict[str, object]] = []


def _truth_checks(path: Path) -> tuple[float, float, int]:
    """The file's truth check RMS (analysis truth_check_rms_ppm: table-step SF changes e_i against the twin's true
    SF changes t_i), the same with each step's rate taken as the delivered one (mean /truth/rate over its window,
    ppm), and the number of step pairs. The second is the one a resumed file is held to: the table's
    once-per-revolution rate ripple (table_rate_ripple_ppm, 100 ppm) is not seen by its encoder, so the analysed
    e_i carry a rate bias that depends on the angles a step covers; an uninterrupted run covers the same angles in
    every pair (the bias cancels against pair 0), a resumed one continues from the angle where the table stood,
    as a bench would, and its later pairs carry up to about that ripple of bias. With the delivered rates only the
    noise of the output means is left: SF_i = (O+ - O-)/(W+ - W-), e_i = SF_i/SF_0 - 1, RMS(e_i - t_i)."""
    if path in _ANALYSES:
        return _ANALYSES[path]  # type: ignore[no-any-return]
    from qmg_lab.analysis.compute import analyze

    a = analyze(path)
    if a.truth_check_rms_ppm is None or not a.pairs:
        return float("nan"), float("nan"), 0
    truth = read_run(path, select=("truth/time", "truth/rate")).groups["truth"]
    t, w = truth["time"], truth["rate"]

    def delivered(win: tuple[float, float]) -> float:
        m = (t >= win[0]) & (t <= win[1])
        return float(w[m].mean())

    sf = np.array(
        [
            (p.output_plus_v - p.output_minus_v) / (delivered(p.window_plus_s) - delivered(p.window_minus_s))
            for p in a.pairs
        ]
    )
    e = (sf / sf[0] - 1.0) * 1e6
    tr = np.array([p.truth_change_ppm for p in a.pairs])
    out = (float(a.truth_check_rms_ppm), float(np.sqrt(np.mean((e - tr) ** 2))), len(a.pairs))
    if path.name.endswith("-ref.h5"):
        _ANALYSES[path] = out
    return out


_ANALYSES: dict[Path, object] = {}  # the reference files' truth checks, computed once


def references(seeds: list[int], tmp: Path) -> tuple[dict[int, Path], dict[int, Path], float, float]:
    """The kill configuration of each seed and its uninterrupted run; the lock-in's sample period and block."""
    configs, refs = {}, {}
    for sd in seeds:
        configs[sd] = tmp / f"kill{sd}.toml"
        refs[sd] = tmp / f"ref{sd}.h5"
        if refs[sd].exists():
            continue
        configs[sd].write_text(kill_config(sd))
        subprocess.run(
            [sys.executable, "-m", "qmg_lab", "run", str(configs[sd]), "-o", str(refs[sd]), "-q"],
            check=True,
            stdout=subprocess.DEVNULL,
            cwd=ROOT,
        )
    cfg0 = parse_config(configs[seeds[0]].read_text())
    t = read_run(refs[seeds[0]], select=("lockin/time",)).groups["lockin"]["time"]
    dt = float(np.median(np.diff(t[:2000])))  # the sample period the lock-in applied (its rate, read back)
    return configs, refs, dt, cfg0.lockin.sim_poll_interval_s


def kills(n: int, seed: int, tmp: Path) -> dict[str, object]:
    rng = random.Random(seed + 7)
    seeds = [seed * 100 + k for k in range(max(1, min(8, n // 7)))]
    configs, refs, dt, poll_s = references(seeds, tmp)
    fig: dict[str, object] = dict(
        kills=0,
        kills_by_phase={p: 0 for p in PHASES},
        not_killed=0,
        resumed_completed=0,
        already_completed=0,
        resume_failed=0,
        files_unreadable=0,
        mismatches=0,
        mismatch_details=[],
        samples_lost=0,
        unflushed_at_kill_s_max=0.0,
    )
    for i in range(n):
        phase, sd = PHASES[i % len(PHASES)], seeds[i % len(seeds)]
        path = tmp / f"kill{i}.h5"
        run_args = ["run", str(configs[sd]), "-o", str(path), "-q"]
        if phase == "anywhere":
            proc = subprocess.Popen(
                [sys.executable, "-m", "qmg_lab", *run_args],
                stdout=subprocess.DEVNULL,
                stderr=subprocess.DEVNULL,
                cwd=ROOT,
            )
            while not path.exists() and proc.poll() is None:  # the station is up and the file created
                with contextlib.suppress(subprocess.TimeoutExpired):
                    proc.wait(timeout=0.01)
            try:
                proc.wait(timeout=rng.uniform(0.0, 1.0))
            except subprocess.TimeoutExpired:
                os.kill(proc.pid, signal.SIGKILL)
                killed_at = time.time()
                proc.wait()
                if path.exists():
                    fig["unflushed_at_kill_s_max"] = max(
                        float(fig["unflushed_at_kill_s_max"]),
                        killed_at - path.stat().st_mtime,
                    )
        else:
            # the first lock and the dither start happen once per run: their kill follows the first occurrence
            nth = 1 if phase in ("lock", "dither") else rng.randint(1, 3) if phase != "end" else rng.randint(1, 6)
            delay = 0.0 if rng.random() < 0.25 else rng.uniform(0.0, 0.003)
            proc = subprocess.Popen(
                [
                    sys.executable,
                    str(Path(__file__).resolve()),
                    "--child",
                    phase,
                    str(nth),
                    repr(delay),
                    "--",
                    *run_args,
                ],
                stdout=subprocess.DEVNULL,
                stderr=subprocess.DEVNULL,
                cwd=ROOT,
            )
            proc.wait()
        if proc.returncode != -signal.SIGKILL or not path.exists():
            fig["not_killed"] += 1
            continue
        fig["kills"] += 1
        fig["kills_by_phase"][phase] += 1
        try:
            killed = read_run(path)
        except Exception as exc:
            fig["files_unreadable"] += 1
            fig["mismatch_details"].append(f"kill{i} ({phase}): unreadable after the kill: {exc}")
            continue
        done = subprocess.run(
            [sys.executable, "-m", "qmg_lab", "run", str(configs[sd]), "--resume", str(path), "-q"],
            capture_output=True,
            text=True,
            timeout=300,
            cwd=ROOT,
        )
        if done.returncode == 0:
            fig["resumed_completed"] += 1
        elif (
            done.returncode == 2
            and killed.status == "completed"
            and "already completed" in " ".join(done.stderr.split())
        ):
            fig["already_completed"] += 1
        else:
            fig["resume_failed"] += 1
            fig["mismatch_details"].append(
                f"kill{i} ({phase}): resume exit {done.returncode}: {' '.join(done.stderr.split())[-300:]}"
            )
            continue
        try:
            bad = check_against(path, refs[sd], dt, poll_s)
        except Exception as exc:
            fig["files_unreadable"] += 1
            bad = [f"unreadable after the resume: {exc}"]
        if bad:
            fig["mismatches"] += 1
            fig["mismatch_details"].append(f"kill{i} ({phase}, seed {sd}): " + "; ".join(bad))
        fig["samples_lost"] += missing_samples(path, 0)
    fig["resumed"] = int(fig["resumed_completed"]) + int(fig["already_completed"])
    return fig


HANG_S = 600.0


def _child_argv(phase: str, nth: int, delay: float, run_args: list[str]) -> list[str]:
    return [sys.executable, str(Path(__file__).resolve()), "--child", phase, str(nth), repr(delay), "--", *run_args]


def _run(argv: list[str], fig: dict[str, object], **kw: object) -> subprocess.CompletedProcess[str] | None:
    """Run a process to its end; None (a hang counted) if it did not end within HANG_S. A traceback or an end
    by a signal other than SIGKILL counts as a crash."""
    try:
        done = subprocess.run(argv, capture_output=True, text=True, timeout=HANG_S, cwd=ROOT, **kw)  # type: ignore[call-overload]
    except subprocess.TimeoutExpired:
        fig["hangs"] = int(fig["hangs"]) + 1
        return None
    if "Traceback" in done.stderr or (done.returncode < 0 and done.returncode != -signal.SIGKILL):
        fig["crashes"] = int(fig["crashes"]) + 1
        fig["details"].append(f"crash: exit {done.returncode}: {' '.join(done.stderr.split())[-300:]}")
    return done


def _kill_after(argv: list[str], seconds: float, fig: dict[str, object]) -> tuple[int | None, str]:
    """Start a process and SIGKILL it `seconds` after its start (if still running); its exit code and stderr."""
    proc = subprocess.Popen(argv, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, cwd=ROOT)
    try:
        proc.wait(timeout=seconds)
    except subprocess.TimeoutExpired:
        os.kill(proc.pid, signal.SIGKILL)
    try:
        _, err = proc.communicate(timeout=HANG_S)
    except subprocess.TimeoutExpired:
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait()
        fig["hangs"] = int(fig["hangs"]) + 1
        return None, ""
    if "Traceback" in err or (proc.returncode < 0 and proc.returncode != -signal.SIGKILL):
        fig["crashes"] = int(fig["crashes"]) + 1
        fig["details"].append(f"crash: exit {proc.returncode}: {' '.join(err.split())[-300:]}")
    return proc.returncode, err


def _checkpoints(path: Path) -> dict[int, tuple[float, float]]:
    """The checkpoints a plain resume of the file keeps (qmg_lab.storage.resume.kept_checkpoints, read-only)."""
    from qmg_lab.storage.resume import kept_checkpoints

    return kept_checkpoints(path)


def _finish_and_compare(
    path: Path,
    cfg: Path,
    ref: Path,
    dt: float,
    poll_s: float,
    before: dict[int, tuple[float, float]],
    fig: dict[str, object],
    label: str,
) -> None:
    """A plain --resume to the end, then the comparison with the uninterrupted run and the restart check: every
    checkpoint that a plain resume of the killed file keeps (`before`) is in the final file, unchanged (a
    restart reruns them)."""
    done = _run([sys.executable, "-m", "qmg_lab", "run", str(cfg), "--resume", str(path), "-q"], fig)
    if done is None:
        return
    if done.returncode != 0:
        fig["resume_failed"] = int(fig["resume_failed"]) + 1
        fig["details"].append(f"{label}: final resume exit {done.returncode}: {' '.join(done.stderr.split())[-300:]}")
        return
    fig["resumed_completed"] = int(fig["resumed_completed"]) + 1
    after = _checkpoints(path)
    # kills inside the resumes must not lose or rerun a checkpoint that a plain resume of the killed file keeps
    moved = [i for i, v in before.items() if i in after and after[i] != v]
    lost = [i for i in before if i not in after]
    if moved or lost:
        fig["restarts"] = int(fig["restarts"]) + 1
        fig["details"].append(f"{label}: checkpoints rerun {moved}, lost {lost}")
    bad = check_against(path, ref, dt, poll_s)
    if bad:
        fig["mismatches"] = int(fig["mismatches"]) + 1
        fig["details"].append(f"{label}: " + "; ".join(bad))


def _outcome_figures(**counts: object) -> dict[str, object]:
    """The figures of parts 3 and 4: their own counts, then the outcomes every part must keep at 0."""
    zero = ("resumed_completed", "resume_failed", "mismatches", "restarts", "hangs", "crashes")
    return {**counts, **dict.fromkeys(zero, 0), "details": []}


def resume_kills(n: int, seed: int, tmp: Path) -> dict[str, object]:
    """Part 3 (module docstring): kills inside --resume, 1-3 in a row, then a plain --resume."""
    rng = random.Random(seed + 11)
    seeds = [seed * 100 + k for k in range(max(1, min(4, n // 6)))]
    configs, refs, dt, poll_s = references(seeds, tmp)
    fig = _outcome_figures(cases=0, kills_inside_resume=0, by_kind={"external": 0, "repair": 0})
    for i in range(n):
        sd = seeds[i % len(seeds)]
        path = tmp / f"rkill{i}.h5"
        run_args = ["run", str(configs[sd]), "-o", str(path), "-q"]
        code, _ = _kill_after(_child_argv("step", rng.randint(1, 3), rng.uniform(0.0, 0.003), run_args), HANG_S, fig)
        if code != -signal.SIGKILL or not path.exists():
            continue
        fig["cases"] = int(fig["cases"]) + 1
        before = _checkpoints(path)
        resume_args = ["run", str(configs[sd]), "--resume", str(path), "-q"]
        for _ in range(rng.randint(1, 3)):
            if rng.random() < 0.5:
                code, err = _kill_after([sys.executable, "-m", "qmg_lab", *resume_args], rng.uniform(0.0, 2.5), fig)
                kind = "external"
            else:
                code, err = _kill_after(_child_argv("repair", rng.randint(1, 40), 0.0, resume_args), HANG_S, fig)
                kind = "repair"
            if code == -signal.SIGKILL:
                fig["kills_inside_resume"] = int(fig["kills_inside_resume"]) + 1
                fig["by_kind"][kind] += 1  # type: ignore[index]
            elif code == 0:
                break  # the resume ran to its end before the kill came: the run is completed
            else:
                fig["resume_failed"] = int(fig["resume_failed"]) + 1
                fig["details"].append(f"rkill{i}: resume ({kind}) exit {code}: {' '.join(err.split())[-300:]}")
        if read_run(path, select=()).status == "completed":
            continue  # the last resume ran to its end before its kill: nothing left to finish
        _finish_and_compare(path, configs[sd], refs[sd], dt, poll_s, before, fig, f"rkill{i} (seed {sd})")
    return fig


def disk_full(n: int, seed: int, tmp: Path) -> dict[str, object]:
    """Part 4 (module docstring): runs under a file size limit, then resumed without it."""
    import resource

    rng = random.Random(seed + 13)
    seeds = [seed * 100 + k for k in range(max(1, min(4, n // 2)))]
    configs, refs, dt, poll_s = references(seeds, tmp)
    fig = _outcome_figures(runs=0, exit_3=0, space_named=0)
    for i in range(n):
        sd = seeds[i % len(seeds)]
        path = tmp / f"full{i}.h5"
        limit = int(refs[sd].stat().st_size * rng.uniform(0.1, 0.9))

        def limited(limit: int = limit) -> None:
            resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))

        argv = [sys.executable, "-m", "qmg_lab", "run", str(configs[sd]), "-o", str(path), "-q"]
        done = _run(argv, fig, preexec_fn=limited)
        if done is None:
            continue
        fig["runs"] = int(fig["runs"]) + 1
        said = " ".join(done.stderr.split())
        if done.returncode == 3:
            fig["exit_3"] = int(fig["exit_3"]) + 1
        else:
            fig["details"].append(f"full{i}: exit {done.returncode}: {said[-300:]}")
        if "The run needs about" in said:
            fig["space_named"] = int(fig["space_named"]) + 1
        if not path.exists():
            continue
        _finish_and_compare(path, configs[sd], refs[sd], dt, poll_s, _checkpoints(path), fig, f"full{i} (seed {sd})")
    return fig


CUTS = {"100 B": lambda n: 100, "4 KiB": lambda n: 4096, "1 %": lambda n: n // 100, "50 %": lambda n: n // 2}
CUTS["size - 4 KiB"] = lambda n: n - 4096


def damaged_files(seed: int, tmp: Path) -> dict[str, object]:
    """Part 5: `qmg-lab analyze` and `qmg-lab run --resume` on copies of an uninterrupted run's file cut at 100 B,
    4 KiB, 1 %, 50 % and size - 4 KiB: exit code and wall time of each (exit 2 expected, within 5 s, no
    traceback, no hang)."""
    configs, refs, _, _ = references([seed * 100], tmp)
    cfg, ref = configs[seed * 100], refs[seed * 100]
    size = ref.stat().st_size
    fig: dict[str, object] = {"file_bytes": size, "cuts": {}, "hangs": 0, "crashes": 0, "details": []}
    for label, cut in CUTS.items():
        copy = tmp / "cut.h5"
        with open(ref, "rb") as fh:
            copy.write_bytes(fh.read(cut(size)))
        row = {}
        for what, argv in (
            ("analyze", ["analyze", str(copy)]),
            ("resume", ["run", str(cfg), "--resume", str(copy), "-q"]),
        ):
            t0 = time.monotonic()
            done = _run([sys.executable, "-m", "qmg_lab", *argv], fig)
            row[what] = {"exit": None if done is None else done.returncode, "wall_s": round(time.monotonic() - t0, 2)}
        fig["cuts"][label] = row  # type: ignore[index]
    return fig


SHORT_HOLD_S = 50.0  # the writer soaks' campaign: 12 steps, 109 s simulated (BASE with a 50 s end hold)


def short_reference(seed: int, tmp: Path) -> tuple[Path, Path, float, float]:
    """The writer soaks' configuration of `seed` (BASE, no faults) and its uninterrupted run; the lock-in's sample
    period and block, read back from the file."""
    cfg, ref = tmp / f"short{seed}.toml", tmp / f"short{seed}-ref.h5"
    if not ref.exists():
        cfg.write_text(BASE.format(hold=SHORT_HOLD_S) + f"[sim]\nseed = {seed}\n")
        subprocess.run(
            [sys.executable, "-m", "qmg_lab", "run", str(cfg), "-o", str(ref), "-q"],
            check=True,
            stdout=subprocess.DEVNULL,
            cwd=ROOT,
        )
    t = read_run(ref, select=("lockin/time",)).groups["lockin"]["time"]
    return cfg, ref, float(np.median(np.diff(t[:2000]))), parse_config(cfg.read_text()).lockin.sim_poll_interval_s


def _wait_steps(proc: subprocess.Popen[str], path: Path, n: int) -> bool:
    """Wait until the file records n completed steps (True) or the process ends (False)."""
    while proc.poll() is None:
        if completed_steps_now(path) >= n:
            return True
        time.sleep(0.02)
    return False


def resume_window_kills(n: int, seed: int, tmp: Path, deadline: float = float("inf")) -> dict[str, object]:
    """Kills inside `--resume`, each followed by a plain `--resume` that must continue the file to the
    uninterrupted run's data. One killed file per seed (SIGKILL in a random late step), copied for every case;
    the resume of the copy is killed: a third of the cases 0-200 ms after it opened the file for writing (before
    the SWMR start, inside the repair, the first rows: the window the issue found), a third right after the k-th
    dataset resize of its repair, a third by an external SIGKILL 0-2.5 s after the process started."""
    import shutil

    rng = random.Random(seed + 17)
    fig = _outcome_figures(cases=0, kills_inside_resume=0, by_kind={"open_0_200ms": 0, "repair": 0, "external": 0})
    bases: dict[int, tuple[Path, Path, Path, float, float]] = {}
    for sd in (seed * 100 + 50 + k for k in range(4)):
        cfg, ref, dt, poll_s = short_reference(sd, tmp)
        base = tmp / f"window-base{sd}.h5"
        run_args = ["run", str(cfg), "-o", str(base), "-q"]
        code, _ = _kill_after(_child_argv("step", rng.randint(1, 3), rng.uniform(0.0, 0.003), run_args), HANG_S, fig)
        if code == -signal.SIGKILL and base.exists():
            bases[sd] = (base, cfg, ref, dt, poll_s)
    kinds = ("open_0_200ms", "repair", "external")
    for i in range(n):
        if time.monotonic() > deadline:
            fig["stopped_at_deadline"] = True
            break
        sd = list(bases)[i % len(bases)]
        base, cfg, ref, dt, poll_s = bases[sd]
        path = tmp / f"window{i}.h5"
        shutil.copyfile(base, path)
        before = _checkpoints(path)
        resume_args = ["run", str(cfg), "--resume", str(path), "-q"]
        kind = kinds[i % 3]
        if kind == "open_0_200ms":
            code, err = _kill_after(_child_argv("open", 1, rng.uniform(0.0, 0.2), resume_args), HANG_S, fig)
        elif kind == "repair":
            code, err = _kill_after(_child_argv("repair", rng.randint(1, 40), 0.0, resume_args), HANG_S, fig)
        else:
            code, err = _kill_after([sys.executable, "-m", "qmg_lab", *resume_args], rng.uniform(0.0, 2.5), fig)
        fig["cases"] = int(fig["cases"]) + 1
        if code == -signal.SIGKILL:
            fig["kills_inside_resume"] = int(fig["kills_inside_resume"]) + 1
            fig["by_kind"][kind] += 1  # type: ignore[index]
        elif code != 0:
            fig["resume_failed"] = int(fig["resume_failed"]) + 1
            fig["details"].append(f"window{i}: resume ({kind}) exit {code}: {' '.join(err.split())[-300:]}")
        if code == 0 or _completed(path):
            path.unlink()
            continue  # the resume ran to its end before the kill: nothing left to continue
        _finish_and_compare(path, cfg, ref, dt, poll_s, before, fig, f"window{i} ({kind}, seed {sd})")
        path.unlink(missing_ok=True)
    return fig


#: free bytes left on the run's disk when it fills up: from nothing to more than a flush needs
FILL_LEVELS = (0, 4096, 65536, 262144, 1 << 20, 2 << 20, 4 << 20, 6 << 20, 8 << 20, 12 << 20)
#: free bytes left when the disk fills again during the resume: less than the rest of the run needs
REFILL_LEVELS = tuple(x for x in FILL_LEVELS if x <= 1 << 20)
TMPFS_BYTES = 80 << 20  # the small disk: room for the run's check before it starts (raw rate) and its file


def _fill(mount: Path, leave: int) -> Path:
    """Fill the disk at `mount` up to `leave` free bytes with a new file (as another program would); the disk
    keeps whole blocks, so at least `leave` bytes stay free (less than one block more)."""
    filler = mount / f"filler-{time.monotonic_ns()}"
    st = os.statvfs(mount)
    todo = max(st.f_bavail * st.f_frsize - leave, 0) // st.f_frsize * st.f_frsize
    with open(filler, "wb") as fh:
        while todo > 0:
            try:
                todo -= fh.write(b"\0" * min(todo, 1 << 20))
            except OSError:
                break
    return filler


def _needed_bytes(said: str) -> int | None:
    """The space the run asked for, bytes ("The run needs about X MB more")."""
    import re

    m = re.search(r"The run needs about ([0-9.]+) MB more", said)
    return int(float(m.group(1)) * 1e6) if m else None


def disk_full_levels(seed: int, tmp: Path) -> dict[str, object]:
    """A real full disk at every level of FILL_LEVELS, twice in a row: each case runs the writer soaks' campaign on
    a small tmpfs; another program fills the disk to the level after a random step; the run must end with exit
    2 or 3 and words, never exit 0 without every step in the file, never a traceback or a signal (segfault). Then
    the disk fills again during the resume (the second full disk, to at most 1 MiB free). Then exactly the space
    the run asked for is freed and a plain --resume must complete the file to the uninterrupted run's data; every
    file a full disk ended is compared with the uninterrupted run, also when its first resume completed it. Needs
    root (mount) on Linux; otherwise skipped."""
    if sys.platform != "linux" or os.geteuid() != 0:
        return {"skipped": "needs root on Linux to mount a tmpfs"}
    rng = random.Random(seed + 19)
    cfg, ref, dt, poll_s = short_reference(seed * 100 + 70, tmp)
    fig = _outcome_figures(
        cases=0, full_disk_ends=0, false_successes=0, segfaults=0, tracebacks=0, asked_enough=0, asked_not_enough=0
    )
    fig["levels"] = list(FILL_LEVELS)
    fig["exit_codes"] = []
    for i, level in enumerate(FILL_LEVELS):
        mount = tmp / f"disk{i}"
        mount.mkdir()
        subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={TMPFS_BYTES}", "tmpfs", str(mount)], check=True)
        try:
            path = mount / "run.h5"
            codes = []
            said = ""
            for attempt, argv in enumerate(
                (["run", str(cfg), "-o", str(path), "-q"], ["run", str(cfg), "--resume", str(path), "-q"])
            ):
                proc = subprocess.Popen(
                    [sys.executable, "-m", "qmg_lab", *argv],
                    stdout=subprocess.DEVNULL,
                    stderr=subprocess.PIPE,
                    text=True,
                    cwd=ROOT,
                )
                start = max(completed_steps_now(path), 0)
                if _wait_steps(proc, path, start + rng.randint(2, 6) if attempt == 0 else start + 1):
                    # the second time, a level the rest of the run cannot fit in: the disk is full twice in a row
                    _fill(mount, level if attempt == 0 else rng.choice(REFILL_LEVELS))
                try:
                    _, err = proc.communicate(timeout=HANG_S)
                except subprocess.TimeoutExpired:
                    proc.kill()
                    proc.wait()
                    fig["hangs"] = int(fig["hangs"]) + 1
                    err = ""
                said = " ".join(err.split())
                codes.append(proc.returncode)
                if proc.returncode < 0:
                    fig["segfaults" if proc.returncode == -signal.SIGSEGV else "crashes"] = (
                        int(fig["segfaults" if proc.returncode == -signal.SIGSEGV else "crashes"]) + 1
                    )
                if "Traceback" in err:
                    fig["tracebacks"] = int(fig["tracebacks"]) + 1
                if proc.returncode == 0:
                    run = read_run(path, select=())
                    if run.status != "completed" or sorted(set(run.steps["index"])) != list(range(12)):
                        fig["false_successes"] = int(fig["false_successes"]) + 1
                        fig["details"].append(f"disk{i}: exit 0 with status {run.status}")
                    break
                fig["full_disk_ends"] = int(fig["full_disk_ends"]) + 1
                for f in mount.glob("filler-*"):
                    f.unlink()
            fig["cases"] = int(fig["cases"]) + 1
            fig["exit_codes"].append(codes)  # type: ignore[union-attr]
            if _completed(path):
                if codes[0] != 0:  # a full disk ended the run and a resume completed it: held to the reference too
                    _compare(path, ref, dt, poll_s, fig, f"disk{i} (level {level} B)")
                continue
            try:
                before = _checkpoints(path)
            except Exception:  # not readable until a resume heals it: nothing to hold the resume to
                before = {}
            asked = _needed_bytes(said)
            if asked is not None:
                _fill(mount, asked)  # exactly what the run asked for, no more
            done = _run([sys.executable, "-m", "qmg_lab", "run", str(cfg), "--resume", str(path), "-q"], fig)
            if done is not None and asked is not None:
                key = "asked_enough" if done.returncode == 0 else "asked_not_enough"
                fig[key] = int(fig[key]) + 1
                if done.returncode != 0:
                    fig["details"].append(
                        f"disk{i}: asked {asked} B, resume exit {done.returncode}: {done.stderr[-200:]}"
                    )
            for f in mount.glob("filler-*"):
                f.unlink()
            if _completed(path):  # freeing what it asked was enough: the resume completed it
                _compare(path, ref, dt, poll_s, fig, f"disk{i} (level {level} B)")
                continue
            _finish_and_compare(path, cfg, ref, dt, poll_s, before, fig, f"disk{i} (level {level} B)")
            _note_truth_check(path, fig)
        finally:
            subprocess.run(["umount", str(mount)], check=False)
    return fig


def _compare(path: Path, ref: Path, dt: float, poll_s: float, fig: dict[str, object], label: str) -> None:
    """A completed file compared with the uninterrupted run (check_against): counted in `compared`, a difference
    in `mismatches`."""
    fig["compared"] = int(fig.get("compared", 0)) + 1  # type: ignore[call-overload]
    bad = check_against(path, ref, dt, poll_s)
    if bad:
        fig["mismatches"] = int(fig["mismatches"]) + 1  # type: ignore[call-overload]
        fig["details"].append(f"{label}: " + "; ".join(bad))  # type: ignore[attr-defined]
    _note_truth_check(path, fig)


def _note_truth_check(path: Path, fig: dict[str, object]) -> None:
    """The file's truth checks (as analysed, with the delivered table rates), ppm, in fig["truth_checks_ppm"]."""
    if TRUTH_CHECKS and TRUTH_CHECKS[-1]["file"] == str(path):
        fig.setdefault("truth_checks_ppm", []).append(  # type: ignore[union-attr]
            [round(float(TRUTH_CHECKS[-1][k]), 2) for k in ("plain_ppm", "delivered_rates_ppm")]  # type: ignore[arg-type]
        )


def _completed(path: Path) -> bool:
    """The file says "completed" (False while no reader can open it: a writer killed before its SWMR start, which
    the next --resume heals)."""
    try:
        return read_run(path, select=()).status == "completed"
    except Exception:
        return False


def completed_steps_now(path: Path) -> int:
    """The run file's completed_steps attribute, read as a SWMR reader; -1 while it cannot be read. Polled every
    few ms while a campaign runs (a twin campaign of this script takes about 1 s of wall time): opened without
    open_run_file's child walk (probe=False), whose Python start would let the campaign finish between polls."""
    from qmg_lab.storage.runfile import open_run_file

    try:
        with open_run_file(path, probe=False) as run:
            return int(run.attrs["completed_steps"])
    except Exception:  # the writer is laying the file out, or it does not exist yet
        return -1


def output_survival(seed: int, tmp: Path) -> dict[str, object]:
    """A run whose stdout reader dies at once (with progress on, stderr's too) and a run under `nohup` that gets a
    SIGHUP in its middle: exit code and whether the file holds the whole run (status completed, 12 steps)."""
    import shutil

    cfg, _, _, _ = short_reference(seed * 100 + 80, tmp)
    out: dict[str, object] = {}
    for label in ("stdout_reader_died", "nohup_hangup"):
        path = tmp / f"{label}.h5"
        argv = [sys.executable, "-m", "qmg_lab", "run", str(cfg), "-o", str(path)]
        if label == "stdout_reader_died":
            proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, cwd=ROOT)
            assert proc.stdout is not None and proc.stderr is not None
            proc.stdout.close()
            proc.stderr.close()
        else:
            nohup = shutil.which("nohup")
            if nohup is None:
                out[label] = {"skipped": "no nohup"}
                continue
            proc = subprocess.Popen(
                [nohup, *argv, "-q"],
                stdout=subprocess.DEVNULL,
                stderr=subprocess.DEVNULL,
                cwd=ROOT,
                start_new_session=True,
            )
            if _wait_steps(proc, path, 4):  # type: ignore[arg-type]
                proc.send_signal(signal.SIGHUP)
        code = proc.wait(timeout=HANG_S)
        run = read_run(path, select=())
        out[label] = {"exit": code, "status": run.status, "steps": len(set(run.steps["index"]))}
    return out


def main() -> None:
    if len(sys.argv) > 1 and sys.argv[1] == "--child":  # faults.py --child PHASE NTH DELAY -- qmg-lab args
        child(sys.argv[2], int(sys.argv[3]), float(sys.argv[4]), sys.argv[6:])
        return
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--json", action="store_true", help="print one JSON object")
    ap.add_argument("--campaigns", type=int, default=60, help="soak campaigns under random faults (part 1)")
    ap.add_argument("--kills", type=int, default=56, help="kill -9 + --resume runs (part 2)")
    ap.add_argument("--resume-kills", type=int, default=24, help="runs whose --resume is killed (part 3)")
    ap.add_argument("--disk-full", type=int, default=8, help="runs that hit a full disk, then resumed (part 4)")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument(
        "--writer",
        type=int,
        metavar="N",
        help="only the writer's soaks: N kills inside --resume (a third in its first 200 ms of writing), a full "
        "disk at every FILL_LEVELS level twice in a row (root, Linux), a dead stdout reader and nohup + SIGHUP",
    )
    ap.add_argument("--parts", default="kills,disk,output", help="with --writer: which of kills, disk, output")
    ap.add_argument("--deadline-s", type=float, help="with --writer: start no kill case after this many seconds")
    args = ap.parse_args()
    t0 = time.monotonic()
    if args.writer is not None:
        deadline = t0 + args.deadline_s if args.deadline_s else float("inf")
        parts = set(args.parts.split(","))
        with tempfile.TemporaryDirectory(prefix="qmg-faults-") as d:
            tmp = Path(d)
            writer: dict[str, object] = {}
            if "kills" in parts:
                writer["resume_window_kills"] = resume_window_kills(args.writer, args.seed, tmp, deadline)
            if "disk" in parts:
                writer["disk_full_levels"] = disk_full_levels(args.seed, tmp)
            if "output" in parts:
                writer["output"] = output_survival(args.seed, tmp)
            writer.update(seed=args.seed, wall_s=round(time.monotonic() - t0, 1))
        print(json.dumps(writer) if args.json else json.dumps(writer, indent=1))
        return
    with tempfile.TemporaryDirectory(prefix="qmg-faults-") as d:
        tmp = Path(d)
        s = soak(args.campaigns, args.seed, tmp)
        k = kills(args.kills, args.seed, tmp)
        rk = resume_kills(args.resume_kills, args.seed, tmp)
        full = disk_full(args.disk_full, args.seed, tmp) if sys.platform != "win32" else {}
        damaged = damaged_files(args.seed, tmp)
    result = {
        **s,
        "files_unreadable": s["files_unreadable"] + int(k["files_unreadable"]),
        "samples_lost": s["samples_lost"] + int(k["samples_lost"]),
        **{key: v for key, v in k.items() if key not in ("files_unreadable", "samples_lost")},
        "resume_kills": rk,
        "disk_full": full,
        "damaged_files": damaged,
        "campaigns": args.campaigns,
        "seed": args.seed,
        "wall_s": round(time.monotonic() - t0, 1),
    }
    result["unflushed_at_kill_s_max"] = round(float(result["unflushed_at_kill_s_max"]), 3)
    if args.json:
        print(json.dumps(result))
    else:
        for key, v in result.items():
            print(f"{key:28s} {v}")


if __name__ == "__main__":
    main()
