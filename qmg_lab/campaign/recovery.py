"""The recovery policy of a campaign: what happens when an instrument call fails (docs/reliability.md).

1. A call that raises InstrumentError is retried after the instrument's `reconnect()` (close, reopen, re-verify
   the identity, re-apply the settings), up to `recovery.reconnect_attempts` times at once.
2. If it still fails, and the instrument is not the lock-in (its stream is the clock) and the campaign is not
   finishing, the instrument is *being recovered*: a suspender holds the step's clock while the campaign keeps
   polling and logging the lock-in, and reconnect + the call are tried again after every block, for up to
   `recovery.timeout_s` of run time. Then the campaign aborts (CampaignAborted).
3. An interlock (InterlockError) is never retried: the hardware protected itself.

The safe state on the way out follows the same idea: each instrument, in SAFE_STATE_ORDER, is told to go safe;
one that refuses is reconnected and retried between lock-in blocks for up to `recovery.safe_state_timeout_s`.

The policy knows nothing of steps or files: the runner hands it a way to poll one more block (`poll_block`), the
run's clock (`run_time_s`) and its event log (`event`).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Mapping
from typing import TypeVar

from qmg_lab.campaign.errors import CampaignAborted
from qmg_lab.config.schema import RecoverySection
from qmg_lab.instruments import SAFE_STATE_ORDER, Instrument, InstrumentError, InterlockError

T = TypeVar("T")

EventLog = Callable[[str, str, str, int], None]
"""event(kind, instrument, message, logging level): one entry of the run's log."""


class RecoveryPolicy:
    """Bounded reconnect-and-retry of instrument calls, suspension while an instrument is recovered, and the
    retried safe state.

    instruments: the station's instruments by name; poll_interval_s: the length of one lock-in block (bounds the
    number of blocks a recovery may take); poll_block(): poll, log and process one more lock-in block;
    run_time_s(): the run's time of the last sample, s.
    """

    def __init__(
        self,
        settings: RecoverySection,
        instruments: Mapping[str, Instrument],
        *,
        poll_interval_s: float,
        poll_block: Callable[[], object],
        run_time_s: Callable[[], float],
        event: EventLog,
    ) -> None:
        self.settings = settings
        self.instruments = instruments
        self.poll_interval_s = poll_interval_s
        self._poll_block = poll_block
        self._run_time_s = run_time_s
        self._event = event
        self.finishing = False  # set when the campaign winds down: nothing is suspended any more
        self.reconnects = 0  # reconnect attempts made
        self.recoveries = 0  # calls that succeeded after a reconnect
        self._recovering: dict[str, str] = {}  # instrument -> why it is being recovered (a suspender)
        self._failed_reads: dict[str, tuple[Callable[[], object], InstrumentError]] = {}

    # ------------------------------------------------------------------ what the runner asks
    def suspender_reasons(self) -> list[str]:
        """Why the step's clock must wait on account of recoveries (empty: it need not)."""
        return list(self._recovering.values())

    def call(self, name: str, fn: Callable[[], T]) -> T:
        """fn(), an instrument call: on InstrumentError reconnect and retry (bounded); if it still fails, suspend
        and recover while logging (not the lock-in, and not while finishing: then InstrumentError)."""
        try:
            return self._attempt(name, fn)
        except InterlockError:
            raise
        except InstrumentError as exc:
            if name == "lockin" or self.finishing:
                raise InstrumentError(
                    f"{name}: {exc} (gave up after {self.settings.reconnect_attempts} reconnections)"
                ) from exc
            return self._recover(name, fn, exc)

    def read(self, name: str, fn: Callable[[], T]) -> T | None:
        """A reading inside a block: None while `name` is being recovered, or if it failed even after
        reconnecting (then `recover_failed_reads`, once the block is logged, recovers it)."""
        if name in self._recovering:
            return None
        try:
            return self._attempt(name, fn)
        except InterlockError:
            raise
        except InstrumentError as exc:
            if not self.finishing:
                self._failed_reads[name] = (fn, exc)
            return None

    def recover_failed_reads(self) -> None:
        """Recover the instruments whose reading failed in the block just logged (suspending meanwhile)."""
        if self.finishing:
            return
        failed, self._failed_reads = self._failed_reads, {}
        for name, (fn, exc) in failed.items():
            self._recover(name, fn, exc)

    def safe_state(self) -> list[str]:
        """Every instrument to its safe state in SAFE_STATE_ORDER, the lock-in last. One that refuses is
        reconnected and retried between lock-in blocks (the stream keeps the clock and the log running) for up
        to recovery.safe_state_timeout_s of run time. Returns what is still not confirmed."""
        *others, clock = SAFE_STATE_ORDER
        pending: dict[str, str] = {}
        for name in others:
            try:
                self.instruments[name].safe_state()
            except Exception as exc:
                pending[name] = str(exc)
        t0, budget = self._run_time_s(), self.settings.safe_state_timeout_s
        max_blocks, blocks = self._max_blocks(budget), 0
        while pending and self._run_time_s() - t0 < budget and blocks < max_blocks:
            try:
                self._recovering.update({n: f"{n} safe state pending" for n in pending})
                self._poll_block()
            except Exception:
                blocks = max_blocks  # the clock itself failed: one last try, then report
            blocks += 1
            for name in list(pending):
                self.reconnects += 1
                self._event("reconnect", name, f"safe state pending: {pending[name]}", logging.INFO)
                try:
                    self.instruments[name].reconnect()
                    self.instruments[name].safe_state()
                    del pending[name]
                except Exception as exc:
                    pending[name] = str(exc)
        self._recovering.clear()
        failures = [f"{n}: {e}" for n, e in pending.items()]
        try:
            self.instruments[clock].safe_state()
        except Exception as exc:
            failures.append(f"{clock}: {exc}")
        return failures

    # ------------------------------------------------------------------ the steps of a recovery
    def _max_blocks(self, budget_s: float) -> int:
        return math.ceil(budget_s / max(self.poll_interval_s, 1e-3)) + 1

    def _attempt(self, name: str, fn: Callable[[], T]) -> T:
        """fn(); on InstrumentError (not an interlock) up to recovery.reconnect_attempts x (reconnect, fn()).
        Raises the last InstrumentError if every try failed."""
        try:
            return fn()
        except InterlockError:
            raise
        except InstrumentError as exc:
            last = exc
            self._event("fault", name, str(exc), logging.WARNING)
        for _ in range(self.settings.reconnect_attempts):
            try:
                return self._reconnect_and_call(name, fn)
            except InterlockError:
                raise
            except InstrumentError as exc:
                last = exc
        raise last

    def _reconnect_and_call(self, name: str, fn: Callable[[], T]) -> T:
        """One recovery try: close, reopen and re-verify `name` (its driver's reconnect), then fn() again."""
        self.reconnects += 1
        self._event("reconnect", name, "closing, reopening and re-verifying the link", logging.INFO)
        try:
            self.instruments[name].reconnect()
            result = fn()
        except InstrumentError as exc:
            self._event("fault", name, f"after reconnecting: {exc}", logging.WARNING)
            raise
        self.recoveries += 1
        self._event("recovered", name, "the call succeeded after reconnecting", logging.INFO)
        return result

    def _recover(self, name: str, fn: Callable[[], T], exc: InstrumentError) -> T:
        """Suspend while `name` is recovered: keep polling and logging the lock-in; after each block reconnect
        and call fn() again. CampaignAborted after recovery.timeout_s of run time."""
        timeout = self.settings.timeout_s
        t0, blocks, max_blocks = self._run_time_s(), 0, self._max_blocks(timeout)
        self._recovering[name] = f"{name} being recovered ({exc})"
        try:
            while True:
                if self._run_time_s() - t0 >= timeout or blocks >= max_blocks:
                    raise CampaignAborted(f"{name} not recovered within recovery.timeout_s = {timeout:g} s: {exc}")
                self._poll_block()
                blocks += 1
                try:
                    return self._reconnect_and_call(name, fn)
                except InterlockError:
                    raise
                except InstrumentError as again:
                    exc = again
                    self._recovering[name] = f"{name} being recovered ({exc})"
        finally:
            self._recovering.pop(name, None)
