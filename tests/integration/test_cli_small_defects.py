"""Small defects a new user hit, each held by a test: `analyze --figures` naming a file; `-o` naming a folder;
`watch` and `analyze` wording a file that is not a run file the same way. (`runs DIR | grep aborted`:
tests/integration/test_run_context.py, test_piped_runs_are_whole_tab_separated_rows.)"""

from __future__ import annotations

import subprocess
from pathlib import Path

import h5py
import pytest

from tests.support import synthetic_runs as syn
from tests.support.campaigns import config_text, qmg


def test_analyze_figures_naming_an_existing_file_is_bad_input(tmp_path: Path) -> None:
    run = tmp_path / "sweep.h5"
    syn.write_sweep(run)
    target = tmp_path / "figs.png"
    target.write_bytes(b"an existing file")
    done = subprocess.run(qmg("analyze", str(run), "--figures", str(target)), capture_output=True, text=True)
    words = " ".join(done.stderr.split())  # the console wraps long lines
    assert done.returncode == 2
    assert "--figures" in words and "is a file" in words and "Traceback" not in words
    assert target.read_bytes() == b"an existing file"
    below = subprocess.run(qmg("analyze", str(run), "--figures", str(target / "sub")), capture_output=True, text=True)
    assert below.returncode == 2 and "Traceback" not in below.stderr
    assert "cannot write the figures" in " ".join(below.stderr.split())


def test_output_naming_a_folder_does_not_suggest_resuming_it(tmp_path: Path) -> None:
    cfg = tmp_path / "short.toml"
    cfg.write_text(config_text())
    folder = tmp_path / "runs"
    folder.mkdir()
    done = subprocess.run(qmg("run", str(cfg), "-o", str(folder)), capture_output=True, text=True)
    words = " ".join(done.stderr.split())
    assert done.returncode == 2 and "Traceback" not in words
    assert "--resume" not in words and "is a folder" in words
    assert list(folder.iterdir()) == []


@pytest.mark.parametrize("kind", ["text", "hdf5"])
def test_watch_and_analyze_word_a_non_run_file_the_same_way(tmp_path: Path, kind: str) -> None:
    path = tmp_path / "notes.h5"
    if kind == "text":
        path.write_text("not a run file\n")
    else:
        with h5py.File(path, "w") as h5:  # an HDF5 file of someone else's program
            h5["x"] = [1.0, 2.0]
    analyzed = subprocess.run(qmg("analyze", str(path)), capture_output=True, text=True)
    watched = subprocess.run(qmg("watch", str(path), "--port", "0"), capture_output=True, text=True, timeout=120)
    assert analyzed.returncode == watched.returncode == 2
    assert "Traceback" not in analyzed.stderr + watched.stderr
    assert analyzed.stderr == watched.stderr
    words = " ".join(analyzed.stderr.split())
    assert ("not an HDF5 file" if kind == "text" else "not written by qmg-lab") in words
