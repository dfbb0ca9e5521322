"""`python -m qmg_lab.storage.probe FILE`: the child process of `open_run_file`'s structure walk
(qmg_lab/storage/runfile.py, step 4). Exit 0 if the walk went through; else exit 1 with the error on stdout."""

from __future__ import annotations

import sys
from pathlib import Path

from qmg_lab.storage.runfile import probe_structure


def main(argv: list[str]) -> int:
    """Walk argv[0]'s structure; the exit code and stdout are what the parent reads."""
    problem = probe_structure(Path(argv[0]))
    if problem:
        print(problem)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
