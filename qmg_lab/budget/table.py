"""The noise budget as a terminal table (`qmg-lab budget`), readable from 80 columns up.

Each source's name wraps onto a second line rather than being cut to "…"; the column of configured values is
shown only where it fits beside the Allan deviations (100 columns or more), and the list printed under the
table gives every value with its origin anyway.
"""

from __future__ import annotations

from rich import box
from rich.table import Table

from qmg_lab.budget.noise import NoiseBudget

BUDGET_TABLE_TAUS = (1.0, 10.0, 60.0, 600.0, 2000.0)  # s: the Allan-deviation columns
VALUE_COLUMN_MIN_WIDTH = 100  # console columns from which the configured values fit in the table
SOURCE_MIN_WIDTH = 14  # "forcer-path" and "quantisation", the longest words of the source names, fit whole


def budget_table(result: NoiseBudget, width: int) -> Table:
    """The budget's sources and total against tau, for a console `width` columns wide."""
    with_values = width >= VALUE_COLUMN_MIN_WIDTH
    table = Table(
        title=f"CLSF noise budget ({result.mode} mode): Allan deviation of the estimate, ppm",
        box=box.SIMPLE_HEAD if not with_values else box.HEAVY_HEAD,
    )
    table.add_column("source", justify="left", min_width=SOURCE_MIN_WIDTH, ratio=1, overflow="fold")
    if with_values:
        table.add_column("value", justify="right", no_wrap=True)
    for col in ("ppm*rt(s)", *(f"{t:g} s" for t in BUDGET_TABLE_TAUS)):
        table.add_column(col, justify="right", no_wrap=True)
    blank = [""] if with_values else []
    for s in result.sources:
        value = [f"{s.value:.3g} {s.unit}"] if with_values else []
        table.add_row(s.name, *value, f"{s.white_ppm_rt_s:.3g}", *(f"{s.adev_ppm[t]:.3g}" for t in BUDGET_TABLE_TAUS))
    table.add_row(
        "total (estimate)", *blank, "", *(f"{result.adev_ppm[t]:.3g}" for t in BUDGET_TABLE_TAUS), style="bold"
    )
    if result.mode == "correct":
        table.add_row("self-calibrated SF", *blank, "", *(f"{result.sf_adev_ppm[t]:.3g}" for t in BUDGET_TABLE_TAUS))
    return table
