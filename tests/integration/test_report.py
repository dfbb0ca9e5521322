"""write_figures: the paper's figures from a synthetic sweep file; missing data gives skips, not errors; the
linearity figure only from a linearity characterization; every format; every figure titled with its run."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import matplotlib.image as mpimg
import pytest

from qmg_lab.analysis.report import make_figures, write_figures
from tests.support.synthetic_runs import write_linearity, write_sweep


def test_sweep_file_gives_figures_and_names_what_it_skips(tmp_path: Path) -> None:
    p = tmp_path / "sweep.h5"
    write_sweep(p, pairs_written=4)
    out = make_figures(p, tmp_path / "fig")
    names = {x.stem for x in out.written}
    assert names == {"fig1_time_series", "fig4_clsf_io", "fig5_rate_steps", "fig6_sf_true_vs_clsf", "fig7_allan"}
    # a sweep's two step rates are no linearity measurement; no static segment: no gyro Allan deviation
    assert set(out.skipped) == {"fig2_rate_response", "fig3_bandwidth", "fig8_gyro_allan"}
    assert "linearity characterization" in out.skipped["fig2_rate_response"]
    assert "sine" in out.skipped["fig3_bandwidth"]
    assert "static" in out.skipped["fig8_gyro_allan"]
    for path in out.written:
        img = mpimg.imread(path)
        assert img.ndim == 3 and img.shape[0] > 200 and img.shape[1] > 300
    assert [x.stem for x in write_figures(p, tmp_path / "fig2")] == [x.stem for x in out.written]


def test_linearity_figure_from_a_linearity_characterization(tmp_path: Path) -> None:
    p = tmp_path / "lin.h5"
    write_linearity(p, 2e-5)
    out = make_figures(p, tmp_path / "fig")
    assert "fig2_rate_response" in {x.stem for x in out.written}


@pytest.mark.parametrize("fmt", ["svg", "pdf"])
def test_formats_and_titles(tmp_path: Path, fmt: str) -> None:
    p = tmp_path / "sweep.h5"
    write_sweep(p, pairs_written=2)
    written = write_figures(p, tmp_path / "fig", fmt=fmt)  # type: ignore[arg-type]
    assert written and all(x.suffix == f".{fmt}" for x in written)
    if fmt == "svg":  # the title names the run file and its configuration (kind and CLSF mode)
        for x in written:
            text = x.read_text()
            assert "sweep.h5" in text and "temperature_sweep" in text and "observe" in text


def test_every_dash_in_the_table_says_why(tmp_path: Path) -> None:
    """The sweep has no sine, level or hold steps and is shorter than 2000 s: each '-' carries its reason."""
    p = tmp_path / "sweep.h5"
    write_sweep(p, pairs_written=3, truth=False)
    done = subprocess.run(
        [sys.executable, "-m", "qmg_lab", "analyze", str(p), "--figures", str(tmp_path / "f"), "--format", "pdf"],
        capture_output=True,
        text=True,
        env={**os.environ, "COLUMNS": "160"},
    )
    assert done.returncode == 0, done.stderr
    lines = [ln for ln in done.stdout.splitlines() if "│" in ln]
    values = [ln.split("│")[2] for ln in lines]
    bare = re.compile(r"(?<![\w.])-(?![\d.])")  # a '-' that is no minus sign of a number
    assert sum("- (" in v for v in values) >= 5
    assert not [v for v in values if bare.search(re.sub(r"- \([^)]*\)", "", v))]
    text = "\n".join(lines)
    for reason in ("no sine steps", "no level steps", "no hold/soak step", "bench: no truth", "run too short"):
        assert reason in text
    assert (tmp_path / "f" / "fig1_time_series.pdf").is_file()
    bad = subprocess.run(
        [sys.executable, "-m", "qmg_lab", "analyze", str(p), "--format", "gif"], capture_output=True, text=True
    )
    assert bad.returncode == 2 and "png, svg or pdf" in bad.stderr
