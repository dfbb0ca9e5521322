"""Soak of damaged run files: every reader answers within 5 s, in words, whatever the bytes.

    nice python benchmarks/damaged_files.py [--files 120] [--seed 1] [--json]

Two reference files are made with `qmg-lab run` on the twins (the short campaign of tests/support/campaigns.py):
one completed (closed cleanly: its superblock's writer flags clear) and one killed with SIGKILL half-way (flags
set, status "running": what a crash leaves, read through SWMR). From them, `--files` damaged copies, cycling
through the kinds below, each on either reference, at offsets drawn from `--seed`:

* flip_metadata: one byte inverted inside an HDF5 metadata structure (found by its signature: object headers,
  extensible-array and B-tree index blocks of the chunk indices, fractal heaps, free-space records);
* flip_data: one byte inverted inside a chunk of a dataset (its address from h5py's get_chunk_info);
* zero_metadata / zero_data: a 4 KiB-aligned 4 KiB block zeroed, holding a metadata signature / inside chunks;
* truncate: the file cut at a random size (from 8 bytes, the HDF5 signature alone, to the size less one byte).

Every damaged file then meets every reader, each in its own process with a 60 s guard (a hang is counted, not
waited out): `qmg-lab analyze F`, `qmg-lab runs DIR --json` (DIR: F and an intact file; the intact file's row
must be listed), `qmg-lab salvage F -o NEW`, the watch page's reader (`RunFollower.poll`, what `qmg-lab watch`
redraws from), `--resume`'s read-only plan (`check_resumable` with the file's own configuration fingerprint) and
`qmg_lab.open_run(F)` with one group read (`to_pandas("clsf")`).

Counted per command: answers within 5 s and over 5 s of wall time, answers within 5 s of CPU time (the child's
user + system time, its own children included: what the command costs whatever else the machine runs), hangs
(no answer within 60 s), tracebacks (on stderr; a child killed by a signal counts as one), lost listings (`runs`
without the intact file's row), and the median and maximum wall and CPU times; the same commands on the intact
references are the baseline (a Python start with the analysis's imports costs seconds before any file is read).
Exit codes and refusals are not judged here beyond "answered in words": a damaged file may still read (a flipped
data byte in an uncompressed column changes a value, nothing more). Also measured: the cost of `open_run_file` on
the two intact references (each pays the structure worker's walk), median of 5.

The figures go to docs/reliability.md ("Damaged files: every reader answers").
"""

from __future__ import annotations

import argparse
import json
import os
import random
import shutil
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import h5py

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from qmg_lab.storage.runfile import open_run_file  # noqa: E402
from tests.support.campaigns import config_text  # noqa: E402 - imported after sys.path points at this checkout

ANSWER_S = 5.0
GUARD_S = 60.0
#: signatures of HDF5 metadata structures (HDF5 File Format Specification, version 3): object header, extensible
#: array header/index/super/data block, v2 B-tree header/internal/leaf, fractal heap header/direct/indirect block,
#: free-space manager header/section list, object header continuation chunk
SIGNATURES = (b"OHDR", b"EAHD", b"EAIB", b"EASB", b"EADB", b"BTHD", b"BTIN", b"BTLF", b"FRHP", b"FHDB", b"FHIB")
SIGNATURES += (b"FSHD", b"FSSE", b"OCHK")
KINDS = ("flip_metadata", "flip_data", "zero_metadata", "zero_data", "truncate")
COMMANDS = ("analyze", "runs", "salvage", "watch", "resume_plan", "open_run")
ENV = {**os.environ, "PYTHONPATH": str(ROOT)}


def _qmg(*args: str) -> list[str]:
    return [sys.executable, "-m", "qmg_lab", *args]


def references(tmp: Path) -> tuple[Path, Path]:
    """A completed run file and one whose writer was killed half-way (SIGKILL)."""
    cfg = tmp / "short.toml"
    cfg.write_text(config_text())
    done = tmp / "completed.h5"
    subprocess.run(_qmg("run", str(cfg), "-o", str(done), "-q"), check=True, env=ENV, capture_output=True)
    killed = tmp / "killed.h5"
    proc = subprocess.Popen(_qmg("run", str(cfg), "-o", str(killed), "-q"), env=ENV, stdout=subprocess.DEVNULL)
    t0 = time.monotonic()
    while time.monotonic() - t0 < 120:  # until the file holds some steps' data
        time.sleep(0.5)
        if killed.exists() and killed.stat().st_size > 2_000_000:
            break
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    return done, killed


def _chunk_spans(path: Path) -> list[tuple[int, int]]:
    spans: list[tuple[int, int]] = []
    with open_run_file(path) as run:
        h5 = run.h5

        def visit(_: str, obj: object) -> None:
            if isinstance(obj, h5py.Dataset) and obj.chunks is not None:
                for i in range(obj.id.get_num_chunks()):
                    info = obj.id.get_chunk_info(i)
                    if info.size:
                        spans.append((int(info.byte_offset), int(info.byte_offset) + int(info.size)))

        h5.visititems(visit)
    return spans


def _metadata_offsets(raw: bytes) -> list[int]:
    found: list[int] = []
    for sig in SIGNATURES:
        at = raw.find(sig)
        while at >= 0:
            found.append(at)
            at = raw.find(sig, at + 1)
    return sorted(found)


def damage(src: Path, dst: Path, kind: str, rng: random.Random) -> str:
    """Write a damaged copy of src to dst; returns where the damage is."""
    raw = bytearray(src.read_bytes())
    if kind == "truncate":
        size = rng.choice([8, rng.randrange(9, 4096), rng.randrange(4096, len(raw) - 1), len(raw) - 1])
        dst.write_bytes(bytes(raw[:size]))
        return f"cut at {size} of {len(raw)} bytes"
    meta = _metadata_offsets(bytes(raw))
    spans = _chunk_spans(src)
    if kind == "flip_metadata":
        start = rng.choice(meta)
        at = min(start + rng.randrange(4, 48), len(raw) - 1)
        raw[at] ^= 0xFF
        where = f"byte {at} inverted (metadata {bytes(raw[start : start + 4]).decode()} at {start})"
    elif kind == "flip_data":
        a, b = rng.choice(spans)
        at = rng.randrange(a, b)
        raw[at] ^= 0xFF
        where = f"byte {at} inverted (chunk {a}..{b})"
    else:
        if kind == "zero_metadata":
            at = rng.choice(meta) // 4096 * 4096
        else:
            a, b = rng.choice([s for s in spans if s[1] - s[0] >= 4096] or spans)
            at = (a + 4095) // 4096 * 4096
        raw[at : at + 4096] = bytes(min(4096, len(raw) - at))
        where = f"bytes {at}..{at + 4096} zeroed"
    dst.write_bytes(bytes(raw))
    return where


def _one(command: str, path: Path, work: Path, intact: Path, sha: str) -> list[str]:
    """The argv of one reader on one damaged file."""
    if command == "analyze":
        return _qmg("analyze", str(path))
    if command == "runs":
        d = work / "runs"
        shutil.rmtree(d, ignore_errors=True)
        d.mkdir()
        shutil.copyfile(path, d / "damaged.h5")
        shutil.copyfile(intact, d / "intact.h5")
        return _qmg("runs", str(d), "--json")
    if command == "salvage":
        out = work / "salvaged.h5"
        out.unlink(missing_ok=True)
        return _qmg("salvage", str(path), "-o", str(out))
    code = {
        "watch": "from qmg_lab.watch.follow import RunFollower; u = RunFollower(P).poll(); print(u.ready, u.problem)",
        "resume_plan": "from qmg_lab.storage.resume import check_resumable\n"
        "try:\n    check_resumable(P, config_sha256=SHA)\n    print('resumable')\n"
        "except StorageError as e:\n    print('refused:', e)",
        "open_run": "import qmg_lab\ntry:\n    r = qmg_lab.open_run(P); print(r.status, r.to_pandas('clsf').shape)\n"
        "except StorageError as e:\n    print('refused:', e)",
    }[command]
    head = "from pathlib import Path\nfrom qmg_lab.storage.layout import StorageError\n"
    head += f"P = Path({str(path)!r}); SHA = {sha!r}\n"
    return [sys.executable, "-c", head + code]


def _wait(argv: list[str], work: Path) -> tuple[int | None, str, str, float, float | None]:
    """Run argv with the GUARD_S guard: (exit code or None if it hung, stdout, stderr, wall s, CPU s). CPU: the
    child's user + system time, its own waited-for children included (os.wait4's resource usage of that child
    alone, so parallel workers do not mix)."""
    out_path, err_path = work / "stdout.txt", work / "stderr.txt"
    t0 = time.monotonic()
    with open(out_path, "w") as out, open(err_path, "w") as err:
        proc = subprocess.Popen(argv, stdout=out, stderr=err, env=ENV, text=True)
        while True:
            pid, status, usage = os.wait4(proc.pid, os.WNOHANG)  # POSIX: the Linux lab and CI machines
            if pid:
                code = os.waitstatus_to_exitcode(status)
                proc.returncode = code
                cpu: float | None = usage.ru_utime + usage.ru_stime
                break
            if time.monotonic() - t0 > GUARD_S:
                proc.kill()
                proc.wait()
                code, cpu = None, None
                break
            time.sleep(0.02)
    wall = time.monotonic() - t0
    return code, out_path.read_text(), err_path.read_text(), wall, cpu


def run_one(argv: list[str], command: str, work: Path) -> dict[str, object]:
    """One reader on one file: wall and CPU time, hang, traceback, exit code, whether `runs` kept the intact row."""
    code, stdout, stderr, wall, cpu = _wait(argv, work)
    if code is None:
        return {"wall_s": GUARD_S, "cpu_s": None, "hang": True, "traceback": False, "exit": None, "said": ""}
    listed = True
    if command == "runs" and code == 0:
        rows = json.loads(stdout)["runs"]
        listed = any(r["file"].endswith("intact.h5") and "name" in r for r in rows) and len(rows) == 2
    return {
        "wall_s": round(wall, 2),
        "cpu_s": round(cpu, 2) if cpu is not None else None,
        "hang": False,
        "traceback": "Traceback" in stderr or code < 0,
        "exit": code,
        "listed": listed,
        "said": " ".join((stderr + stdout).split())[-300:],
    }


def soak_file(i: int, src: Path, kind: str, seed: int, tmp: Path, intact: Path, sha: str) -> list[dict[str, object]]:
    """Damage one copy of src and put every reader to it; a row per command (in its own work folder)."""
    work = tmp / f"work_{i:03d}"
    work.mkdir()
    path = work / f"damaged_{i:03d}.h5"
    where = damage(src, path, kind, random.Random(seed * 100_003 + i))
    label = f"{kind}/{'closed' if src == intact else 'killed'}"
    rows = []
    for command in COMMANDS:
        row = run_one(_one(command, path, work, intact, sha), command, work)
        rows.append({"file": i, "label": label, "where": where, "command": command, **row})
    shutil.rmtree(work / "runs", ignore_errors=True)
    (work / "salvaged.h5").unlink(missing_ok=True)
    return rows


def open_cost(path: Path) -> float:
    """Median wall time of `open_run_file` on `path` in this process (s), 5 opens after one warm-up; the probe
    cache is cleared each time (`forget_walks`), so each open pays the worker's walk of the file (the worker
    itself is started once, at the warm-up)."""
    from qmg_lab.storage import runfile

    times = []
    for _ in range(6):
        runfile.forget_walks()
        t0 = time.perf_counter()
        with runfile.open_run_file(path):
            pass
        times.append(time.perf_counter() - t0)
    return statistics.median(times[1:])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--files", type=int, default=120, help="damaged files (cycling through the kinds)")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--keep", type=Path, default=None, help="keep the damaged files whose readers failed here")
    ap.add_argument("--workers", type=int, default=1, help="files soaked at once (each reader is its own process)")
    args = ap.parse_args()
    t_start = time.monotonic()
    with tempfile.TemporaryDirectory(prefix="qmg-damaged-") as d:
        tmp = Path(d)
        done, killed = references(tmp)
        with open_run_file(done) as run:
            sha = str(run.attrs["config_sha256"])
        cost = {"completed_open_s": round(open_cost(done), 4), "killed_open_s": round(open_cost(killed), 4)}
        baseline = {  # the same commands on the intact references: what a command costs before any damage
            f"{c}/{label}": run_one(_one(c, ref, tmp, done, sha), c, tmp)
            for label, ref in (("closed", done), ("killed", killed))
            for c in COMMANDS
        }
        per: dict[str, dict[str, list[dict[str, object]]]] = {c: {} for c in COMMANDS}
        failures: list[dict[str, object]] = []
        jobs = [(i, (done, killed)[(i // len(KINDS)) % 2], KINDS[i % len(KINDS)]) for i in range(args.files)]
        with ThreadPoolExecutor(max_workers=args.workers) as pool:
            results = pool.map(lambda j: soak_file(*j, args.seed, tmp, done, sha), jobs)
            for rows in results:
                for row in rows:
                    print(json.dumps(row), file=sys.stderr, flush=True)  # progress: one line per answer
                    per[str(row["command"])].setdefault(str(row["label"]), []).append(row)
                    cpu = row["cpu_s"]
                    if row["hang"] or row["traceback"] or not row.get("listed", True) or (cpu or 0.0) > ANSWER_S:  # type: ignore[operator]
                        failures.append(row)
                        if args.keep is not None:
                            args.keep.mkdir(parents=True, exist_ok=True)
                            name = f"damaged_{int(row['file']):03d}.h5"  # type: ignore[call-overload]
                            shutil.copyfile(tmp / f"work_{int(row['file']):03d}" / name, args.keep / name)  # type: ignore[call-overload]
                if rows:
                    shutil.rmtree(tmp / f"work_{int(rows[0]['file']):03d}", ignore_errors=True)  # type: ignore[call-overload]
    summary: dict[str, object] = {}
    for command, labels in per.items():
        rows = [r for rs in labels.values() for r in rs]
        walls = [float(r["wall_s"]) for r in rows]  # type: ignore[arg-type]
        cpus = [float(r["cpu_s"]) for r in rows if r["cpu_s"] is not None]  # type: ignore[arg-type]
        summary[command] = {
            "calls": len(rows),
            "within_5s": sum(1 for r in rows if not r["hang"] and float(r["wall_s"]) <= ANSWER_S),  # type: ignore[arg-type]
            "over_5s": sum(1 for r in rows if not r["hang"] and float(r["wall_s"]) > ANSWER_S),  # type: ignore[arg-type]
            "hangs": sum(1 for r in rows if r["hang"]),
            "tracebacks": sum(1 for r in rows if r["traceback"]),
            "listing_lost": sum(1 for r in rows if not r.get("listed", True)),
            "cpu_within_5s": sum(1 for c in cpus if c <= ANSWER_S),
            "wall_s_median": round(statistics.median(walls), 2),
            "wall_s_max": round(max(walls), 2),
            "cpu_s_median": round(statistics.median(cpus), 2) if cpus else None,
            "cpu_s_max": round(max(cpus), 2) if cpus else None,
        }
    result = {
        "files": args.files,
        "seed": args.seed,
        "workers": args.workers,
        "kinds": {k: sum(1 for i in range(args.files) if KINDS[i % len(KINDS)] == k) for k in KINDS},
        "open_run_file_cost": cost,
        "intact_baseline": {
            k: {"wall_s": v["wall_s"], "cpu_s": v["cpu_s"], "exit": v["exit"]} for k, v in baseline.items()
        },
        "load_average_1min_at_end": round(os.getloadavg()[0], 1),
        "commands": summary,
        "failures": failures,
        "wall_s": round(time.monotonic() - t_start, 1),
    }
    if args.json:
        print(json.dumps(result))
    else:
        for k, v in result.items():
            print(f"{k:20s} {json.dumps(v)}")


if __name__ == "__main__":
    main()
