"""How a campaign ends other than completed: the exceptions the runner, its recovery policy and the CLI share."""

from __future__ import annotations


class CampaignAborted(RuntimeError):
    """The campaign stopped on an instrument fault; the station reached its safe state (exit code 3)."""


class CampaignInterrupted(RuntimeError):
    """Ctrl-C: the station reached its safe state (exit code 130)."""
