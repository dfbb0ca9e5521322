"""write_figures: the paper's figures from a synthetic sweep file; missing data gives skips, not errors."""

from __future__ import annotations

from pathlib import Path

import matplotlib.image as mpimg

from qmg_lab.analysis.report import make_figures, write_figures
from tests.support.synthetic_runs import write_sweep


def test_sweep_file_gives_figures_and_names_what_it_skips(tmp_path: Path) -> None:
    p = tmp_path / "sweep.h5"
    write_sweep(p, pairs_written=4)
    out = make_figures(p, tmp_path / "fig")
    names = {x.stem for x in out.written}
    assert names == {"fig2_rate_response", "fig4_clsf_io", "fig5_rate_steps", "fig6_sf_true_vs_clsf", "fig7_allan"}
    # the synthetic sweep has no static segment: the gyro's Allan deviation is skipped with its reason
    assert set(out.skipped) == {"fig3_bandwidth", "fig8_gyro_allan"} and "sine" in out.skipped["fig3_bandwidth"]
    assert "static" in out.skipped["fig8_gyro_allan"]
    for path in out.written:
        img = mpimg.imread(path)
        assert img.ndim == 3 and img.shape[0] > 200 and img.shape[1] > 300
    assert [x.stem for x in write_figures(p, tmp_path / "fig2")] == [x.stem for x in out.written]
