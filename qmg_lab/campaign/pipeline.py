"""The one path of a campaign into a run file: plan, a new run file, the runner, the file's close.

    plan = checked_plan(cfg)                      every command against the instruments' limits, before anything
    station                                       connected by the caller (qmg_lab.station.build_station)
    writer = new_run_file(path, cfg, text, plan)  the file at the configured storage level, its root attributes
    CampaignRunner(cfg, station, writer).run()    the steps and blocks, ending in the safe state
    writer.close()

`qmg-lab run` (qmg_lab/cli/main.py: with the checks, the lock, the stop signals and the progress view around it,
and `--resume`'s reopen), a study point (qmg_lab/study/task.py) and the benchmarks take this path; the root
attributes of a new file (the configuration's fingerprint, the mode, the software version, t0, each instrument's
twin/hardware mode) are decided here and nowhere else.
"""

from __future__ import annotations

from collections.abc import Callable
from datetime import UTC, datetime
from pathlib import Path

from qmg_lab import __version__
from qmg_lab.campaign.plan import CheckedPlan, checked_plan
from qmg_lab.campaign.runner import CampaignRunner, Progress, RunSummary
from qmg_lab.campaign.study_level import create_run_writer
from qmg_lab.config.schema import Config, config_fingerprint
from qmg_lab.instruments import Station
from qmg_lab.storage.layout import RUN_CONTEXT_ATTRS
from qmg_lab.storage.writer import RunWriter


def new_run_file(
    path: Path,
    cfg: Config,
    config_text: str,
    plan: CheckedPlan,
    *,
    t0_unix: float | None = None,
    software_version: str = __version__,
    note: str = "",
) -> RunWriter:
    """A new run file for `plan` at the configuration's storage level; t0_unix: now unless given; note: the run's
    own note (`run --note`), stored with the configuration's operator, device serial and notes."""
    who = cfg.campaign
    context = dict(zip(RUN_CONTEXT_ATTRS, (who.operator, who.device_serial, who.notes, note), strict=True))
    return create_run_writer(
        path,
        cfg,
        plan.steps,
        config_text=config_text,
        config_sha256=config_fingerprint(config_text),
        mode="sim" if cfg.all_sim else "hardware",
        software_version=software_version,
        t0_unix=datetime.now(UTC).timestamp() if t0_unix is None else t0_unix,
        instrument_modes=cfg.instrument_modes(),
        extra_attrs=context,
    )


def run_campaign(
    cfg: Config,
    config_text: str,
    station: Station,
    path: Path,
    *,
    plan: CheckedPlan | None = None,
    progress: Callable[[Progress], None] | None = None,
    note: str = "",
) -> RunSummary:
    """Run the configuration's campaign on `station` into a new run file at `path`; the file is closed on every
    way out (the station is the caller's to close). Raises what CampaignRunner.run raises."""
    plan = checked_plan(cfg) if plan is None else plan
    writer = new_run_file(path, cfg, config_text, plan, note=note)
    try:
        return CampaignRunner(cfg, station, writer, plan=plan, progress=progress).run()
    finally:
        writer.close()
