"""The one way a run file is made, continued, guarded and closed: `run_campaign`.

    run_campaign(cfg, config_text, path, resume=..., station=..., hooks=...) -> RunEnd
      1. checks that need no instrument, before anything changes: the plan against the instruments' limits; the
         run file's one-writer lock (qmg_lab/storage/lock.py), held from here to the file's last close; for a new
         file its folder writable and no file there (unless overwrite); for --resume the file writable and
         resumable (not completed, same configuration, writer gone, same twin/hardware instruments); the space the
         run needs on the file's disk (qmg_lab/storage/space.py)
      2. the stop signals deferred to the campaign's block boundaries (InterruptGuard), to the file's last close
      3. the station: the caller's, or connected here from the configuration once the checks passed
      4. the file: `new_run_file` (its root attributes are decided here and nowhere else) or RunWriter.reopen
      5. CampaignRunner(...).run(): the steps, the space check after every step, the safe state on every way out
      6. the file's close, then the closed file read back: success (exit code 0) only if it says "completed" and
         holds every planned step

`qmg-lab run` and `--resume` (qmg_lab/cli/main.py), a study point (qmg_lab/study/task.py), the test helpers
(tests/support/campaigns.py) and the benchmarks take this path. What the caller adds plugs in as `RunHooks`: the
progress view (called after every block, entered around the steps), a callback once the file is open; the outcome
is a `RunEnd` whose `exit_code` and `message` the CLI prints as they are (0 done, 2 bad input, 3 fault or data not
recorded, 128 + n stopped by signal n).
"""

from __future__ import annotations

import contextlib
import logging
import os
from collections.abc import Callable
from contextlib import AbstractContextManager, ExitStack
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from qmg_lab import __version__
from qmg_lab.campaign.errors import CampaignAborted, CampaignInterrupted
from qmg_lab.campaign.interrupts import InterruptGuard, exit_code
from qmg_lab.campaign.plan import CheckedPlan, checked_plan, plan_duration_s
from qmg_lab.campaign.runner import CampaignRunner, Progress, RunSummary, run_space_need
from qmg_lab.campaign.study_level import study_reductions
from qmg_lab.config.schema import Config, ConfigError, config_fingerprint
from qmg_lab.instruments import InstrumentError, LimitError, Station
from qmg_lab.storage.layout import RUN_CONTEXT_ATTRS, DamagedFileError, StorageError
from qmg_lab.storage.lock import RunFileLock
from qmg_lab.storage.resume import SALVAGE, ends_short, heal_interrupted_open
from qmg_lab.storage.runfile import start_structure_worker
from qmg_lab.storage.space import WORDS_PATTERN, SpaceNeed
from qmg_lab.storage.study_level import create_study_writer, refuse_study_resume
from qmg_lab.storage.superblock import read_superblock
from qmg_lab.storage.writer import RunFileWriteError, RunWriter, read_run

log = logging.getLogger(__name__)

EXIT_DONE, EXIT_BAD_INPUT, EXIT_FAULT = 0, 2, 3


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
    kwargs: dict[str, Any] = dict(
        config_text=config_text,
        config_sha256=config_fingerprint(config_text),
        mode="sim" if cfg.all_sim else "hardware",
        software_version=software_version,
        t0_unix=datetime.now(UTC).timestamp() if t0_unix is None else t0_unix,
        flush_interval_s=cfg.storage.flush_interval_s,
        compression=cfg.storage.resolved_compression(cfg.lockin.sim),
        instrument_modes=cfg.instrument_modes(),
        realtime=not cfg.lockin.sim,
        extra_attrs=context,
    )
    if cfg.storage.level == "full":  # `[storage] level`: the raw streams, or the study level's reductions
        return RunWriter.create(path, truth=cfg.lockin.sim, **kwargs)
    return create_study_writer(path, study_reductions(cfg, plan.steps), **kwargs)


@dataclass
class RunHooks:
    """What a caller plugs into a run: `progress` after every lock-in block; `view` entered around the steps (the
    CLI's live panel); `file_open` once the run file is made or reopened, before the first step."""

    progress: Callable[[Progress], None] | None = None
    view: AbstractContextManager[Any] | None = None
    file_open: Callable[[RunWriter], None] | None = None


@dataclass
class RunEnd:
    """How a run ended. exit_code: 0 only if the closed file says "completed" and holds every planned step; 2 bad
    input (nothing was changed); 3 an instrument fault, an abort, or data that could not be written (the file is
    left resumable); 128 + n stopped by signal n. message: the last words for the operator ("" on success)."""

    exit_code: int
    message: str
    path: Path
    summary: RunSummary | None = None
    error: BaseException | None = None
    safe_state_note: str = ""
    notes: list[str] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return self.exit_code == EXIT_DONE


class RunRefused(Exception):
    """A check before anything changed failed: bad input, exit 2."""


def safe_state_words(note: str) -> str:
    """The words about the safe state, from the text of the file's safe_state event ("confirmed" or "not
    confirmed: <what failed>"), word for word, so the terminal never contradicts the file; before the safe state
    was commanded (note ""): the station's own close commands it, without a file event."""
    if note == "confirmed":
        return "instruments in their safe state (safe_state: confirmed)"
    if note:
        return f"safe_state: {note}; go and check the instruments"
    return "safe state commanded when the station closed"


def run_campaign(
    cfg: Config,
    config_text: str,
    path: Path,
    *,
    resume: bool = False,
    overwrite: bool = False,
    station: Station | None = None,
    plan: CheckedPlan | None = None,
    hooks: RunHooks | None = None,
    t0_unix: float | None = None,
    software_version: str = __version__,
    realtime: bool = False,
    note: str = "",
) -> RunEnd:
    """Run the configuration's campaign into a new run file at `path`, or continue it (`resume`). The module
    docstring's protocol. station: the caller's, already connected (it stays the caller's to close); None: the
    station is built from the configuration after the checks and closed here, its lock-in twin paced to the wall
    clock if `realtime` (`run --sim --realtime`, qmg_lab.station.RealTimePacing). note: `run --note`, stored in a
    new file's root attributes."""
    hooks = hooks or RunHooks()
    with ExitStack() as stack:
        try:
            plan = checked_plan(cfg) if plan is None else plan
            if resume and not path.is_file():
                raise RunRefused(f"{path}: no such run file to resume")
            if path.is_dir():
                raise RunRefused(f"{path} is a folder: -o takes the run file's name, e.g. -o {path / 'run.h5'}")
            stack.enter_context(_locked(path))
            if resume:
                done = _check_resumable(cfg, config_text, path)
            else:
                done = set()
                _check_new_file(path, overwrite)
            _check_space(cfg, plan, path, done, resume)
        except DamagedFileError as exc:  # a file --resume cannot continue: the way out is named
            words = str(exc) if "salvage" in str(exc) else f"{exc}; nothing was changed: {SALVAGE.format(path=path)}"
            return RunEnd(EXIT_BAD_INPUT, words, path, error=exc)
        except (RunRefused, StorageError, LimitError) as exc:
            return RunEnd(EXIT_BAD_INPUT, str(exc), path, error=exc)
        start_structure_worker()  # the read-back's walk of the closed file (_read_back) finds its worker started
        guard = stack.enter_context(InterruptGuard())
        # from here to the file's last close a stop signal is kept for the campaign, which stops at its first block
        if station is None:
            try:
                station = stack.enter_context(_connected(cfg, realtime))
            except ConfigError as exc:  # a configuration the physics refuses (the station's pull-in check)
                return RunEnd(EXIT_BAD_INPUT, str(exc), path, error=exc)
            except (InstrumentError, OSError) as exc:
                return RunEnd(EXIT_FAULT, f"could not connect the station: {exc}", path, error=exc)
        try:
            writer = _open_file(cfg, config_text, path, plan, resume, t0_unix, software_version, note)
        except (StorageError, OSError) as exc:
            return RunEnd(EXIT_BAD_INPUT, _file_words(path, exc), path, error=exc)
        return _run(cfg, station, writer, plan, resume, hooks, guard)
    raise AssertionError("unreachable")  # pragma: no cover - ExitStack does not swallow exceptions


# ================================================================================ checks before the instruments
@contextlib.contextmanager
def _locked(path: Path) -> Any:
    """The run file's one-writer lock (its folder made first); RunRefused if another process writes the file."""
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise RunRefused(f"cannot write the run file: {exc}") from None
    with RunFileLock(path):
        yield


def _check_new_file(path: Path, overwrite: bool) -> None:
    if path.exists() and not (overwrite and path.is_file()):
        raise RunRefused(f"{path} exists: choose another -o, or continue it with --resume {path}")
    if not os.access(path.parent, os.W_OK):
        raise RunRefused(f"cannot write the run file: its folder {path.parent} is not writable")
    if path.exists() and not os.access(path, os.W_OK):
        raise RunRefused(f"{path} is read-only: --overwrite cannot replace it; choose another -o")


def _check_resumable(cfg: Config, config_text: str, path: Path) -> set[int]:
    """--resume's read-only checks (after healing a resume killed before its SWMR start); the completed steps."""
    if not os.access(path, os.W_OK):
        raise RunRefused(f"{path} is read-only: make it writable (chmod u+w) to continue it, then --resume again")
    heal_interrupted_open(path)
    # a file cut short is checked first, on a padded copy opened without SWMR: a SWMR open of it could retry for
    # minutes
    short = ends_short(path)
    if not short:
        refuse_study_resume(path)
    run = RunWriter.check_resumable(
        path, config_sha256=config_fingerprint(config_text), instrument_modes=cfg.instrument_modes()
    )
    if short:
        refuse_study_resume(path)
    return {int(i) for i, s in zip(run.steps["index"], run.steps["status"], strict=True) if s == "completed"}


def _check_space(cfg: Config, plan: CheckedPlan, path: Path, done: set[int], resume: bool) -> None:
    """The space the rest of the plan needs on the file's disk: refused before anything starts if it is not free."""
    if resume:
        need = resume_space_need(cfg, plan, path, done)
    else:
        left_s = plan_duration_s([s for s in plan.steps if s.index not in done])
        need = run_space_need(cfg, path, run_time_s=0.0, left_s=left_s)
    if not need.enough:
        raise RunRefused(
            f"not enough space for the run file {path}: {need.words()}. Free the space or write to another disk "
            "(-o), then start again"
        )


def resume_space_need(cfg: Config, plan: CheckedPlan, path: Path, done: set[int] | None = None) -> SpaceNeed:
    """The space `--resume` of the file at `path` needs, as its own check computes it (`_check_space`): the
    steps the file does not hold as completed (`done`; None: read from the file, every step if it does not read)
    at the bytes per second the file shows over the run time it holds (qmg_lab/storage/space.py). A file a full
    disk left shorter than its superblock's end of file (`ends_short`) needs that end's bytes more: the resume
    checks it on a copy padded to that end (the whole file once more, while the check runs) and then pads the
    file itself. The figure a run that ran out of space asks for is this one, computed once its file is closed,
    so freeing it is enough for the resume's check."""
    if done is None:
        try:
            steps = read_run(path, select=()).steps
            done = {int(i) for i, st in zip(steps["index"], steps["status"], strict=True) if st == "completed"}
        except StorageError:
            done = set()
    left_s = plan_duration_s([s for s in plan.steps if s.index not in done])
    need = run_space_need(cfg, path, run_time_s=_file_run_time(path), left_s=left_s)
    try:
        short = ends_short(path)
        eof = read_superblock(path).eof_address if short else None
    except (StorageError, OSError):
        short, eof = False, None
    if short and eof is not None:
        size = path.stat().st_size
        needed = max(need.needed + (eof - size), eof)
        need = SpaceNeed(needed, need.free, need.bytes_per_s, need.left_s, need.measured)
    return need


def _file_run_time(path: Path) -> float:
    """The run time a run file holds: its last /lockin time, s (0 if it cannot be read)."""
    try:
        t = read_run(path, select=("lockin/time",)).groups.get("lockin", {}).get("time")
    except StorageError:
        return 0.0
    return float(t[-1]) if t is not None and len(t) else 0.0


@contextlib.contextmanager
def _connected(cfg: Config, realtime: bool = False) -> Any:
    """The station built from the configuration (its lock-in twin paced to the wall clock if `realtime`); on the way
    out every instrument is made safe and closed."""
    from qmg_lab.station import RealTimePacing, build_station  # the composition root, imported when a run connects

    station = build_station(cfg, pacing=RealTimePacing() if realtime else None)
    try:
        yield station
    finally:
        station.close()


# ================================================================================ the file and the run
def _open_file(
    cfg: Config,
    config_text: str,
    path: Path,
    plan: CheckedPlan,
    resume: bool,
    t0_unix: float | None,
    software_version: str,
    note: str,
) -> RunWriter:
    if resume:
        return RunWriter.reopen(
            path,
            config_sha256=config_fingerprint(config_text),
            flush_interval_s=cfg.storage.flush_interval_s,
            instrument_modes=cfg.instrument_modes(),
        )
    if path.exists():
        path.unlink()  # --overwrite, now that the checks passed and the station answered
    return new_run_file(path, cfg, config_text, plan, t0_unix=t0_unix, software_version=software_version, note=note)


def _file_words(path: Path, exc: BaseException) -> str:
    text = str(exc)
    return text if isinstance(exc, StorageError) else f"cannot write the run file {path}: {text}"


def _run(
    cfg: Config,
    station: Station,
    writer: RunWriter,
    plan: CheckedPlan,
    resume: bool,
    hooks: RunHooks,
    guard: InterruptGuard,
) -> RunEnd:
    """Steps 5 and 6 of the module docstring: the campaign, the file's close, the file read back."""
    path = writer.path
    runner: CampaignRunner | None = None
    end: RunEnd
    try:
        if hooks.file_open is not None:
            hooks.file_open(writer)
        runner = CampaignRunner(cfg, station, writer, progress=hooks.progress, resume=resume, plan=plan, guard=guard)
        with hooks.view if hooks.view is not None else contextlib.nullcontext():
            summary = runner.run()
        end = RunEnd(EXIT_DONE, "", path, summary=summary, safe_state_note=runner.safe_state_note)
    except CampaignInterrupted as exc:
        note = runner.safe_state_note if runner else ""
        end = RunEnd(
            exit_code(exc.signum),
            f"{exc}; {safe_state_words(note)}; file {path} (status aborted; continue with --resume {path})",
            path,
            summary=runner.summary("aborted", str(exc)) if runner else None,
            error=exc,
            safe_state_note=note,
        )
    except (CampaignAborted, InstrumentError) as exc:
        note = runner.safe_state_note if runner else ""
        resumable = f"; continue with --resume {path}" if "--resume" not in str(exc) else ""
        end = RunEnd(
            EXIT_FAULT,
            f"{exc}; {safe_state_words(note)}; file {path} (status aborted{resumable})",
            path,
            summary=runner.summary("aborted", str(exc)) if runner else None,
            error=exc,
            safe_state_note=note,
        )
    except LimitError as exc:
        end = RunEnd(EXIT_BAD_INPUT, str(exc), path, error=exc)
    finally:
        with guard.protect():  # a second stop signal waits for the file's last write
            closed = _close(writer)
    if closed is not None:  # the last flush or close failed: what the run did is not all in the file
        return _not_recorded(end, closed, path, cfg, plan)
    if end.ok:
        return _read_back(end, plan, path)
    return end


def _close(writer: RunWriter) -> BaseException | None:
    """Close the file; the failure of its last flush or close (a full disk), or None."""
    try:
        writer.close()
    except (StorageError, OSError, RuntimeError) as exc:
        log.error("the run file's last write failed: %s", exc)
        return exc
    return writer.write_error


def _not_recorded(end: RunEnd, exc: BaseException, path: Path, cfg: Config, plan: CheckedPlan) -> RunEnd:
    """A failed write turns any ending into exit 3 (a signal's exit code stays): the file keeps its last
    successful flush and resumes from there. Out of space: the figure to free is what the resume's check of the
    closed file asks (`resume_space_need`), not what the run had left when it failed (checkpoints written after
    the last successful flush did not reach the disk, and the resume reruns their steps)."""
    space, before = "", end.message
    if isinstance(exc, RunFileWriteError) and exc.out_of_space:
        need = resume_space_need(cfg, plan, path).words()
        space = f" (out of space: {need}; free that much, then resume)"
        # a figure the run named before this write failed (its space check) counted steps whose rows were lost
        before = WORDS_PATTERN.sub(need, before)
    words = f"the run file's last write failed{space}: {exc}; file {path} (continue with --resume {path})"
    code = end.exit_code if end.exit_code not in (EXIT_DONE, EXIT_BAD_INPUT) else EXIT_FAULT
    message = f"{before}; {words}" if before else words
    return RunEnd(code, message, path, summary=end.summary, error=exc, safe_state_note=end.safe_state_note)


def _read_back(end: RunEnd, plan: CheckedPlan, path: Path) -> RunEnd:
    """Success is what the closed file says: status "completed" and every planned step "completed"."""
    try:
        run = read_run(path, select=())
    except StorageError as exc:
        return RunEnd(EXIT_FAULT, f"the closed run file cannot be read back: {exc}", path, summary=end.summary)
    done = {int(i) for i, s in zip(run.steps["index"], run.steps["status"], strict=True) if s == "completed"}
    missing = sorted({s.index for s in plan.steps} - done)
    if run.status != "completed" or missing:
        return RunEnd(
            EXIT_FAULT,
            f"the run file {path} does not hold the whole run (status {run.status!r}, steps not recorded: "
            f"{missing[:10]}{' ...' if len(missing) > 10 else ''}); continue with --resume {path}",
            path,
            summary=end.summary,
            safe_state_note=end.safe_state_note,
        )
    return end
