"""`qmg-lab characterize sf-model RUN -o model.json`: the whole-SF calibration's pickoff-ratio model from a
characterisation run (qmg_lab/analysis/calibrated_sf.py, qmg_lab/clsf/pickoff_model.py), and the rendering of the
calibrated SF that `qmg-lab analyze RUN --sf-model model.json` prints beside the CLSF-only figures.

The characterisation run is an ordinary temperature sweep (configs/sf_characterisation.toml: another temperature
path than the evaluated run, long table dwells so that the loop's tail has died in each window); its table steps
teach the model. The evaluated run's table steps only judge.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Annotated

import typer
from rich.table import Table

from qmg_lab.cli.common import EXIT_BAD_INPUT, JsonOpt, characterize_app, fail, out


def characterize_sf_model(
    run_file: Annotated[Path, typer.Argument(help="the characterisation run (HDF5)", show_default=False)],
    output: Annotated[Path, typer.Option("-o", "--output", help="model file to write (JSON)")],
    json_out: JsonOpt = False,
) -> None:
    """Fit the pickoff-ratio model (drive frequency as thermometer, one front-end lag) to a run's table steps."""
    from qmg_lab.analysis.calibrated_sf import characterise
    from qmg_lab.storage.layout import StorageError

    if not run_file.exists():
        fail(EXIT_BAD_INPUT, f"{run_file}: no such run file")
    try:
        model = characterise(run_file)
    except (ValueError, StorageError) as exc:
        fail(EXIT_BAD_INPUT, str(exc))
    try:
        model.save(output)
    except OSError as exc:
        fail(EXIT_BAD_INPUT, f"cannot write {output}: {exc}")
    data = model.to_json()
    data["file"] = str(output)
    if json_out:
        out.print_json(json.dumps(data))
        return
    out.print(f"pickoff-ratio model written to {output}")
    for k in ("anchor_hz", "linear_per_hz", "quadratic_per_hz2", "lagged_per_hz", "lag_tau_s", "residual_rms_ppm"):
        out.print(f"  {k} = {data[k]:.6g}")
    out.print(f"  from {model.n_pairs} step pairs of {run_file}")


def render_calibrated(c: object) -> Table:
    """The calibrated SF beside the CLSF-only one (a CalibratedSF)."""
    from qmg_lab.analysis.calibrated_sf import CalibratedSF

    assert isinstance(c, CalibratedSF)

    def f(v: float | None) -> str:
        return "-" if v is None or not math.isfinite(v) else f"{v:.1f}"

    tab = Table(title="whole-SF calibration (CLSF + drive-frequency pickoff model)", show_header=True)
    for col in ("quantity", "CLSF only", "calibrated", "unit"):
        tab.add_column(col, justify="left" if col == "quantity" else "right")
    tab.add_row("accuracy RMS vs table steps", f(c.clsf_accuracy_vs_table_ppm), f(c.accuracy_vs_table_ppm), "ppm")
    tab.add_row("accuracy RMS vs /truth (twin)", f(c.clsf_vs_truth_ppm), f(c.vs_truth_ppm), "ppm")
    adev = (f(c.clsf_adev_2000s_error_ppm), f(c.adev_2000s_error_ppm))
    tab.add_row("ADEV at 2000 s of the error vs /truth", *adev, "ppm")
    return tab


def register(app: typer.Typer) -> None:
    """Add `qmg-lab characterize sf-model` to the characterize group (common.characterize_app, already on `app`)."""
    characterize_app.command("sf-model")(characterize_sf_model)
