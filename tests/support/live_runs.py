"""Run files for the data API and watch page tests: a RunWriter left open (a running file) fed block by block,
and a twin campaign interrupted at 30 s of run time and resumed (as `qmg-lab run --resume` does)."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np

from qmg_lab.campaign.pipeline import new_run_file
from qmg_lab.campaign.plan import checked_plan
from qmg_lab.config.schema import parse_config
from qmg_lab.storage.writer import RunWriter
from tests.support.campaigns import Outcome, config_text, run_inprocess


def live_writer(path: Path, name: str, planned_kinds: list[str]) -> RunWriter:
    """A new run file of a bench configuration (no /truth) made as every run file is made
    (qmg_lab.campaign.pipeline.new_run_file), with the plan `planned_kinds`; the caller keeps its writer open."""
    text = f'[campaign]\nname = "{name}"\n'
    cfg = parse_config(text)
    w = new_run_file(path, cfg, text, checked_plan(cfg), t0_unix=1.7e9, software_version="test")
    w.set_plan(len(planned_kinds), planned_kinds)
    return w


def append_block(w: RunWriter, k: int, kind: str) -> None:
    """Step k, 10 s from 10 k: CLSF periods at 7 Hz ending at 10 k + j/7 (j = 1..70) with estimate 1e-6 t,
    chamber 25 + 0.1 t degC and table at rest every 0.5 s from 10 k; the step row; a flush."""
    tc = np.arange(k * 70, (k + 1) * 70) / 7.0 + 1 / 7.0
    z = 0 * tc
    w.append("clsf", time=tc, eta=z, sf_change_estimate=1e-6 * tc, gain_correction=1 + z, rate_output_mean=z)
    tt = np.arange(k * 10.0, (k + 1) * 10.0, 0.5)
    w.append("chamber", time=tt, setpoint=30 + 0 * tt, temperature=25 + 0.1 * tt)
    w.append("table", time=tt, rate_command=0 * tt, rate_measured=0 * tt, position=0 * tt)
    w.append_step(
        index=k,
        kind=kind,
        t_start=10.0 * k,
        t_end=10.0 * (k + 1),
        table_rate=0.0,
        chamber_setpoint=30.0,
        status="completed",
    )
    w.flush()


def interrupted_then_resumed(tmp_path: Path, between: Callable[[Path], None] | None = None) -> Outcome:
    """The short twin campaign stopped by Ctrl-C at 30 s of run time (`between` gets the aborted file), then
    resumed to its end."""
    text = config_text()

    def stop_at_30_s(p) -> None:  # type: ignore[no-untyped-def]
        if p.run_time_s >= 30.0:
            raise KeyboardInterrupt

    first = run_inprocess(tmp_path, text, progress=stop_at_30_s)
    assert first.error is not None
    if between is not None:
        between(first.path)
    second = run_inprocess(tmp_path, text, resume=True)
    assert second.error is None
    return second
