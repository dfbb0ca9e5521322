"""The study point's lock (qmg_lab/study/task.py point_lock, on the `filelock` package since fcntl is POSIX-only):
exclusive across processes, and released by the operating system when its holder dies (a killed worker)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
from filelock import FileLock, Timeout

from qmg_lab.study.task import point_lock, points_dir

ROOT = Path(__file__).resolve().parents[2]

HOLDER = (
    "import sys; from pathlib import Path; from qmg_lab.study.task import point_lock\n"
    "with point_lock(Path(sys.argv[1]), 'p0000-s0'):\n"
    "    print('held', flush=True)\n"
    "    sys.stdin.read()  # until the test kills this process\n"
)


@pytest.mark.timeout(120)
def test_a_point_lock_excludes_other_processes_until_its_holder_dies(tmp_path: Path) -> None:
    points_dir(tmp_path).mkdir()
    holder = subprocess.Popen(
        [sys.executable, "-c", HOLDER, str(tmp_path)],
        cwd=ROOT,
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert holder.stdout is not None and holder.stdout.readline().strip() == "held"
        with pytest.raises(Timeout):  # another process holds it: not acquired
            FileLock(points_dir(tmp_path) / "p0000-s0.lock", timeout=0).acquire()
    finally:
        holder.kill()  # dies holding the lock, as a worker killed mid-point
        holder.wait()
    # released by the OS: taken at once (a hang here fails by the test's timeout), and held against others again
    with point_lock(tmp_path, "p0000-s0"), pytest.raises(Timeout):
        FileLock(points_dir(tmp_path) / "p0000-s0.lock", timeout=0).acquire()
