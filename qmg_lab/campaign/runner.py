"""The campaign sequencer: plan -> steps -> checkpoints, with suspenders, safe state and resume.

The lock-in stream is the heartbeat: the runner never sleeps, it polls the lock-in for the next block of
demodulator samples (on hardware the poll waits for real time; on the twin it advances the simulated world by
that block) and, between blocks, reads the table and the chamber, feeds the CLSF estimator, writes the file and
checks the suspenders. A step's clock only runs while no suspender holds: while the PLL is unlocked, the chamber
is out of its band or an instrument is being recovered, the campaign keeps logging but the step waits.

Every exit path ends in the safe state (table stopped, chamber to its safe setpoint, dither muted, lock-in outputs
safe) and with the file's status set: "completed", or "aborted" with the reason.

Fault handling is the recovery policy's (qmg_lab/campaign/recovery.py, docs/reliability.md): bounded
reconnect-and-retry, suspension while an instrument is recovered, abort with the reason; the retried safe state on
the way out.

Why one module of this length: the runner's state (the run clock, the step clock, the suspenders, the resume
offset) is shared by every step and block; recovery (recovery.py), recording (recorder.py) and the plan
(plan.py) are already elsewhere, and what stays is the sequencing itself.
"""

from __future__ import annotations

import contextlib
import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TypeVar

import numpy as np

from qmg_lab.campaign.errors import CampaignAborted, CampaignInterrupted
from qmg_lab.campaign.interrupts import InterruptGuard
from qmg_lab.campaign.loops import forcer_path_problem, lockin_setup
from qmg_lab.campaign.plan import CheckedPlan, Step, StepKind, checked_plan, plan_duration_s
from qmg_lab.campaign.recorder import BlockRecorder
from qmg_lab.campaign.recovery import RecoveryPolicy
from qmg_lab.campaign.snapshots import station_snapshots
from qmg_lab.clsf.demod_filter import DemodFilter
from qmg_lab.clsf.dither_edges import edge_threshold_v
from qmg_lab.clsf.estimator import ClsfEstimator
from qmg_lab.clsf.moving_mean import SF_MEAN_WINDOW_S, MovingMean
from qmg_lab.config.schema import Config, dither_amplitude_vpp
from qmg_lab.instruments import (
    InstrumentError,
    Station,
)
from qmg_lab.storage.space import SpaceNeed, measured_bytes_per_s, raw_bytes_per_s, space_need
from qmg_lab.storage.writer import RunFileWriteError, RunWriter

T = TypeVar("T")

__all__ = [
    "CampaignAborted",  # re-exported: the runner's callers catch them from here
    "CampaignInterrupted",
    "CampaignRunner",
    "Progress",
    "RunSummary",
    "run_space_need",
]

log = logging.getLogger(__name__)


@dataclass
class Progress:
    """What the CLI shows while a campaign runs."""

    step: Step
    n_steps: int
    step_elapsed_s: float
    run_time_s: float
    planned_s: float
    done_s: float
    chamber_c: float
    chamber_setpoint_c: float
    table_rate_dps: float
    sf_change_ppm: float
    gain_correction: float
    suspended: str
    wall_s: float


@dataclass
class RunSummary:
    path: str
    status: str
    steps_completed: int
    steps_planned: int
    simulated_s: float
    wall_s: float
    blocks: int
    samples: int
    samples_lost: int
    suspensions: int
    recoveries: int
    sf_change_mean_ppm: float  # the CLSF SF-change estimate over the last SF_MEAN_WINDOW_S of run time, ppm
    gain_correction: float
    abort_reason: str = ""
    resumed: bool = False
    reconnects: int = 0
    safe_state_confirmed: bool = True
    faults_injected: list[dict[str, object]] = field(default_factory=list)

    def as_dict(self) -> dict[str, object]:
        return dict(self.__dict__)


@dataclass
class _Readings:
    table_cmd: float = 0.0
    table_rate: float = float("nan")
    chamber_c: float = float("nan")
    chamber_sp: float = float("nan")
    sf_change: float = float("nan")


@dataclass
class CampaignRunner:
    """Runs a configuration's plan on a station, writing the run file."""

    cfg: Config
    station: Station
    writer: RunWriter
    progress: Callable[[Progress], None] | None = None
    resume: bool = False
    plan: CheckedPlan | None = None  # None: made (and checked) here from cfg
    guard: InterruptGuard | None = None  # the caller's, already installed (the CLI's); None: run() installs one

    def __post_init__(self) -> None:
        self.steps: list[Step] = list((self.plan or checked_plan(self.cfg)).steps)
        self._planned_s = plan_duration_s(self.steps)  # the progress line's total, summed once
        self.clsf = ClsfEstimator(
            tau_s=self.cfg.device.tau_s,
            mode=self.cfg.clsf.mode,
            time_constant_s=self.cfg.clsf.time_constant_s,
            reference_periods=self.cfg.clsf.reference_periods,
            dither_min_step_v=edge_threshold_v(dither_amplitude_vpp(self.cfg)),
        )
        self._forcer_checked = False  # the CLSF reference checked against the configured plant (forcer_path_problem)
        self._offset = 0.0
        self._t = 0.0  # file time of the last sample, s
        self._dt = 1.0 / self.cfg.lockin.demod_rate_hz
        self._read = _Readings()
        self._sf_mean = MovingMean(SF_MEAN_WINDOW_S)  # the summary's SF change, over the periods
        self._wall0 = time.monotonic()
        self._blocks = self._samples = self._lost = self._suspensions = 0
        self._suspended = ""
        self._done_s = 0.0
        self._guard: InterruptGuard | None = None
        self._recovery = RecoveryPolicy(
            self.cfg.recovery,
            self.station.instruments(),
            poll_interval_s=self.station.poll_interval_s,
            poll_block=lambda: self._block(self._step, self._step_elapsed, self.station.poll_interval_s),
            run_time_s=lambda: self._t,
            event=self._event,
        )
        self._safe_confirmed = True
        self._status_error: RunFileWriteError | None = None  # the final status/flush could not be written
        #: the safe_state event's message, word for word ("confirmed" or "not confirmed: ..."): what the CLI's last
        #: words about the safe state say, so the terminal never contradicts the file
        self.safe_state_note = ""
        self._interrupted = False  # stopped by a stop signal (event "interrupted", not "abort")
        self._step = Step(-1, StepKind.LOCK, 0.0, self.cfg.plan.chamber_start_c, self.cfg.plan.chamber_ramp_c_per_min)
        self._step_elapsed = 0.0
        self._records = self.writer.records()
        self._recorder = BlockRecorder(self.writer)
        self._last_locked = True  # the PLL's lock in the last block
        self._offset_target: float | None = None  # file time the next stream (re)start continues from
        self._last_stream_t: float | None = None  # the lock-in stream's time of the last sample
        self._log_t = 0.0  # the run log's clock: the block being processed

    # ================================================================== run log
    def _now(self) -> float:
        """Run time for the log: the last sample's time (before the first block of a resumed run, where the
        file ends)."""
        if self._blocks:
            return max(self._t, self._log_t)
        return self._offset_target if self._offset_target is not None else 0.0

    def _event(self, kind: str, instrument: str, message: str, level: int = logging.WARNING) -> None:
        """One entry of the run's log: the module logger and the run file's /events (qmg_lab/storage/records.py)."""
        log.log(level, "t=%.3f s %s %s: %s", self._now(), kind, instrument or "campaign", message)
        try:
            self._records.event(self._now(), kind, instrument, message)
        except Exception as exc:
            log.error("could not write the event to the run file: %s", exc)

    def _snapshots(self) -> None:
        """Each instrument's identity, firmware, settings and state into /snapshots (start and every resume)."""
        occasion = "resume" if self.resume else "start"
        for name, doc in station_snapshots(self.cfg, self.station).items():
            try:
                self._records.snapshot(self._now(), name, occasion, doc)
            except Exception as exc:
                log.error("could not write the %s snapshot: %s", name, exc)

    # ================================================================== public
    def run(self) -> RunSummary:
        """Execute every step not yet completed; always leave the station safe and the file's status set."""
        status, reason = "aborted", ""
        with contextlib.nullcontext(self.guard) if self.guard is not None else InterruptGuard() as guard:
            self._guard = guard
            try:
                self._prepare()
                done = self.writer.completed_steps()
                for step in self.steps:
                    if step.index in done:
                        self._done_s += step.duration_s
                        continue
                    self._run_step(step)
                status = "completed"
            except KeyboardInterrupt:
                self._interrupted = True
                reason = guard.reason()
                raise CampaignInterrupted(reason, guard.exit_code() - 128) from None
            except CampaignInterrupted as exc:
                self._interrupted = True
                reason = str(exc)
                raise
            except InstrumentError as exc:
                reason = f"instrument fault: {exc}"
                raise CampaignAborted(reason) from exc
            except CampaignAborted as exc:
                reason = str(exc)
                raise
            except RunFileWriteError as exc:  # a full disk: abort to the safe state, say how much space it needs
                reason = self._write_failure_reason(exc)
                raise CampaignAborted(reason) from exc
            except Exception as exc:
                reason = f"internal error: {type(exc).__name__}: {exc}"
                raise
            finally:
                failures = self._finish_protected(status, reason)
                if failures and status == "completed":
                    raise CampaignAborted("safe state not confirmed: " + "; ".join(failures))
                if self._status_error is not None and status == "completed":  # the data are not all in the file
                    raise CampaignAborted(self._write_failure_reason(self._status_error)) from self._status_error
        return self.summary(status, reason)

    def summary(self, status: str, reason: str = "") -> RunSummary:
        return RunSummary(
            path=str(self.writer.path),
            status=status,
            steps_completed=len(self.writer.completed_steps()),
            steps_planned=len(self.steps),
            simulated_s=self._t,
            wall_s=time.monotonic() - self._wall0,
            blocks=self._blocks,
            samples=self._samples,
            samples_lost=self._lost,
            suspensions=self._suspensions,
            recoveries=self._recovery.recoveries,
            sf_change_mean_ppm=self._sf_mean.mean * 1e6,
            gain_correction=self.clsf.gain_correction,
            abort_reason=reason,
            resumed=self.resume,
            reconnects=self._recovery.reconnects,
            safe_state_confirmed=self._safe_confirmed,
            faults_injected=list(self.station.injected_faults()) if self.station.injected_faults else [],
        )

    # ================================================================== set-up and tear-down
    def _prepare(self) -> None:
        self.writer.set_plan(len(self.steps), [s.label for s in self.steps])
        if self.resume:
            state = self.writer.resume_state()
            self._offset_target = state.last_time
            if state.rho_ref is not None:
                self.clsf.rho_ref = state.rho_ref
                self._forcer_checked = True  # by the run that formed it, at the forcer gain then in force
            if state.gain_correction is not None:
                self.clsf.gain_correction = state.gain_correction
            if self.station.restore is not None:
                self.station.restore(state.as_dict())
        setup = lockin_setup(self.cfg, forcer_gain=self.clsf.gain_correction)
        self._event("started", "", "resumed run" if self.resume else "new run", logging.INFO)
        self._recovery.call("lockin", lambda: self.station.lockin.configure(setup))
        timing = self._recovery.call("lockin", self.station.lockin.stream_timing)
        self.clsf.set_stream_timing(DemodFilter(timing.filter_order, timing.filter_tc_s), timing.auxin_window_s)
        self._dt = 1.0 / timing.rate_hz
        self._snapshots()
        self._recovery.call("lockin", self.station.lockin.start_stream)
        if self.resume:
            # the loops were re-closed in a new process: wait for lock again, then restart the dither
            self._step = Step(
                -1,
                StepKind.LOCK,
                self.cfg.loops.lock_settle_s,
                self.cfg.plan.chamber_start_c,
                self.cfg.plan.chamber_ramp_c_per_min,
            )
            self._wait_for_lock(self._step)
            if self.clsf.mode != "off" and self.clsf.rho_ref is not None:
                self._start_dither()

    def _finish_protected(self, status: str, reason: str) -> list[str]:
        """_finish with Ctrl-C deferred for its whole length: a second Ctrl-C cannot cut the safe state or the
        file's last writes; one that arrives meanwhile is dropped (the campaign is stopping anyway)."""
        self._recovery.finishing = True
        guard = self._guard
        if guard is None:
            return self._finish(status, reason)
        failures: list[str] = []
        try:
            with guard.protect():
                failures = self._finish(status, reason)
        except KeyboardInterrupt:
            pass
        return failures

    def _finish(self, status: str, reason: str) -> list[str]:
        failures = self._recovery.safe_state()
        try:
            self.station.lockin.stop_stream()
        except Exception as exc:
            failures.append(f"lockin stream: {exc}")
        self._safe_confirmed = not failures
        self.safe_state_note = "confirmed" if not failures else "not confirmed: " + "; ".join(failures)
        self._event(
            "safe_state",
            "",
            self.safe_state_note,
            logging.INFO if not failures else logging.ERROR,
        )
        if failures and not reason:
            reason = "safe state not confirmed: " + "; ".join(failures)
            status = "aborted"
        elif failures:
            reason = reason + " (safe state not confirmed: " + "; ".join(failures) + ")"
        if status == "completed":
            self._event("completed", "", "every step completed", logging.INFO)
        else:
            self._event("interrupted" if self._interrupted else "abort", "", reason, logging.ERROR)
        try:
            self.writer.set_status(status, reason)
            self.writer.flush()
        except RunFileWriteError as exc:  # the file cannot take its status (a full disk): it keeps its last flush
            log.error("could not write the run's status: %s", exc)
            self._status_error = exc
        return failures

    def _write_failure_reason(self, exc: RunFileWriteError) -> str:
        """The abort reason of a failed write. Out of space: what is full; the space to free is named once the
        file is closed (qmg_lab.campaign.pipeline.resume_space_need: what the resume's check will ask of it)."""
        if not exc.out_of_space:
            return f"the run file could not be written: {exc}"
        path = self.writer.path
        what = "the process's file size limit (ulimit -f) was reached" if exc.size_limit else "the disk is full"
        return f"the run file could not be written: {what} ({path}, {self._t:.0f} s of run time written)"

    def _space_need(self) -> SpaceNeed:
        return run_space_need(
            self.cfg, self.writer.path, run_time_s=self._t, left_s=max(self._planned_s - self._done_s, 0.0)
        )

    def _check_space(self) -> None:
        """After every step: stop at this checkpoint, in the safe state, if the rest of the plan does not fit on the
        file's disk (a full disk in the middle of a write is avoided, not only survived)."""
        need = self._space_need()
        if not need.enough:
            raise CampaignAborted(
                f"not enough space left for the rest of the run: {need.words()}. Free the space, then continue "
                f"with --resume {self.writer.path}"
            )

    # ================================================================== steps
    def _run_step(self, step: Step) -> None:
        t_start = self._t
        self._step, self._step_elapsed = step, 0.0
        if step.kind is StepKind.LOCK:
            self._wait_for_lock(step)
        else:
            self._apply(step)
            self._dwell(step)
        self.writer.append_step(
            index=step.index,
            kind=step.label,
            t_start=t_start,
            t_end=self._t,
            table_rate=step.table_rate_dps,
            chamber_setpoint=step.chamber_target_c,
            status="completed",
        )
        self._done_s += step.duration_s  # append_step flushed the file (in the twins' layout with the step's chunk)
        if len(self.writer.completed_steps()) < len(self.steps):
            self._check_space()

    def _apply(self, step: Step) -> None:
        """Commands at the start of a step (idempotent, so a resumed step can re-apply them)."""
        st, p = self.station, self.cfg.plan
        self._recovery.call(
            "chamber", lambda: st.chamber.set_setpoint(step.chamber_target_c, step.chamber_ramp_c_per_min)
        )
        if step.kind is StepKind.DITHER:
            self._start_dither()
        previous = self._read.table_cmd
        if step.kind in (StepKind.RATE, StepKind.LEVEL):
            self._recovery.call("table", lambda: st.table.set_rate(step.table_rate_dps, p.table_accel_dps2))
            self._read.table_cmd = step.table_rate_dps
        elif step.kind is StepKind.SINE:
            self._recovery.call(
                "table", lambda: st.table.set_sinusoid(step.table_rate_dps, step.sine_frequency_hz, p.table_accel_dps2)
            )
            self._read.table_cmd = 0.0
            self.clsf.hold(self._t, self._t + step.duration_s)
        elif step.kind in (StepKind.RETURN, StepKind.HOLD, StepKind.SOAK) and previous != 0.0:
            self._recovery.call("table", st.table.stop)
            self._read.table_cmd = 0.0
        if step.moves_table or previous != self._read.table_cmd:
            move_s = abs(self._read.table_cmd - previous) / p.table_accel_dps2
            self.clsf.hold(self._t, self._t + move_s + self.cfg.clsf.hold_s)

    def _start_dither(self) -> None:
        vpp = dither_amplitude_vpp(self.cfg)
        self._recovery.call(
            "generator", lambda: self.station.generator.set_square(self.cfg.dither.frequency_hz, vpp, 0.0)
        )

    def _dwell(self, step: Step) -> None:
        elapsed = 0.0
        while step.duration_s - elapsed > 0.5 * self._dt:
            # a block is a whole number of samples, so a step's last block may be a fraction of a sample short of
            # its end: never ask for less than the lock-in's shortest poll (1 ms) or two samples
            want = max(min(self.station.poll_interval_s, step.duration_s - elapsed), 2 * self._dt, 1e-3)
            block_s = self._block(step, elapsed, want)
            if not self._suspended:
                elapsed += block_s
            self._step_elapsed = elapsed

    def _wait_for_lock(self, step: Step) -> None:
        """Poll until the PLL is locked and the loops have stayed settled for lock_settle_s."""
        lp = self.cfg.loops
        locked_for, waited = 0.0, 0.0
        while locked_for < max(step.duration_s, self._dt):
            block_s = self._block(step, locked_for, min(self.station.poll_interval_s, lp.lock_timeout_s))
            waited += block_s
            locked_for = locked_for + block_s if self._last_locked else 0.0
            if waited > lp.lock_timeout_s + step.duration_s:
                raise CampaignAborted(
                    f"the PLL did not lock within loops.lock_timeout_s = {lp.lock_timeout_s:g} s "
                    "(check the drive wiring and loops.pll_bandwidth_hz)"
                )

    # ================================================================== one block
    def _block(self, step: Step, step_elapsed: float, want_s: float) -> float:
        """Poll one block, log it, run CLSF and the suspenders. Returns the block's duration (s)."""
        if self._guard is not None and self._guard.requested and not self._recovery.finishing:
            raise CampaignInterrupted(self._guard.reason(), self._guard.exit_code() - 128)
        block = self._recovery.call("lockin", lambda: self.station.lockin.poll(want_s))
        n = len(block)
        self._lost += block.samples_lost  # also an empty block's: samples the lock-in could not pair are lost
        if block.samples_lost:
            self.clsf.reset_buffer()
        if n == 0:
            return 0.0
        t = self._file_time(block.time)
        self._log_t = float(t[-1])  # the run log's clock: the block being processed
        self._blocks += 1
        self._samples += n
        self._last_locked = bool(block.pll_locked)
        periods = self.clsf.process(t, block.x_sense, block.rate_output, block.dither)
        if self.clsf.mode == "correct" and len(periods):
            self._recovery.call("lockin", lambda: self.station.lockin.set_forcer_gain(self.clsf.gain_correction))
        tab = self._recovery.read("table", self.station.table.read)
        cham = self._recovery.read("chamber", self.station.chamber.read)
        t_end = float(t[-1])
        truth = self.station.truth.drain() if self.station.truth is not None else None
        guard = self._guard
        with guard.protect() if guard is not None else contextlib.nullcontext():
            self._recorder.record(
                t, block, periods, tab, self._read.table_cmd, cham, truth, self._dt, clsf_reference=self.clsf.rho_ref
            )
        if not self._forcer_checked and self.clsf.rho_ref is not None:
            self._forcer_checked = True
            problem = forcer_path_problem(self.clsf.rho_ref, self.cfg.device, self.clsf.gain_correction)
            if problem is not None and not self._recovery.finishing:
                raise CampaignAborted(problem)
        if len(periods):
            self._read.sf_change = float(periods.sf_change_estimate[-1])
            for t_k, sf_k in zip(periods.time.tolist(), periods.sf_change_estimate.tolist(), strict=True):
                self._sf_mean.add(t_k, sf_k)
        self._t = t_end
        if tab is not None:
            self._read.table_rate = tab.rate_dps
        if cham is not None:
            self._read.chamber_c, self._read.chamber_sp = cham.temperature_c, cham.setpoint_c
        if tab is not None and tab.interlock and not self._recovery.finishing:
            raise CampaignAborted(
                f"rate-table interlock tripped (table status {tab.status}); the table braked "
                "to rest; reset the interlock at the controller before resuming"
            )
        self._update_suspenders(step, self._read.chamber_c if cham is not None else math.nan, self._read.chamber_sp)
        block_s = n * self._dt
        if self.progress is not None:
            self.progress(
                Progress(
                    step=step,
                    n_steps=len(self.steps),
                    step_elapsed_s=step_elapsed,
                    run_time_s=self._t,
                    planned_s=self._planned_s,
                    done_s=self._done_s + step_elapsed,
                    chamber_c=self._read.chamber_c,
                    chamber_setpoint_c=self._read.chamber_sp,
                    table_rate_dps=self._read.table_rate,
                    sf_change_ppm=self._read.sf_change * 1e6,
                    gain_correction=self.clsf.gain_correction,
                    suspended=self._suspended,
                    wall_s=time.monotonic() - self._wall0,
                )
            )
        self._recovery.recover_failed_reads()  # a reading failed even after reconnecting: recover it now
        return block_s

    def _file_time(self, stream_t: np.ndarray) -> np.ndarray:
        """File time of a block's samples: the lock-in stream's time plus an offset, so that the file's /lockin
        time runs on continuously. The offset is set when a stream (re)starts: at the first block (0 on a new
        run: the first sample is t = 0; on a resumed run the first sample follows the file's last one by one
        sample period) and whenever the stream's time goes back (the lock-in was reconnected and restarted its
        stream: the new stream follows the last logged sample by one period)."""
        first = float(stream_t[0])
        if self._last_stream_t is None or first <= self._last_stream_t:
            if self._last_stream_t is not None:
                self._offset_target = self._t
            dt = float(stream_t[1] - stream_t[0]) if len(stream_t) > 1 else self._dt
            self._offset = 0.0 if self._offset_target is None else self._offset_target + dt - first
        self._last_stream_t = float(stream_t[-1])
        return stream_t + self._offset

    def _update_suspenders(self, step: Step, chamber_c: float, chamber_sp: float) -> None:
        """Pause the step's clock while the PLL is unlocked or the chamber is out of its band."""
        reasons = self._recovery.suspender_reasons()
        if step.kind is not StepKind.LOCK and not self._last_locked:
            reasons.append("PLL unlocked")
        band = self.cfg.plan.chamber_band_c
        if step.kind is not StepKind.LOCK and math.isfinite(chamber_c) and abs(chamber_c - chamber_sp) > band:
            reasons.append(f"chamber {chamber_c:.2f} degC outside {chamber_sp:.2f} +- {band:g} degC")
        new = "; ".join(reasons)
        if new and not self._suspended:
            self._suspensions += 1
            self.clsf.hold(self._t - 1.0, math.inf)
            self._event("suspended", "", new)
        if not new and self._suspended:
            self.clsf.release_hold(self._t + self.cfg.clsf.hold_s)
            self._event("resumed", "", f"after: {self._suspended}", logging.INFO)
        self._suspended = new


def run_space_need(cfg: Config, path: Path, *, run_time_s: float, left_s: float) -> SpaceNeed:
    """The space a run of `cfg` at `path` still needs for `left_s` of run time (qmg_lab/storage/space.py): at the
    bytes per second its file shows over `run_time_s` of run time, or, before it holds data, at the layout's raw
    rate (every /lockin sample, /truth on the twins, a /clsf row per dither period, a /table and /chamber reading
    per lock-in block of at least 0.05 s)."""
    measured = measured_bytes_per_s(path, run_time_s)
    if measured is not None:
        return space_need(path, bytes_per_s=measured, left_s=left_s, measured=True)
    lk = cfg.lockin
    rows = {"lockin": lk.demod_rate_hz, "clsf": cfg.dither.frequency_hz, "table": 20.0, "chamber": 20.0}
    if lk.sim:
        rows["truth"] = lk.demod_rate_hz
    return space_need(path, bytes_per_s=raw_bytes_per_s(rows), left_s=left_s, measured=False)
