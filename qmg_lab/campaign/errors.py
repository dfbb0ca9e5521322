"""How a campaign ends other than completed: the exceptions the runner, its recovery policy and the CLI share."""

from __future__ import annotations

import signal


class CampaignAborted(RuntimeError):
    """The campaign stopped on an instrument fault; the station reached its safe state (exit code 3)."""


class CampaignInterrupted(RuntimeError):
    """A stop signal (Ctrl-C, SIGTERM, SIGHUP, SIGQUIT, SIGBREAK): the station reached its safe state; the process
    exits 128 + `signum` (130 for Ctrl-C)."""

    def __init__(self, reason: str, signum: int = int(signal.SIGINT)) -> None:
        super().__init__(reason)
        self.signum = int(signum)
