"""Instrument snapshots for the run file: who each instrument was and what it was doing (docs/hdf5.md).

`station_snapshots(cfg, station)` returns one JSON-serialisable document per instrument: the instrument's own
`snapshot()` (identity, firmware, settings, state) plus what the configuration says about it (real or twin,
address, driver). An instrument that cannot answer gets an `error` entry instead: a snapshot never stops a run.
"""

from __future__ import annotations

import logging
import time
from typing import Any

from qmg_lab.config.schema import Config
from qmg_lab.instruments import InstrumentError, Station

log = logging.getLogger(__name__)


def address(cfg: Config, name: str) -> str:
    """Where the configuration says the instrument is (its transport's address), or "twin"."""
    section = getattr(cfg, name)
    if section.sim:
        return "twin"
    if name == "lockin":
        return f"{section.host}:{section.port} {section.device}"
    if name == "generator":
        return f"{section.resource}{' ' + section.visa_backend if section.visa_backend else ''}"
    return str(section.port)


def instrument_snapshot(cfg: Config, name: str, instrument: Any) -> dict[str, Any]:
    """One instrument's snapshot document."""
    doc: dict[str, Any] = {
        "instrument": name,
        "simulated": bool(getattr(cfg, name).sim),
        "address": address(cfg, name),
        "driver": f"{type(instrument).__module__}.{type(instrument).__name__}",
        "taken_unix": time.time(),
    }
    try:
        doc.update(instrument.snapshot())
    except InstrumentError as exc:
        log.warning("snapshot of %s failed: %s", name, exc)
        doc["error"] = str(exc)
    return doc


def station_snapshots(cfg: Config, station: Station) -> dict[str, dict[str, Any]]:
    """A snapshot document for each of the four instruments."""
    return {name: instrument_snapshot(cfg, name, inst) for name, inst in station.instruments().items()}
